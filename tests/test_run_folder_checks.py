"""A run folder has one writer, and what it keeps is checked before it is used again: a second `run --resume` of a
folder being written is refused naming the holder; a damaged CITL state is recomputed from the last good one (never
a traceback or advice that loops); a changed derived image sends the run back to the step that wrote it; an edited
calibration copy is refused on resume; a CITL run that diverges stops and a resume continues at half the rate."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_BENCH, truly_registered
from test_citl import ABERRATED
from test_citl import PROCEDURE as CITL
from test_procedures import CAPTURE as CAPTURE_TEST

from benchctl.cli import main
from benchctl.devices.errors import DeviceError
from benchctl.images import write_png
from benchctl.profiles import Profile
from benchctl.runner.builtin.citl.procedure import _save_state
from benchctl.runner.engine import run_procedure

pytestmark = pytest.mark.slow  # procedure runs: seconds each


@pytest.fixture
def profile(make_bench_profile: Callable[..., Profile]) -> Profile:
    return truly_registered(make_bench_profile(SMALL_BENCH, ABERRATED))


def events(folder: Path) -> list[dict]:
    return [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]


def done(folder: Path) -> dict[str, dict]:
    return {e["step"]: e["result"] for e in events(folder) if e["event"] == "done"}


def citl_cut_at_iteration_3(tmp_path: Path, profile: Profile, extra: str = "") -> Path:
    """A CITL run of 4 iterations whose camera cable is pulled at iteration 3's frame (the probe is frame 1):
    iterations 0-2 are done, the states of iterations 2 and 3 are on disk."""
    procedure = tmp_path / "citl.toml"
    procedure.write_text(CITL % (4, 0, "false") + extra)
    assert main(["sim", "fault", "sim-camera", "unplug_at=5"]) == 0
    with pytest.raises(DeviceError, match="cable pulled"):
        run_procedure(procedure, profile=str(profile.path), out=tmp_path / "runs", say=lambda line: None)
    assert main(["sim", "fault", "sim-camera", "--clear"]) == 0
    (folder,) = (tmp_path / "runs").iterdir()
    assert sorted(p.name for p in (folder / "state" / "green").iterdir()) == ["0002.npz", "0003.npz"]
    return folder


def _pickled(path: Path) -> None:
    buffer = io.BytesIO()
    np.savez(buffer, phase=np.array([{"not": "an array"}], dtype=object))
    path.write_bytes(buffer.getvalue())


DAMAGE: dict[str, Callable[[Path], None]] = {
    "truncated": lambda path: path.write_bytes(path.read_bytes()[:200]),
    "zero bytes": lambda path: path.write_bytes(b""),
    "wrong shape": lambda path: _save_state(path, __import__("torch").zeros(3, 5), None),
    "pickled": _pickled,
    "readable, other values": lambda path: _save_state(path, __import__("torch").full((64, 96), 0.5), None),
    "deleted": lambda path: path.unlink(),
}


def test_a_damaged_citl_state_is_recomputed_from_the_last_good_one(tmp_path: Path, profile: Profile) -> None:
    """Each kind of damage to the state iteration 3 starts from sends the resumed run back to iteration 2 (whose own
    state is good), which recomputes it; the run finishes, and a second resume has nothing left to do."""
    cut = citl_cut_at_iteration_3(tmp_path, profile)
    for name, damage in DAMAGE.items():
        folder = tmp_path / name.replace(" ", "-").replace(",", "")
        shutil.copytree(cut, folder)
        damage(folder / "state" / "green" / "0003.npz")
        said: list[str] = []
        outcome = run_procedure(None, resume=folder, say=said.append)
        assert outcome.ran[:2] == ["citl/green/0002", "citl/green/0003"], (name, outcome.ran)
        assert any("CITL green iteration 3: its state 0003.npz" in line and "step 'citl/green/0002' is done again"
                   in line for line in said), (name, said)
        log = [(e["event"], e["step"]) for e in events(folder)]
        assert ("invalid", "citl/green/0002") in log and log[-1] == ("done", "report"), name
        assert sorted(done(folder)) == sorted(done(cut) | {f"citl/green/{k:04d}": {} for k in (3, 4)}
                                              | {"report": {}}), name
        assert run_procedure(None, resume=folder, say=lambda line: None).ran == [], name


def test_both_states_damaged_go_back_to_the_start(tmp_path: Path, profile: Profile) -> None:
    folder = citl_cut_at_iteration_3(tmp_path, profile)
    for k in (2, 3):
        DAMAGE["truncated"](folder / "state" / "green" / f"{k:04d}.npz")
    outcome = run_procedure(None, resume=folder, say=lambda line: None)
    # the start redone, every step that finished after it is too (the probe included)
    assert outcome.ran[:6] == ["citl/green/start", "citl/green/probe", "citl/green/0000", "citl/green/0001",
                               "citl/green/0002", "citl/green/0003"], outcome.ran


def test_a_citl_run_that_diverges_stops_and_resumes_at_half_the_rate(tmp_path: Path, profile: Profile,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """learning_rate = 1 (the bound; 1e30 is refused before anything runs) makes iteration 1's capture 6.4 x worse
    than iteration 0's: the run stops with one line, and a resume goes back to iteration 0 at half the rate."""
    procedure = tmp_path / "citl.toml"
    procedure.write_text(CITL.replace("learning_rate = 0.05", "learning_rate = 1.0") % (3, 0, "false"))
    assert main(["run", str(procedure), "--profile", str(profile.path), "--out", str(tmp_path / "runs")]) == 2
    line = capsys.readouterr().err.splitlines()[-1]
    assert line.startswith("benchctl: error: CITL green diverged at iteration 1: captured loss ") and (
        "x iteration 0's" in line and "(learning_rate 1): the run stops; a resume continues from iteration 0's phase "
        "at half that rate, or start a new run with a lower learning_rate" in line), line
    (folder,) = (tmp_path / "runs").iterdir()
    first = done(folder)["citl/green/0000"]["learning_rate"]
    assert main(["run", "--resume", str(folder)]) == 0
    results = done(folder)
    assert first == 1.0 and results["citl/green/0000"]["learning_rate"] == 0.5
    assert results["citl/green/0001"]["loss"] < 4 * results["citl/green/0000"]["loss"]
    assert [(e["event"], e["step"]) for e in events(folder) if e["event"] in ("failed", "invalid")] == [
        ("failed", "citl/green/0001"), ("invalid", "citl/green/0000")]


# test_procedures' colour capture, green alone, one frame, the registration stored
CAPTURE = (CAPTURE_TEST.replace("[parameters]", '[parameters]\ncolours = ["green"]')
           .replace('setpoints = { red = "100%", green = "100%", blue = "100%" }', 'setpoints = { green = "2mW" }')
           .replace("frames = 2\ndark_frames = 1", "frames = 1\ndark_frames = 0")
           .replace('registration = "auto"', 'registration = "stored"'))


@pytest.fixture
def captured(tmp_path: Path, profile: Profile) -> Path:
    procedure = tmp_path / "capture.toml"
    procedure.write_text(CAPTURE)
    outcome = run_procedure(procedure, profile=str(profile.path), out=tmp_path / "runs", say=lambda line: None)
    assert outcome.folder is not None
    return outcome.folder


@pytest.mark.parametrize("damage", ["truncated", "deleted", "swapped"])
def test_a_damaged_derived_image_is_made_again_by_its_step(captured: Path, damage: str) -> None:
    """The merged capture the report embeds: truncated or deleted (the report step failed on every resume) or
    swapped for another image (used silently): a resume redoes the step that wrote it, then the report."""
    image = captured / "images" / "bars" / "capture.png"
    original = image.read_bytes()
    if damage == "truncated":
        image.write_bytes(original[:100])
    elif damage == "deleted":
        image.unlink()
    else:
        shutil.copy(captured / "images" / "bars" / "target.png", image)
    said: list[str] = []
    outcome = run_procedure(None, resume=captured, say=said.append)
    assert outcome.ran == ["process/bars", "report"], outcome.ran
    assert any(line.startswith("step 'process/bars': images/bars/capture.png") for line in said), said
    assert image.read_bytes() == original  # the same captures, processed again


def test_a_derived_file_damaged_while_the_run_goes_on_is_made_again_before_use(tmp_path: Path,
                                                                                profile: Profile) -> None:
    """Verified on use, not only on resume: the hologram the capture is to show, replaced after its step finished,
    sends the run back to the hologram step before the laser shows anything."""
    procedure = tmp_path / "capture.toml"
    procedure.write_text(CAPTURE)
    runs, said = tmp_path / "runs", []

    def say(line: str) -> None:
        said.append(line)
        first = [earlier for earlier in said if earlier.startswith("[2/4, ")] == [line]
        if first and "expose bars" in line:
            (hologram,) = runs.glob("*/holograms/bars-green.png")
            original.append(hologram.read_bytes())
            write_png(hologram, np.zeros((64, 96), np.uint8))

    original: list[bytes] = []
    outcome = run_procedure(procedure, profile=str(profile.path), out=runs, say=say)
    assert outcome.folder is not None
    assert any(line.startswith("      holograms/bars-green.png changed since it was written") and
               line.endswith("step 'hologram/bars/green' is done again") for line in said), said
    assert (outcome.folder / "holograms" / "bars-green.png").read_bytes() == original[0]
    log = [(e["event"], e["step"]) for e in events(outcome.folder)]
    assert log[:6] == [("start", "hologram/bars/green"), ("done", "hologram/bars/green"),
                       ("start", "capture/bars/green"), ("failed", "capture/bars/green"),
                       ("invalid", "hologram/bars/green"), ("start", "hologram/bars/green")]


def test_an_edited_calibration_copy_is_refused_on_resume(captured: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The red team edited the run's registration copy and the resumed report scored 13.0 dB instead of 18.1 without
    a word; now the resume is refused in one line naming the file."""
    copy = captured / "calibration" / "registration.json"
    data = json.loads(copy.read_text())
    data["colours"]["green"]["homography"][0][2] += 3.0
    copy.write_text(json.dumps(data))
    (captured / "images" / "bars" / "capture.png").unlink()  # something for the resume to do
    assert main(["run", "--resume", str(captured)]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"benchctl: error: {captured / 'calibration'}/registration.json changed since the run "
                           "wrote it (SHA-256 ") and "put that file back, or start a new run" in line, line


HOLD = textwrap.dedent("""\
    import sys
    from benchctl.devices.lock import set_command
    from benchctl.runner.record import run_folder_lock
    set_command("benchctl run")
    with run_folder_lock(sys.argv[1]):
        print("held", flush=True)
        sys.stdin.readline()
""")


def test_a_run_folder_has_one_writer(captured: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two `run --resume` of one folder both executed steps (duplicate `done` events); the second is now refused,
    told who holds it, and writes nothing; `runs remove --force` leaves it alone too."""
    (captured / "images" / "bars" / "capture.png").unlink()  # work for a resume to do
    log = (captured / "steps.jsonl").read_bytes()
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(captured)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        assert main(["run", "--resume", str(captured)]) == 2
        (line,) = capsys.readouterr().err.splitlines()
        assert line.startswith(f"benchctl: error: {captured}: this run is being written already, held by `benchctl "
                               f"run` (pid {holder.pid}) since "), line
        assert (captured / "steps.jsonl").read_bytes() == log
        # nor removed under its writer
        assert main(["runs", "remove", str(captured), "--yes", "--force", "--out", str(captured.parent)]) == 2
        assert "this run is being written already" in capsys.readouterr().err and captured.is_dir()
    finally:
        holder.communicate("\n", timeout=30)
    assert main(["run", "--resume", str(captured)]) == 0  # the holder gone, the resume runs
