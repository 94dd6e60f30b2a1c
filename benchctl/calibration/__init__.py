"""What was measured about a bench and how it applies: the calibration store per profile (`store`), its files
checked as they are read (`files`), the acceptance test a new calibration passes before it replaces one
(`acceptance`), each channel's optical setup (`setups`), profiles on other grids (`geometry`).

The face: `Calibrated` (the profile as calibrated, built once and passed down) and `Calibration` (one profile's
calibration files). It loads no torch: device commands build a `Calibrated` bench.
"""

from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.store import Calibration

__all__ = ["Calibrated", "Calibration"]
