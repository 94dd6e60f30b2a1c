"""The device commands start without torch, OpenCV or the networks: `benchctl laser off` must be instant."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("torch", "cv2", "benchctl.cgh", "benchctl.optics")
PROBE = """
import contextlib, io, json, sys
from benchctl.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
        code = main(sys.argv[1:])
    except SystemExit as exc:
        code = exc.code
print(json.dumps({"code": code, "heavy": [m for m in %r if m in sys.modules]}))
""" % (HEAVY,)


@pytest.mark.parametrize("command", [
    ["laser", "off"], ["laser", "status"], ["laser", "set", "green", "1mW"], ["camera", "info"],
    ["sim", "status"], ["sim", "fault", "sim-camera", "unplug_at=5"], ["devices"], ["--help"], ["laser", "--help"],
])
def test_device_commands_never_import_torch(command: list[str]) -> None:
    done = subprocess.run([sys.executable, "-c", PROBE, *command], capture_output=True, text=True, timeout=120,
                          check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["code"] == 0, (command, done.stderr)
    assert result["heavy"] == [], command
