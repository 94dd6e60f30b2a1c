"""The device commands start without torch, OpenCV or the networks: `benchctl laser off` must be instant.

Commands that write or read an image file (the simulated SLM's panel is a PNG) may load OpenCV, never torch.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchctl.devices.sim.slm import read_displayed
from benchctl.devices.slm import slm_for
from benchctl.images import write_png
from benchctl.profiles import load_profile

HEAVY = ("torch", "cv2", "benchctl.cgh", "benchctl.optics.propagation")
TORCH = ("torch", "benchctl.cgh", "benchctl.optics.propagation")
PROBE = """
import contextlib, io, json, sys
from benchctl.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
        code = main(sys.argv[1:])
    except SystemExit as exc:
        code = exc.code
print(json.dumps({"code": code, "loaded": [m for m in %r if m in sys.modules]}))
""" % (HEAVY,)


def _loaded(command: list[str]) -> list[str]:
    """Which of HEAVY `benchctl COMMAND` loaded, run in a fresh interpreter (it must succeed)."""
    done = subprocess.run([sys.executable, "-c", PROBE, *command], capture_output=True, text=True, timeout=120,
                          check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["code"] == 0, (command, done.stderr)
    return result["loaded"]


@pytest.mark.parametrize("command", [
    ["laser", "off"], ["laser", "status"], ["laser", "set", "green", "1mW"], ["camera", "info"],
    ["sim", "status"], ["sim", "fault", "sim-camera", "unplug_at=5"], ["devices"], ["--help"], ["laser", "--help"],
    ["slm", "info"], ["profile", "check"], ["profile", "check", "simulated-aberrated"], ["focus", "status"],
    ["focus", "home"], ["focus", "move", "0"],
])
def test_device_commands_never_import_torch(command: list[str]) -> None:
    assert _loaded(command) == [], command


def test_slm_frames_from_files_never_import_torch(tmp_path: Path) -> None:
    frame, phase = tmp_path / "frame.png", tmp_path / "phase.npy"
    write_png(frame, np.full((1088, 1920), 7, np.uint8))
    np.save(phase, np.linspace(-3 * np.pi, 3 * np.pi, 1088 * 1920, dtype=np.float32).reshape(1088, 1920))
    show_phase = ["slm", "show", str(phase), "--channel", "green", "--profile", "simulated"]  # a "sim" SLM driver
    for command in (["slm", "blank"], ["slm", "show", str(frame)], show_phase):
        assert [m for m in _loaded(command) if m in TORCH] == [], command
    shown, _ = read_displayed()
    assert np.array_equal(shown, slm_for(load_profile("simulated")).encode(np.load(phase), "green"))
