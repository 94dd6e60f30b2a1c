"""The genicam driver against Aravis's fake GigE Vision camera on loopback (`arv-fake-gv-camera-0.8 -i 127.0.0.1`):
discovery, streaming, injected packet loss, and the camera killed in the middle of a run.

Each scenario runs in tests/gigevision.py inside a network namespace with loopback only (`unshare -rn`), so GigE
Vision discovery broadcasts reach no other machine."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from conftest import SMALL_PROFILE

SCENARIOS = Path(__file__).with_name("gigevision.py")
pytestmark = [pytest.mark.third_party,
              pytest.mark.skipif(shutil.which("arv-fake-gv-camera-0.8") is None,
                                 reason="needs Debian's aravis-tools (.ci/run installs it)")]


def scenario(name: str, **args: Any) -> dict[str, Any]:
    """Run scenario `name` of tests/gigevision.py in a network namespace of its own; its JSON result."""
    command = f"ip link set lo up && exec {sys.executable} {SCENARIOS} {name} '{json.dumps(args)}'"
    done = subprocess.run(["unshare", "--net", "--map-root-user", "sh", "-c", command], capture_output=True,
                          text=True, timeout=280)
    assert done.returncode == 0, done.stderr[-3000:]
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def test_discovery_and_streaming() -> None:
    result = scenario("streaming", lost_per_thousand=0, frames=5, frame_retries=2, image_timeout_s=5.0)
    assert result["found"] == [["Aravis-Fake-GV01", "GV01", "GigEVision", "127.0.0.1"]]
    assert result["error"] is None and result["kept_exact"] == [True] * 5


def test_lost_packets_give_retried_frames_never_incomplete_ones() -> None:
    """20 % of the stream's packets dropped: frames that lost some are re-triggered; every frame kept is exact."""
    result = scenario("streaming", lost_per_thousand=200, frames=12, frame_retries=20, image_timeout_s=1.0)
    assert result["error"] is None, result["error"]
    assert result["kept_exact"] == [True] * 12
    assert result["refused"], "no frame lost a packet at 20 % loss"


def test_a_frame_that_never_arrives_whole_is_refused_in_one_line() -> None:
    result = scenario("streaming", lost_per_thousand=1000, frames=1, frame_retries=1, image_timeout_s=1.0)
    assert result["kept_exact"] == []
    assert result["error"] == ("DeviceTimeout: Aravis Fake (serial GV01) delivered no frame within 1.01 s of each of 2 "
                               "software triggers: camera off, cable pulled or network down (camera.image_timeout_s)")


@pytest.mark.slow
def test_camera_killed_mid_run_then_resumed(tmp_path: Path) -> None:
    profile = tmp_path / "gige.toml"
    profile.write_text(SMALL_PROFILE.replace('name = "small"', 'name = "gige"').replace(
        "pitch_um = 8.0", "pitch_um = 8.0\nsettle_ms = 300") + """
[camera]
driver = "genicam"
device_id = "127.0.0.1"
pixel_format = "BayerGR8"
region = [0, 0, 64, 48]
image_timeout_s = 1.0
frame_retries = 1
""")
    procedure = tmp_path / "sweep.toml"
    procedure.write_text('name = "sweep"\nprocedure = "power-sweep"\n\n[parameters]\ncolours = ["green"]\n'
                         'levels = ["10%", "20%", "30%"]\nframes = 1\n')
    result = scenario("killed_run", profile=str(profile), procedure=str(procedure), out=str(tmp_path / "runs"))
    assert result["code"] == 2
    assert result["stderr"] == ["benchctl: error: Aravis Fake (serial GV01): software trigger failed: "
                                "[TriggerSoftware] [TriggerSoftwareCommandRegister] GigEVision write_register timeout"]
    assert "emission off" in result["laser_status"] and "emission ON" not in result["laser_status"]
    assert result["first_files"] and result["unchanged"] == result["first_files"]
    assert result["resumed_code"] == 0, result["resumed_stderr"]
    assert result["started"].count("sweep/green/0") == 1  # done before the camera died: not captured again
    assert result["started"].count("sweep/green/1") == 2  # the step it died in: captured again on resume
    assert result["done"].count("sweep/green/1") == 1 and "report" in result["done"]
