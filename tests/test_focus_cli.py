"""`benchctl focus` and the focus parts of `benchctl sim fault` and `benchctl devices`: one-line errors, --help."""

from __future__ import annotations

import pytest
from conftest import one_error_line

from benchctl.calibration.store import FOCUS_FILE, Calibration
from benchctl.cli import main
from benchctl.devices import discovery
from benchctl.devices.sim.state import load_state
from benchctl.profiles import load_profile
from benchctl.runner.device_commands import devices_found


def test_focus_commands_on_the_simulated_stage(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["focus", "home"]) == 0
    assert main(["focus", "move", "-5"]) == 2  # below home: the stage refuses
    assert main(["focus", "move", "1200"]) == 0
    out = capsys.readouterr().out
    assert "moved +1200 microstep(s); believed position 1200 microstep(s); the device reports 1200" in out
    assert main(["focus", "status"]) == 0
    out = capsys.readouterr().out
    assert "position: 1200 microstep(s)" in out and "not calibrated" in out


@pytest.mark.parametrize("argv, message", [
    (["focus", "go", "70mm"], "no focus calibration for this profile"),
    (["focus", "go", "seventy"], "depth 'seventy' not understood"),
    (["focus", "move", "10"], "no reference position (warning WR): home it first"),
    (["sim", "fault", "focus-stage", "melted"], "unknown fault 'melted'"),
])
def test_focus_mistakes_are_one_line(capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    assert message in one_error_line(capsys, argv)


def test_stage_faults_are_set_from_the_command_line() -> None:
    assert main(["sim", "fault", "focus-stage", "stall"]) == 0
    assert load_state("focus-stage")["faults"] == ["stall"]
    assert main(["focus", "home"]) == 2  # the carriage stalls half-way
    assert main(["sim", "fault", "focus-stage", "--clear"]) == 0 and load_state("focus-stage")["faults"] == []


def test_help_explains_the_focus_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["focus", "go", "--help"])
    out = capsys.readouterr().out
    assert "diopters" in out and "--channel" in out


def test_devices_lists_focus_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    found = discovery.Discovery(
        serial_ports=[discovery.SerialPortInfo("/dev/ttyUSB3", "Zaber X-LSM stage", "USB VID:PID=0403:6001"),
                      discovery.SerialPortInfo("/dev/ttyUSB0", "FT232R USB UART", "USB VID:PID=0403:6001")],
        cameras=[discovery.UsbCameraInfo("04a9:32a0", 1, 4, "Canon Inc.", "Canon EOS M10")])
    monkeypatch.setattr(discovery, "discover", lambda: found)
    lines = devices_found()
    focus = lines[lines.index("focus (a [focus] driver for each):") + 1:]
    assert focus == ["  /dev/ttyUSB3  Zaber X-LSM stage  (driver zaber)",
                     "  the lens of Canon EOS M10 04a9:32a0  (driver eos, with camera driver ptp)"]


def test_profile_check_and_run_check_the_focus_calibration_file(capsys: pytest.CaptureFixture[str]) -> None:
    folder = Calibration.store(load_profile("simulated")).folder
    folder.mkdir(parents=True, exist_ok=True)
    (folder / FOCUS_FILE).write_text('{"colours": {"green": {"focus": "zaber x", "coefficients": [70.0], '
                                     '"approach": 1, "backlash_steps": 0, "overshoot_steps": 1, '
                                     '"range_steps": [0, 1], "residual_mm": 0}}}')
    line = one_error_line(capsys, ["profile", "check"])
    assert "focus.json: colours.green.coefficients" in line
    assert "focus.json: colours.green.coefficients" in one_error_line(
        capsys, ["run", "procedures/focus_calibration.toml", "--dry-run"])
