"""A process that holds the laser with emission on and dies without Python's clean-up (SIGKILL, as the kernel's
out-of-memory killer sends it; a native crash, SIGSEGV) leaves emission off: the watchdog the laser started before
switching on connects through the same driver and port and switches it off (benchctl.devices.watchdog). The laser is
the simulated unit on sim://, whose state outlives the process (benchctl.devices.sim.state), as hardware's does."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from benchctl.devices.laser import open_laser
from benchctl.devices.sim.state import load_state
from benchctl.profiles import load_profile

HOLDER = """
import os, signal, sys, time
from benchctl.devices.laser import open_laser
from benchctl.profiles import load_profile

laser = open_laser(load_profile(sys.argv[1]))
laser.set_power("green", "2mW")
laser.set_emission("green", True)
print("emitting", flush=True)
if sys.argv[2] == "crash":
    os.kill(os.getpid(), signal.SIGSEGV)  # a native crash: no Python clean-up runs
time.sleep(120)
"""


def hold_and_die(profile: Path, how: str) -> tuple[int, str]:
    """Run a holder that switches green on, then crashes or is killed; its exit status and its stderr, which the
    watchdog shares (read to its end: the watchdog has then finished)."""
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(profile), how], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    assert holder.stdout is not None and holder.stdout.readline() == "emitting\n"
    assert load_state("rgb-laser")["channels"]["2"]["emission"] is True
    if how == "kill":
        holder.send_signal(signal.SIGKILL)
    _, stderr = holder.communicate(timeout=120)
    return holder.returncode, stderr


@pytest.mark.parametrize("how, status", [("kill", -signal.SIGKILL), ("crash", -signal.SIGSEGV)])
def test_a_holder_killed_or_crashed_with_emission_on_leaves_it_off(small_profile_path: Path, how: str,
                                                                    status: int) -> None:
    code, stderr = hold_and_die(small_profile_path, how)
    assert code == status
    assert load_state("rgb-laser")["channels"]["2"] == {"setpoint_w": pytest.approx(0.002), "emission": False}
    lines = [line for line in stderr.splitlines() if line.startswith("benchctl laser watchdog:")]
    assert len(lines) == 1 and lines[0].endswith("ended without switching it off; emission off on every channel "
                                                 "(green was emitting at 2 mW; switched off)"), stderr
    with open_laser(load_profile(small_profile_path), observe=True) as laser:
        assert not any(laser.emission(name) for name in laser.channel_names)


def test_an_orderly_close_disarms_the_watchdog(small_profile_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A plain close (emission off) and a `--leave-on` close end the watchdog without it touching the laser: the light
    left on stays on; a laser that never emitted has none."""
    profile = load_profile(small_profile_path)
    for leave_on in (False, True):
        with open_laser(profile, leave_on=leave_on) as laser:
            assert laser._watchdog is None
            laser.set_power("green", "2mW")
            laser.set_emission("green", True)
            watchdog = laser._watchdog
            assert watchdog is not None and watchdog._process.poll() is None
        assert watchdog._process.returncode == 0  # ended when told
        assert load_state("rgb-laser")["channels"]["2"]["emission"] is leave_on
    assert "watchdog" not in capfd.readouterr().err
    with open_laser(profile) as laser:
        assert laser.connect_report() == ["green was emitting at 2 mW; switched off"]
