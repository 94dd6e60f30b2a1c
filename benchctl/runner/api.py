"""The procedure API: everything a procedure uses, from one import (`from benchctl.runner.api import ...`).

A procedure (a built-in, or a user's Python file) defines

    DESCRIPTION = "one line"
    class PARAMETERS(ExposureParameters, kw_only=True):   # Parameters, or a shared group it derives from
        period_px: Annotated[float, msgspec.Meta(gt=2)] = 32.0
    def plan(context: Context) -> list[Step]: ...

`plan` validates and returns the steps without touching a device or writing a file (what --dry-run prints,
with every exposure the steps declare checked against the profile's limits). Each step does one resumable piece
of work and returns a JSON-ready result that later steps read with `context.result(key)`. The step builders
and savers place every file in the run folder; a procedure names its files, never the folders they go in.

- context: `Context` (profile, parameters, `Calibration`, optical setups, instruments), `Step`, `Expose`, `FocusAt`, and
  `StepRedo` (a step sends the run back to an earlier step whose work is damaged or diverged).
- parameters: `Parameters`, the shared groups `ExposureParameters` and `HologramParameters`, and the types
  `Frames`, `DarkFrames`, `RegistrationMode`, `ExposureMode`, `PeakGoal`, `ExposureCap`.
- planning: `channels`, `power_w` and `checked_power` (watts from a procedure's setting such as "1mW"),
  `unknown_setpoints`, `exposure_cap_w` with `unknown_caps` (automatic exposure's
  bound), `unregistered`, `check_method`, `carried`, `prepared_target`, `target_label`, `target_plane`,
  `focus_moves` (where the focus calibration puts a depth).
- holograms and steps: `compute_hologram`, `hologram_step`, `exposure_step`, `probe_step` with `probed_power`,
  `measure` (an exposure inside a step of one's own, decoded), `shown` and `displayed_frame` (what a hologram
  step kept).
- captures: `load_exposure`, `registered`, `registered_saturation`, `signal_stats`.
- files: `save_hologram`, `save_image`, `save_array` (each file's checksum joins the step's result), `load_image`,
  `load_array` (checked against it before use), `state_path`.
- calibration: `Verdict` (a new calibration's acceptance test), stored or kept by `Context.store_calibration`.
- reports: `Report` with the HTML helpers `table`, `figure`, `row` (figures side by side), `stepper` (a series
  stepped through with a slider), `line_plot`,
  `front_plot`, and the pictures `error_map` and `dots_over`.
"""

from benchctl.calibration.acceptance import AcceptMode, Verdict
from benchctl.calibration.store import Calibration
from benchctl.errors import BenchctlError
from benchctl.runner.auto_exposure import (
    ExposureCap,
    ExposureMode,
    PeakGoal,
    exposure_cap_w,
    probe_step,
    probed_power,
    signal_stats,
    unknown_caps,
)
from benchctl.runner.context import Context, Expose, FocusAt, Parameters, Step, StepRedo
from benchctl.runner.plots import ERROR_FULL_SCALE, dots_over, error_map, front_plot, line_plot
from benchctl.runner.report import Report, figure, row, stepper, table
from benchctl.runner.steps import (
    DarkFrames,
    ExposureParameters,
    Frames,
    HologramParameters,
    Measurement,
    RegistrationMode,
    carried,
    channels,
    check_method,
    checked_power,
    compute_hologram,
    displayed_frame,
    exposure_step,
    focus_moves,
    hologram_step,
    load_array,
    load_exposure,
    load_image,
    measure,
    power_w,
    prepared_target,
    registered,
    registered_saturation,
    save_array,
    save_hologram,
    save_image,
    shown,
    state_path,
    target_label,
    unknown_setpoints,
    unregistered,
)
from benchctl.targets import target_plane

__all__ = [
    "ERROR_FULL_SCALE",
    "AcceptMode",
    "BenchctlError",
    "Calibration",
    "Context",
    "DarkFrames",
    "Expose",
    "ExposureMode",
    "ExposureParameters",
    "FocusAt",
    "Frames",
    "HologramParameters",
    "Measurement",
    "Parameters",
    "PeakGoal",
    "ExposureCap",
    "RegistrationMode",
    "Report",
    "Step",
    "StepRedo",
    "carried",
    "channels",
    "checked_power",
    "check_method",
    "compute_hologram",
    "displayed_frame",
    "dots_over",
    "error_map",
    "exposure_cap_w",
    "exposure_step",
    "figure",
    "focus_moves",
    "front_plot",
    "hologram_step",
    "line_plot",
    "load_array",
    "load_exposure",
    "load_image",
    "measure",
    "power_w",
    "prepared_target",
    "probe_step",
    "probed_power",
    "registered",
    "registered_saturation",
    "row",
    "save_array",
    "save_hologram",
    "save_image",
    "shown",
    "signal_stats",
    "state_path",
    "stepper",
    "table",
    "target_label",
    "target_plane",
    "unknown_caps",
    "unknown_setpoints",
    "unregistered",
    "Verdict",
]
