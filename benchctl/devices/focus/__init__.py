"""The camera's focus: the `Focus` interface and its drivers (benchctl.drivers lists them), chosen by `driver` in the
profile's [focus] section.

    with open_focus(profile) as focus:
        focus.home()
        focus.move_to(1200, approach=+1, overshoot=400)   # arrive moving up, past the backlash
"""

from __future__ import annotations

from benchctl.devices.camera import Camera
from benchctl.devices.focus.base import Focus, FocusMove
from benchctl.drivers import driver_class
from benchctl.profiles import Profile

__all__ = ["Focus", "FocusMove", "focus_for", "open_focus"]


def focus_for(profile: Profile) -> Focus:
    """The profile's focus driver, not yet connected."""
    driver: type[Focus] = driver_class("focus", profile.section("focus").driver)
    return driver.for_profile(profile)


def open_focus(profile: Profile, camera: Camera | None = None) -> Focus:
    """The profile's focus, opened (use it as a context manager so it is closed again). `camera`: the profile's
    camera, open and kept open by its holder (a run, the console): an EOS lens is driven through it instead of
    opening the body a second time."""
    from benchctl.devices.camera.ptp_camera import PtpCamera
    from benchctl.devices.focus.eos import EosFocus

    config = profile.section("focus")
    if config.driver == "eos" and isinstance(camera, PtpCamera):
        return EosFocus.on_camera(config, camera).open()
    return focus_for(profile).open()
