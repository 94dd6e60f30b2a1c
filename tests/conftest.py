"""Shared fixtures: a small simulated bench so end-to-end tests run in seconds on a CPU."""

from __future__ import annotations

from pathlib import Path

import pytest

SMALL_PROFILE = """\
name = "small"
description = "scaled-down simulated bench for tests"

[optics]
distance_mm = 20.0
roi = [48, 80]

[slm]
width = 96
height = 64
pitch_um = 8.0
bit_depth = 8

[laser]
driver = "template"
port = "sim://rgb-laser"

[laser.protocol]
set_power = "CH{channel}:POW {mw:.2f}"
get_power = "CH{channel}:POW?"
get_measured = "CH{channel}:MEAS?"
enable = "CH{channel}:EMIT 1"
disable = "CH{channel}:EMIT 0"
get_emission = "CH{channel}:EMIT?"
get_status = "CH{channel}:STAT?"
identify = "*IDN?"

[[laser.channels]]
name = "red"
index = 1
wavelength_nm = 680
max_power_mw = 40
setpoint_mw = 40

[[laser.channels]]
name = "green"
index = 2
wavelength_nm = 520
max_power_mw = 40
setpoint_mw = 2

[[laser.channels]]
name = "blue"
index = 3
wavelength_nm = 450
max_power_mw = 40
setpoint_mw = 2
"""


@pytest.fixture
def small_profile_path(tmp_path: Path) -> Path:
    """A valid profile for a 64 x 96 SLM grid (ROI 48 x 80), 8 um pitch, 20 mm."""
    path = tmp_path / "small.toml"
    path.write_text(SMALL_PROFILE)
    return path


@pytest.fixture(autouse=True)
def sim_state_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Each test gets its own simulated-bench state folder, so tests never see each other's (or a user's) state."""
    folder = tmp_path_factory.mktemp("sim-state")
    monkeypatch.setenv("BENCHCTL_SIM_DIR", str(folder))
    return folder
