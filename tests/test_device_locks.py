"""One holder per device: a second command is told who holds the SLM, camera or laser; `laser off` reaches the
holder from another shell."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from benchctl.cli import main
from benchctl.devices.lock import DeviceHeld, DeviceLock, set_command
from benchctl.devices.sim.state import load_state
from benchctl.profiles import load_profile

BENCHCTL = [sys.executable, "-m", "benchctl"]


def test_a_second_holder_is_told_who_holds_the_lock(lock_dir: Path) -> None:
    set_command("benchctl run")
    with DeviceLock("slm:framebuffer:/dev/fb1", "SLM (framebuffer /dev/fb1)"):
        with pytest.raises(DeviceHeld) as caught:
            DeviceLock("slm:framebuffer:/dev/fb1", "SLM (framebuffer /dev/fb1)").acquire()
    assert str(caught.value).startswith(f"SLM (framebuffer /dev/fb1) busy: held by `benchctl run` (pid {os.getpid()}) "
                                        "since 20")
    assert caught.value.holder is not None and caught.value.holder.pid == os.getpid()
    DeviceLock("slm:framebuffer:/dev/fb1", "SLM").acquire().release()  # free again once released


@pytest.mark.slow
@pytest.mark.parametrize("command", [["slm", "blank"], ["camera", "capture", "-o", "x.dng"], ["laser", "status"],
                                     ["run", "PROCEDURE"]])
def test_commands_are_refused_while_another_holds_the_devices(tmp_path: Path, bench_profile_path: Path,
                                                              capsys: pytest.CaptureFixture[str],
                                                              command: list[str]) -> None:
    from benchctl.runner.instruments import Instruments

    procedure = tmp_path / "p.toml"
    procedure.write_text('procedure = "colour-capture"\n[parameters]\ntargets = ["chart:bars"]\n'
                         'registration = "auto"\nlut_calibration = "skip"\n')
    argv = [str(procedure) if word == "PROCEDURE" else word for word in command]
    set_command("benchctl run")
    with Instruments(load_profile(bench_profile_path)) as instruments:
        instruments.slm, instruments.camera, instruments.laser  # noqa: B018 (opening them is the point)
        shown = load_state("slm")
        assert main([*argv, "-p", str(bench_profile_path), *(["-o", str(tmp_path / "runs")] if "run" in argv
                                                               else [])]) == 2
        err = capsys.readouterr().err
        assert f"busy: held by `benchctl run` (pid {os.getpid()}) since" in err, err
        assert "Traceback" not in err
        assert load_state("slm") == shown  # the displayed frame is untouched
    assert not (tmp_path / "x.dng").exists()


def _start(argv: list[str], until: str) -> subprocess.Popen[str]:
    """A benchctl subprocess, once its standard output printed a line containing `until`."""
    proc = subprocess.Popen([*BENCHCTL, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=os.environ.copy())
    line = ""
    while until not in line:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        if not line and proc.poll() is not None:
            raise AssertionError(f"{argv} exited {proc.returncode}: {proc.stderr.read()}")  # type: ignore[union-attr]
    return proc


def test_laser_off_from_another_shell_stops_the_holder(small_profile_path: Path) -> None:
    holder = _start(["laser", "on", "green", "-p", str(small_profile_path)], until="emission ON")
    try:
        assert load_state("rgb-laser")["channels"]["2"]["emission"] is True
        off = subprocess.run([*BENCHCTL, "laser", "off", "-p", str(small_profile_path)], capture_output=True,
                             text=True, timeout=120)
        assert off.returncode == 0, off.stderr
        assert f"was held by `benchctl laser on` (pid {holder.pid}) since" in off.stdout
        assert "sent it SIGTERM" in off.stdout and "green: emission off" in off.stdout
        assert holder.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        if holder.poll() is None:
            holder.kill()
    assert not any(channel["emission"] for channel in load_state("rgb-laser")["channels"].values())


def test_laser_off_says_emission_is_unknown_when_the_holder_does_not_let_go(small_profile_path: Path) -> None:
    from benchctl.devices.errors import EmissionNotOff
    from benchctl.devices.laser.base import port_lock
    from benchctl.runner.device_commands import laser_off

    # A holder that ignores SIGTERM: a child process holding the port's lock with the signal ignored.
    script = ("import signal, sys, time\nsignal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
              "from benchctl.devices.lock import DeviceLock, set_command\nset_command('stubborn')\n"
              "held = DeviceLock(sys.argv[1], 'laser').acquire()\nprint('held', flush=True)\ntime.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", script, port_lock("sim://rgb-laser").key], stdout=subprocess.PIPE,
                            text=True, env=os.environ.copy())
    try:
        assert proc.stdout.readline().strip() == "held"  # type: ignore[union-attr]
        with pytest.raises(EmissionNotOff, match=r"`stubborn` \(pid \d+\) still holds it 0.2 s after SIGTERM; "
                                                 "emission state UNKNOWN, possibly ON: use the key switch / interlock"):
            laser_off(load_profile(small_profile_path), "all", wait_s=0.2)
    finally:
        proc.kill()
        proc.wait()
    assert port_lock("sim://rgb-laser").wait_free(30)  # the kernel drops a killed holder's lock
