"""The laser never surprises: `laser on` says the power it emits at (read back, next to the profile's setpoint), and a
run leaves every channel at the profile's setpoint however it ends (its automatic exposure may have chosen others)."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchctl.cli import main
from benchctl.devices.sim.state import load_state
from benchctl.errors import BenchctlError
from benchctl.runner.engine import run_procedure

SETS_POWER = """\
from benchctl.errors import BenchctlError
from benchctl.runner.api import Expose, Parameters, Step

DESCRIPTION = "sets green and blue as an automatic exposure would, then {ending}"
PARAMETERS = Parameters


def expose(context):
    context.instruments.laser.set_power("green", 0.0274)
    context.instruments.laser.set_power("blue", 0.03396)
    context.instruments.laser.set_emission("green", True)
    {ending}
    return {{}}


def plan(context):
    return [Step("expose", "expose", expose, (Expose("green", None, 1, 0),))]
"""


def setpoints_mw() -> dict[str, float]:
    """The simulated laser's setpoints (channel index -> mW) and that no channel emits."""
    channels = load_state("rgb-laser")["channels"]
    assert not any(channel["emission"] for channel in channels.values())
    return {index: round(channel["setpoint_w"] * 1e3, 6) for index, channel in channels.items()}


@pytest.mark.parametrize("ending, error", [
    ("pass", None),
    ("raise BenchctlError('the camera fell over')", BenchctlError),
    ("raise KeyboardInterrupt", KeyboardInterrupt),
])
def test_a_run_leaves_every_channel_at_the_profiles_setpoint(ending: str, error: type[BaseException] | None,
                                                             tmp_path: Path, small_profile_path: Path) -> None:
    procedure = tmp_path / "sets_power.py"
    procedure.write_text(SETS_POWER.format(ending=ending))
    said: list[str] = []
    run = lambda: run_procedure(procedure, profile=str(small_profile_path), out=tmp_path / "runs",  # noqa: E731
                                say=said.append)
    if error is None:
        run()
    else:
        with pytest.raises(error):
            run()
    assert setpoints_mw() == {"1": 40.0, "2": 2.0, "3": 2.0}  # the profile's 40 / 2 / 2 mW
    assert "laser: green setpoint back to the profile's 2 mW (the run left 27.4 mW)" in said
    assert "laser: blue setpoint back to the profile's 2 mW (the run left 33.96 mW)" in said


def test_laser_on_says_the_power_it_emits_at(capsys: pytest.CaptureFixture[str], small_profile_path: Path) -> None:
    p = str(small_profile_path)
    assert main(["laser", "set", "green", "27.4mW", "-p", p]) == 0
    assert main(["laser", "on", "green", "--for", "10ms", "-p", p]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("green: emission ON at 27.4 mW (read back; measured 27.4")
    assert out[1].endswith(" mW; 13.7x the profile's setpoint of 2 mW) for 0.01 s")
    assert main(["laser", "set", "green", "2mW", "-p", p]) == 0
    assert main(["laser", "on", "green", "--leave-on", "-p", p]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("green: emission ON at 2 mW (read back; measured 2.00")
    assert out[1].endswith(" mW) and LEFT ON after exit; `benchctl laser off green` turns it off")
    assert main(["laser", "off", "-p", p]) == 0
