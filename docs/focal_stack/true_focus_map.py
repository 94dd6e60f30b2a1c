"""Store the simulated stage's true focus map (its hidden [sim.focus] values) as aberrated-quarter's focus calibration,
for each colour: the target plane at start_steps, mm_per_step per step approached from below, backlash_steps of play.
docs/focal_stack/measure.sh runs it where the focus calibration stores no map on that bench (docs/focal_stack.md)."""

from benchctl.calibration.store import Calibration, calibration_root
from benchctl.capture.focus import FocusMap
from benchctl.profiles import load_profile

profile = load_profile("docs/focal_stack/aberrated-quarter.toml")
mechanics = profile.sim.focus
plane_mm = profile.section("optics").distance_mm
steps = [21000.0, 126000.0, 231000.0]
points = [(s, plane_mm + (s - mechanics.start_steps) * mechanics.mm_per_step) for s in steps]
calibration = Calibration(calibration_root() / profile.name, profile)
for channel in profile.channels:
    found = FocusMap.fit(points, approach=1, backlash_steps=mechanics.backlash_steps, repeatability_steps=0.0,
                         range_steps=(0.0, float(mechanics.range_steps)))
    print(channel.name, calibration.save_focus(channel.name, {**found.to_dict(), "unit": "microstep"}))
