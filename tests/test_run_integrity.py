"""Run records that can be trusted: every captured frame saw the SLM frame its step displayed, the step log
survives a crash at any byte, procedure code and captured files are checked before a resumed run reuses them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchctl.devices.errors import DeviceError
from benchctl.devices.sim.state import device_file, load_state, save_state
from benchctl.images import write_png
from benchctl.runner.engine import run_procedure

# One exposure step: a fixed gray frame, green alone, three RAW frames and one dark.
EXPOSE = """\
import numpy as np

from benchctl.runner.steps import EXPOSURE_PARAMETERS, channels, exposure_step, power_w

PARAMETERS = {**EXPOSURE_PARAMETERS}


def plan(context):
    green = [channel for channel in channels(context) if channel.name == "green"][0]
    frame = lambda context: np.full(context.profile.slm.shape, 100, np.uint8)
    return [exposure_step(context, "expose", ("expose",), green, power_w(context, green), frame, "expose",
                          frames=3, dark_frames=1)]
"""


@pytest.fixture
def expose_procedure(tmp_path: Path) -> Path:
    path = tmp_path / "expose.py"
    path.write_text(EXPOSE)
    return path


def _events(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]


def test_a_frame_that_saw_another_slm_frame_fails_the_step_and_resume_redoes_it(
        tmp_path: Path, bench_profile_path: Path, expose_procedure: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from benchctl.devices.camera import sim as sim_camera

    render = sim_camera.render_capture
    calls = []

    def render_then_change_the_slm(*args, **kwargs):
        """The second lit frame is captured after another program put a blank frame on the SLM."""
        calls.append(1)
        if len(calls) == 2:
            state = load_state("slm")
            write_png(device_file(f"slm-{state['frame'] + 1}.png"), np.zeros(state["shape"], np.uint8))
            save_state("slm", {**state, "frame": state["frame"] + 1, "file": f"slm-{state['frame'] + 1}.png"})
        return render(*args, **kwargs)

    monkeypatch.setattr(sim_camera, "render_capture", render_then_change_the_slm)
    with pytest.raises(DeviceError, match=r"frame-001.dng: captured while the SLM showed frame 2, not frame 1 that "
                                          r"this step displayed"):
        run_procedure(expose_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda _: None)
    (folder,) = (tmp_path / "runs").iterdir()
    assert [e["event"] for e in _events(folder)] == ["start", "failed"]
    assert not any(s.get("emission") for s in load_state("rgb-laser")["channels"].values())

    monkeypatch.setattr(sim_camera, "render_capture", render)
    outcome = run_procedure(None, resume=folder, say=lambda _: None)
    assert outcome.ran == ["expose"]
    done = _events(folder)[-1]
    assert done["event"] == "done" and done["result"]["slm_frame"] == 3
    assert done["result"]["slm_frames_seen"] == [3, 3, 3]
