"""Run records that can be trusted: every captured frame saw the SLM frame its step displayed, the step log
survives a crash at any byte, procedure code and captured files are checked before a resumed run reuses them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchctl.cli import main
from benchctl.devices.errors import DeviceError
from benchctl.devices.sim.state import device_file, load_state, save_state
from benchctl.images import write_png
from benchctl.runner.engine import run_procedure

# One exposure step: a fixed gray frame, green alone, three RAW frames and one dark.
EXPOSE = """\
import numpy as np

from benchctl.runner.api import ExposureParameters, channels, exposure_step, power_w

PARAMETERS = ExposureParameters


def plan(context):
    green = [channel for channel in channels(context) if channel.name == "green"][0]
    frame = lambda context: np.full(context.profile.slm.shape, 100, np.uint8)
    return [exposure_step(context, "expose", green, power_w(context, green), frame, "expose", frames=3,
                          dark_frames=1)]
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
    from benchctl.devices.sim import physics  # the simulated camera renders through this module

    render = physics.render_capture
    calls = []

    def render_then_change_the_slm(*args, **kwargs):
        """The second lit frame is captured after another program put a blank frame on the SLM."""
        calls.append(1)
        if len(calls) == 2:
            state = load_state("slm")
            write_png(device_file(f"slm-{state['frame'] + 1}.png"), np.zeros(state["shape"], np.uint8))
            save_state("slm", {**state, "frame": state["frame"] + 1, "file": f"slm-{state['frame'] + 1}.png"})
        return render(*args, **kwargs)

    monkeypatch.setattr(physics, "render_capture", render_then_change_the_slm)
    with pytest.raises(DeviceError, match=r"frame-001.dng: captured while the SLM showed frame 2, not frame 1 that "
                                          r"this step displayed"):
        run_procedure(expose_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda _: None)
    (folder,) = (tmp_path / "runs").iterdir()
    assert [e["event"] for e in _events(folder)] == ["start", "failed"]
    assert not any(s.get("emission") for s in load_state("rgb-laser")["channels"].values())

    monkeypatch.setattr(physics, "render_capture", render)
    outcome = run_procedure(None, resume=folder, allow_code=True, say=lambda _: None)
    assert outcome.ran == ["expose"]
    done = _events(folder)[-1]
    assert done["event"] == "done" and done["result"]["slm_frame"] == 3
    assert done["result"]["slm_frames_seen"] == [3, 3, 3]


def _finished_run(tmp_path: Path, procedure: Path, profile: Path) -> Path:
    outcome = run_procedure(procedure, profile=str(profile), out=tmp_path / "runs", say=lambda _: None)
    assert outcome.folder is not None
    return outcome.folder


def test_a_step_log_cut_at_any_byte_of_its_last_event_is_repaired_on_resume(tmp_path: Path) -> None:
    from benchctl.runner.record import create_run, open_run

    folder = create_run(tmp_path, "cut", {}, {}).folder
    record = open_run(folder)
    record.started("first")
    record.finished("first", 0.5, {"checksums": {}, "text": "caf\u00e9 \u2713"})
    log = (folder / "steps.jsonl").read_bytes()
    last = log[log.rindex(b"\n", 0, len(log) - 1) + 1:]
    head = log[:-len(last)]
    for cut in range(len(last)):  # every cut of the last event, up to the whole event without its newline
        (folder / "steps.jsonl").write_bytes(head + last[:cut])
        for aside in folder.glob("steps.jsonl.cut-*"):
            aside.unlink()
        record = open_run(folder)
        complete = cut == len(last) - 1
        assert record.is_done("first") == complete, cut
        record.started("next")  # the next event goes on its own line
        events = record.events()
        assert [e["event"] for e in events] == (["start", "done", "start"] if complete else ["start", "start"]), cut
        assert (folder / "steps.jsonl").read_bytes().startswith(head + (last if complete else b"")), cut
        cut_aside = sorted(folder.glob("steps.jsonl.cut-*"))
        assert [p.read_bytes() for p in cut_aside] == ([] if complete or cut == 0 else [last[:cut]]), cut
        assert open_run(folder).events() == events  # and every later resume reads it


def test_resume_refuses_a_changed_python_procedure(tmp_path: Path, bench_profile_path: Path,
                                                   expose_procedure: Path) -> None:
    from benchctl.errors import BenchctlError

    assert main(["sim", "fault", "sim-camera", "unplug_at=2"]) == 0
    with pytest.raises(DeviceError):
        run_procedure(expose_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda _: None)
    (folder,) = (tmp_path / "runs").iterdir()
    copy = folder / "expose.py"
    copy.write_text(copy.read_text() + "\nraise SystemExit('procedure code ran')\n")
    with pytest.raises(BenchctlError, match=r"expose.py changed since run .* started \(or is missing\); a resumed run "
                                            r"runs only the procedure code it started with"):
        run_procedure(None, resume=folder, allow_code=True, say=lambda _: None)


def test_a_corrupt_captured_frame_is_captured_again_on_resume_once(tmp_path: Path, bench_profile_path: Path,
                                                                    expose_procedure: Path) -> None:
    folder = _finished_run(tmp_path, expose_procedure, bench_profile_path)
    done = _events(folder)[-1]["result"]
    assert sorted(done["checksums"]) == ["raw/expose/dark-000.dng", "raw/expose/frame-000.dng",
                                         "raw/expose/frame-001.dng", "raw/expose/frame-002.dng"]
    frame = folder / "raw" / "expose" / "frame-001.dng"
    damaged = bytearray(frame.read_bytes())
    damaged[-100] ^= 0xFF  # one flipped byte in the image data
    frame.write_bytes(bytes(damaged))

    said: list[str] = []
    outcome = run_procedure(None, resume=folder, allow_code=True, say=said.append)
    assert outcome.ran == ["expose"]
    assert any("step 'expose': raw/expose/frame-001.dng changed since it was written" in line for line in said)
    assert (folder / "raw" / "expose.attempt-1" / "frame-001.dng").read_bytes() == bytes(damaged)  # kept aside
    assert run_procedure(None, resume=folder, allow_code=True, say=said.append).ran == []  # verified: nothing to redo


def test_a_full_disk_shows_the_first_error_and_the_resume_hint(tmp_path: Path, bench_profile_path: Path,
                                                               expose_procedure: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    import errno
    import os

    from benchctl import files

    real_fdopen = os.fdopen
    full = []

    def full_from_the_first_frame_on(fd, *args, **kwargs):
        """Atomic writes into the run folder fail with ENOSPC from the first RAW frame on (devices.json and
        run.json included)."""
        handle = real_fdopen(fd, *args, **kwargs)
        name = os.readlink(f"/proc/self/fd/{fd}")
        if name.startswith(str(tmp_path / "runs")) and (".frame-000.dng." in name or full):
            full.append(fd)

            def write(data):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            handle.write = write
        return handle

    monkeypatch.setattr(files.os, "fdopen", full_from_the_first_frame_on)
    code = main(["run", str(expose_procedure), "-p", str(bench_profile_path), "-o", str(tmp_path / "runs")])
    captured = capsys.readouterr()
    assert code == 2
    (error,) = captured.err.splitlines()
    assert error.startswith("benchctl: error: cannot write ") and error.endswith(
        "frame-000.dng: No space left on device"), error
    (folder,) = (tmp_path / "runs").iterdir()
    assert f"finish it with: benchctl run --resume {folder}" in captured.out
    assert "could not save devices.json" in captured.out


@pytest.mark.parametrize("frames, existing", [(1, "shot.dng"), (3, "shot-001.dng"), (1, "shot-000.dng")])
def test_camera_capture_never_replaces_a_file(tmp_path: Path, bench_profile_path: Path,
                                              capsys: pytest.CaptureFixture[str], frames: int, existing: str) -> None:
    (tmp_path / existing).write_bytes(b"an earlier capture")
    shutter = load_state("sim-camera").get("frame", 0)
    code = main(["camera", "capture", "-o", str(tmp_path / "shot.dng"), "-n", str(frames),
                 "-p", str(bench_profile_path)])
    assert code == 2
    assert capsys.readouterr().err == (f"benchctl: error: {tmp_path / existing} exists; captured files never replace "
                                       "one (choose another --output)\n")
    assert (tmp_path / existing).read_bytes() == b"an earlier capture"
    assert load_state("sim-camera").get("frame", 0) == shutter  # refused before the shutter
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".dng") == [existing]


def test_a_raw_file_is_never_replaced_by_the_camera(tmp_path: Path, bench_profile_path: Path) -> None:
    from benchctl.devices.camera import open_camera
    from benchctl.errors import BenchctlError
    from benchctl.profiles import load_profile

    (tmp_path / "frame-001.dng").write_bytes(b"kept")
    with open_camera(load_profile(bench_profile_path)) as camera:
        with pytest.raises(BenchctlError, match=r"frame-001.dng exists; it is kept as it is"):
            camera.capture(tmp_path, frames=2)
    assert (tmp_path / "frame-001.dng").read_bytes() == b"kept"
    assert (tmp_path / "frame-000.dng").read_bytes()[:2] in (b"II", b"MM")
    assert not list(tmp_path.glob(".*.tmp"))


def test_a_dry_run_of_python_code_says_the_code_ran_and_help_says_procedures_are_code(
        tmp_path: Path, bench_profile_path: Path, expose_procedure: Path, sim_state_dir: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    said: list[str] = []
    run_procedure(expose_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", dry_run=True,
                  say=said.append)
    assert said[-1] == ("dry run: benchctl opened no device and wrote nothing; the procedure's own code (expose.py) "
                        "ran to plan these steps, with your rights")
    assert not (tmp_path / "runs").exists() and list(sim_state_dir.iterdir()) == []
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "A .py procedure is code: running, dry-running or resuming it executes it with your rights" in help_text
    assert "(a .py procedure's own code still runs)" in help_text


EVIL = "from pathlib import Path\nPath(__file__).with_name('ran').write_text('code ran')\n"


def test_a_toml_procedure_runs_only_python_files_in_its_own_folder_after_allow_code(
        tmp_path: Path, bench_profile_path: Path, expose_procedure: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A TOML file is data: naming a .py elsewhere is refused even with --allow-code, and one beside it runs only with
    --allow-code. Before, `procedure = "/abs/evil.py"` was imported by a dry run."""
    from conftest import one_error_line

    outside = tmp_path / "x"
    outside.mkdir()
    (outside / "evil.py").write_text(EVIL)
    folder = tmp_path / "procedures"
    folder.mkdir()
    (folder / "linked.py").symlink_to(outside / "evil.py")
    toml = folder / "p.toml"
    for kind in (str(outside / "evil.py"), "../x/evil.py", "linked.py"):
        toml.write_text(f'procedure = "{kind}"\n')
        for flags in ([], ["--allow-code"]):
            line = one_error_line(capsys, ["run", str(toml), "-p", str(bench_profile_path), "--dry-run", *flags])
            assert line == (f"benchctl: error: {toml}: procedure: {kind!r} is outside the procedure file's folder "
                            f"{folder}: a TOML procedure names a built-in or a Python file in its own folder"), kind
    assert not (outside / "ran").exists()

    (folder / "expose.py").write_text(expose_procedure.read_text() + EVIL)
    toml.write_text('procedure = "expose.py"\n')
    line = one_error_line(capsys, ["run", str(toml), "-p", str(bench_profile_path), "--dry-run"])
    assert line == (f"benchctl: error: {toml}: procedure: 'expose.py' is Python code, which would run with your "
                    "rights: add --allow-code if you trust it")
    assert not (folder / "ran").exists()
    assert main(["run", str(toml), "-p", str(bench_profile_path), "--dry-run", "--allow-code"]) == 0
    assert (folder / "ran").read_text() == "code ran"


def test_resuming_a_python_procedure_needs_allow_code(tmp_path: Path, bench_profile_path: Path, expose_procedure: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A run folder may come from anywhere: its Python code runs on resume only with --allow-code."""
    from conftest import one_error_line

    assert main(["sim", "fault", "sim-camera", "unplug_at=2"]) == 0
    with pytest.raises(DeviceError):
        run_procedure(expose_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda _: None)
    (folder,) = (tmp_path / "runs").iterdir()
    line = one_error_line(capsys, ["run", "--resume", str(folder)])
    assert line == (f"benchctl: error: {folder}: this run's procedure is Python code (expose.py), which a resume runs "
                    "with your rights: add --allow-code if you trust it")
    assert main(["sim", "fault", "sim-camera", "--clear"]) == 0
    assert main(["run", "--resume", str(folder), "--allow-code"]) == 0


CRAFTED = [  # (file, change, the one line it gives)
    ("run.json", lambda d: [1], "run.json: (top level): expected a JSON object {...}, got list"),
    ("run.json", lambda d: {k: v for k, v in d.items() if k != "procedure_file"},
     "run.json: procedure_file: missing required key"),
    ("run.json", lambda d: {**d, "procedure_file": "../../x.py"},
     "run.json: procedure_file: '../../x.py' is not a file name of the run folder"),
    ("run.json", lambda d: {**d, "calibration_sha256": 5},
     "run.json: calibration_sha256: expected a table of strings, got 5 (int)"),
    ("run.json", lambda d: {**d, "profile_path": 5}, "run.json: profile_path: expected a string, got 5 (int)"),
    ("steps.jsonl", lambda e: [1], "steps.jsonl, line 2: (top level): expected a JSON object {...}, got list"),
    ("steps.jsonl", lambda e: {"event": "done"}, "steps.jsonl, line 2: step: missing: a step's event names its step"),
    ("steps.jsonl", lambda e: {**e, "step": [1]}, "steps.jsonl, line 2: step: expected a string, got [1] (list)"),
    ("steps.jsonl", lambda e: {**e, "result": 5}, "steps.jsonl, line 2: result: expected a [result] table, got 5"),
    ("steps.jsonl", lambda e: {**e, "result": {"checksums": {"../../etc/passwd": "0"}}},
     "steps.jsonl, line 2: result.checksums: '../../etc/passwd' is not a file inside the run folder"),
    ("steps.jsonl", lambda e: {**e, "attempt": "a"}, "steps.jsonl, line 2: attempt: expected an integer, got 'a'"),
]


def test_a_crafted_run_record_is_one_line_on_resume(tmp_path: Path, bench_profile_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Each case was a traceback (AttributeError, KeyError, TypeError, ValueError) or read a file outside the run
    folder."""
    import shutil

    from conftest import one_error_line

    toml = tmp_path / "p.toml"
    toml.write_text('procedure = "power-sweep"\n[parameters]\ncolours = ["green"]\nlevels = ["10%", "20%"]\n')
    finished = _finished_run(tmp_path, toml, bench_profile_path)
    for number, (name, change, message) in enumerate(CRAFTED):
        folder = shutil.copytree(finished, tmp_path / f"crafted-{number}")
        path = folder / name
        if name == "run.json":
            path.write_text(json.dumps(change(json.loads(path.read_text()))))
        else:
            events = [json.loads(line) for line in path.read_text().splitlines()]
            events[1] = change(events[1])
            path.write_text("".join(json.dumps(e) + "\n" for e in events))
        line = one_error_line(capsys, ["run", "--resume", str(folder)])
        assert line.startswith(f"benchctl: error: {folder}/{message}"), (line, message)
    # a well-formed log whose exposure result lacks what the report reads (the report's own lines removed)
    folder = shutil.copytree(finished, tmp_path / "crafted-result")
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    events = [{**e, "result": {"frames": 5}} if e["event"] == "done" and e["step"] == "sweep/green/0" else e
              for e in events if e.get("step") != "report"]
    (folder / "steps.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))
    assert one_error_line(capsys, ["run", "--resume", str(folder)]) == (
        f"benchctl: error: {folder}/steps.jsonl: step 'sweep/green/0': no 'folder' in its recorded result: the step "
        "log is damaged (start the run anew)")


def test_frames_left_in_a_steps_folder_are_set_aside_even_when_the_log_lost_its_start(
        tmp_path: Path, bench_profile_path: Path, expose_procedure: Path) -> None:
    """A log that lost a finished step's events (cut by hand, or restored from an old copy) left its RAW frames in
    place: the resume stopped with "frame-000.dng exists"; now they are set aside, kept, and captured again."""
    folder = _finished_run(tmp_path, expose_procedure, bench_profile_path)
    log = folder / "steps.jsonl"
    log.write_text("")
    before = (folder / "raw" / "expose" / "frame-000.dng").read_bytes()
    assert run_procedure(None, resume=folder, allow_code=True, say=lambda _: None).ran == ["expose"]
    assert (folder / "raw" / "expose.attempt-1" / "frame-000.dng").read_bytes() == before
    assert (folder / "raw" / "expose" / "frame-000.dng").is_file()
