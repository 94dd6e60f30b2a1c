"""Calibration files (optical-model.json, registration.json, lut.json) are checked like profiles: a hand-edited or
damaged one is one line naming the file, the key and the value, wherever it is read, never a traceback or a
silently used wrong number; `profile check` and `run --dry-run` check every file a run would use."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import pytest
from conftest import one_error_line

from benchctl.calibration.files import OpticalModelFile, checked_json
from benchctl.calibration.setups import optical_setup
from benchctl.calibration.store import Calibration
from benchctl.cli import main
from benchctl.errors import BenchctlError
from benchctl.optics.fitted import FittedOptics
from benchctl.profiles import load_profile
from benchctl.runner.engine import run_procedure

FIT = {"zernike_waves": {"defocus": 0.2, "spherical": -0.05}, "waist_mm": 0.5, "offset_mm": [0.01, -0.02],
       "crosstalk_px": 0.05, "zero_order": 0.02, "residual": 0.2, "initial_residual": 0.6, "patterns": 4,
       "flat": True, "camera_blur_px": 0.4}


def stored_model(profile_path: Path) -> Path:
    """A valid optical-model.json for every channel in the profile's calibration store; returns its path."""
    store = Calibration.store(load_profile(profile_path))
    for colour in ("red", "green", "blue"):
        path = store.save_model(colour, FIT)
    return path


def edit(path: Path, change: Any) -> None:
    """Rewrite the JSON file at `path`: `change(data)` changes it in place (returning None), or returns what to write
    instead (a str as text, anything else as JSON)."""
    data = json.loads(path.read_text())
    out = change(data)
    path.write_text(out if isinstance(out, str) else json.dumps(data if out is None else out))


def without(key: str):
    return lambda entry: entry.__delitem__(key)


def green(key: str, value: Any):
    return lambda data: data["colours"]["green"].__setitem__(key, value)


def waves(term: str, value: Any):
    return lambda data: data["colours"]["green"]["zernike_waves"].__setitem__(term, value)


# The red team's malformed files (each gave AttributeError, AssertionError, ValueError, IndexError or TypeError
# before), values outside their range that were used, and what each must now say after "<file>: ".
MALFORMED = [
    (lambda data: [1, 2], "(top level): expected a JSON object {...}, got list"),
    (lambda data: data.__setitem__("colours", [1]), "colours: expected a table of [colours.<name>] tables, got [1]"),
    (lambda data: data["colours"].__setitem__("green", "x"),
     "colours.green: expected a [colours.green] table, got 'x' (str)"),
    (green("zernike_waves", [0.1]), "colours.green.zernike_waves: expected a table whose entries are each a finite "
                                    "number, got [0.1] (list)"),
    (green("waist_mm", "big"), "colours.green.waist_mm: expected a finite number, got 'big' (str)"),
    (green("waist_mm", None), "colours.green.waist_mm: expected a finite number, got None (NoneType)"),
    (green("offset_mm", [0.1]), "colours.green.offset_mm: expected two numbers [rows, cols], got [0.1] (list)"),
    (green("offset_mm", 3), "colours.green.offset_mm: expected two numbers [rows, cols], got 3 (int)"),
    (waves("coma", 0.1), "colours.green.zernike_waves.coma: unknown key"),
    (waves("defocus", "a"), "colours.green.zernike_waves.defocus: expected a finite number, got 'a' (str)"),
    (green("geometry", [1]), "colours.green.geometry: expected a table whose entries are each a string or"),
    (lambda data: "{not json", "not a JSON calibration file: Expecting property name"),
    (green("waist_mm", float("nan")), "colours.green.waist_mm: expected a finite number, got nan (float)"),
    (green("waist_mm", -3), "colours.green.waist_mm: must be >= 0, got -3.0"),
    (green("waist_mm", 1e-9), "colours.green.waist_mm: must be 0 (uniform light) or at least 0.08 mm (10 SLM pixels), "
                              "got 1e-09: a narrower beam lights almost none of the panel"),
    (green("crosstalk_px", -0.5), "colours.green.crosstalk_px: must be >= 0, got -0.5"),
    (green("zero_order", 1.0), "colours.green.zero_order: must be < 1, got 1.0"),
    (waves("defocus", 1e6), "colours.green.zernike_waves.defocus: must be <= 10, got 1000000.0"),
    (green("surprise", 1), "colours.green.surprise: unknown key"),
]


@pytest.mark.parametrize("change, message", MALFORMED, ids=[m.split(":")[0] for _, m in MALFORMED])
def test_a_malformed_optical_model_is_one_line_naming_file_key_and_value(
        change: Any, message: str, tmp_path: Path, small_profile_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    path = stored_model(small_profile_path)
    edit(path, change)
    line = one_error_line(capsys, ["generate", "chart:bars", "--colours", "green", "-o", str(tmp_path / "g"),
                                   "-p", str(small_profile_path)])
    assert line.startswith(f"benchctl: error: {path}: {message}")
    assert not (tmp_path / "g").exists()


def test_a_good_optical_model_is_used_as_stored(small_profile_path: Path) -> None:
    stored_model(small_profile_path)
    profile = Calibration.store(load_profile(small_profile_path)).applied(load_profile(small_profile_path))
    setup = optical_setup(profile, "green")
    assert setup.field_model == FittedOptics.from_dict(FIT)
    assert setup.field_model.waist_m == pytest.approx(0.5e-3) and dict(setup.field_model.zernike_waves) == {
        "defocus": 0.2, "spherical": -0.05}


def test_a_beam_that_misses_the_panel_is_refused(small_profile_path: Path) -> None:
    path = stored_model(small_profile_path)
    edit(path, lambda data: data["colours"]["green"].update(waist_mm=0.1, offset_mm=[50.0, 0.0]))
    profile = Calibration.store(load_profile(small_profile_path)).applied(load_profile(small_profile_path))
    with pytest.raises(BenchctlError, match=r"colours\.green\.offset_mm: a beam of waist 0.1 mm centred at "
                                            r"\[50.0, 0.0\] mm misses the 0.512 x 0.768 mm panel by 49.744 mm"):
        optical_setup(profile, "green")
    assert optical_setup(profile, "red").field_model is not None  # the other colours are fine


def test_a_model_the_profile_names_is_checked_too(tmp_path: Path, small_profile_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    model = tmp_path / "hand-made.json"
    model.write_text(json.dumps({"colours": {"green": {"zernike_waves": {"defocus": 0.1}, "waist_mm": -1}}}))
    profile = tmp_path / "with-model.toml"
    profile.write_text(small_profile_path.read_text().replace("roi = [48, 80]", 'roi = [48, 80]\nmodel = '
                                                              '"hand-made.json"'))
    line = one_error_line(capsys, ["profile", "check", str(profile)])
    assert line == f"benchctl: error: {model.resolve()}: colours.green.waist_mm: must be >= 0, got -1.0"
    model.write_text(json.dumps({"colours": {"green": {"zernike_waves": {"defocus": 0.1}}}}))
    assert main(["profile", "check", str(profile)]) == 0
    out = capsys.readouterr().out
    assert f"calibration: optical model {model.resolve()}: green: OK" in out


REGISTRATION = {"homography": [[2.0, 0.0, 10.0], [0.0, 2.0, 5.0], [0.0, 0.0, 1.0]], "rms_px": 0.3, "max_px": 0.9,
                "inliers": 240, "points": 252}


@pytest.mark.parametrize("change, message", [
    (lambda entry: entry.__setitem__("homography", [[1, 0], [0, 1]]),
     "colours.green.homography: expected 3 x 3 numbers, got [[1, 0], [0, 1]]"),
    (lambda entry: entry.__setitem__("rms_px", "x"), "colours.green.rms_px: expected a finite number, got 'x' (str)"),
    (lambda entry: entry.__setitem__("max_px", float("inf")),
     "colours.green.max_px: expected a finite number, got inf (float)"),
    (without("rms_px"), "colours.green.rms_px: missing required key"),
    (lambda entry: entry.__setitem__("inliers", 2.5), "colours.green.inliers: expected an integer, got 2.5 (float)"),
])
def test_profile_check_and_dry_run_check_every_calibration_file(
        change: Any, message: str, tmp_path: Path, bench_profile_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    stored_model(bench_profile_path)
    store = Calibration.store(load_profile(bench_profile_path))
    for colour in ("red", "green", "blue"):
        path = store.save_registration(colour, copy.deepcopy(REGISTRATION))
    procedure = tmp_path / "capture.toml"
    procedure.write_text('procedure = "colour-capture"\n[parameters]\nlut_calibration = "skip"\n')
    dry_run = ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"]
    assert main(["profile", "check", str(bench_profile_path)]) == 0
    assert main(dry_run) == 0
    out = capsys.readouterr().out
    for text in (f"calibration: optical model {store.folder / 'optical-model.json'}: red, green, blue: OK",
                 f"calibration: registration {path}: red, green, blue: OK"):
        assert out.count(text) == 2, text

    edit(path, lambda data: change(data["colours"]["green"]))
    for argv in (["profile", "check", str(bench_profile_path)], dry_run):
        assert one_error_line(capsys, argv) == f"benchctl: error: {path}: {message}", argv


def test_a_measured_lookup_table_and_its_index_are_checked(tmp_path: Path, bench_profile_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    store = Calibration.store(load_profile(bench_profile_path))
    table = store.lut_path("green")
    table.write_text("gray,phase_rad\n" + "".join(f"{g},{g * 0.0245}\n" for g in range(256)))
    store.record_lut("green", {"grays": 9})
    assert main(["profile", "check", str(bench_profile_path)]) == 0
    assert f"calibration: lookup table green: {table.resolve()}: OK" in capsys.readouterr().out
    table.write_text(table.read_text().replace("7,0.1715", "7,oops"))
    assert one_error_line(capsys, ["profile", "check", str(bench_profile_path)]) == (
        f"benchctl: error: {table.resolve()}: line 9: phase 'oops' is not a number")
    index = store.folder / "lut.json"
    edit(index, lambda data: without("file")(data["green"]))
    assert one_error_line(capsys, ["profile", "check", str(bench_profile_path)]) == (
        f"benchctl: error: {index}: green.file: missing required key")
    edit(index, lambda data: [data])
    assert checked_json(store.folder / "absent.json", OpticalModelFile) is None
    with pytest.raises(BenchctlError, match=r"lut.json: \(top level\): expected a JSON object \{...\}, got list"):
        store.lut_files()


NOTHING = """\
from benchctl.runner.procedure import Parameters, Step

DESCRIPTION = "one step that uses no device"
PARAMETERS = Parameters


def plan(context):
    return [Step("nothing", "nothing at all", lambda context: {"done": True})]
"""


def test_a_resumed_run_refuses_an_edited_calibration_copy(tmp_path: Path, small_profile_path: Path) -> None:
    stored_model(small_profile_path)
    procedure = tmp_path / "nothing.py"
    procedure.write_text(NOTHING)
    outcome = run_procedure(procedure, profile=str(small_profile_path), out=tmp_path / "runs", say=lambda _: None)
    assert outcome.folder is not None and outcome.ran == ["nothing"]
    copied = outcome.folder / "calibration" / "optical-model.json"
    edit(copied, green("crosstalk_px", -1))
    with pytest.raises(BenchctlError) as error:
        run_procedure(None, resume=outcome.folder, allow_code=True, say=lambda _: None)
    assert str(error.value).startswith(f"{copied} changed since the run wrote it (SHA-256 ")
    assert str(error.value).endswith("put that file back, or start a new run")


def test_a_meaningless_beam_is_refused_where_it_is_read_and_a_resume_takes_the_fixed_file(
        tmp_path: Path, bench_profile_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """`waist_mm = 1e-9` passed `profile check` and the dry run; a run then failed naming no file, and its resume
    failed the same way after the stored file was fixed (it kept using the run's copy)."""
    from benchctl.calibration import files

    path = stored_model(bench_profile_path)
    edit(path, green("waist_mm", 1e-9))
    message = (f"{path}: colours.green.waist_mm: must be 0 (uniform light) or at least 0.08 mm (10 SLM pixels), got "
               "1e-09: a narrower beam lights almost none of the panel")
    procedure = tmp_path / "nothing.py"
    procedure.write_text(NOTHING)
    p = str(bench_profile_path)
    for argv in (["profile", "check", p], ["run", str(procedure), "-p", p, "--dry-run"]):
        assert one_error_line(capsys, argv) == f"benchctl: error: {message}"
    # A run that started with it (as before this check: let through once), then resumed.
    with monkeypatch.context() as patch:
        patch.setattr(files, "waist_problem", lambda waist, slm: None)
        outcome = run_procedure(procedure, profile=p, out=tmp_path / "runs", say=lambda _: None)
    assert outcome.folder is not None
    copied = outcome.folder / "calibration" / "optical-model.json"
    with pytest.raises(BenchctlError) as error:
        run_procedure(None, resume=outcome.folder, allow_code=True, say=lambda _: None)
    assert str(error.value) == (f"{message.replace(str(path), str(copied))}; the store it came from fails too "
                                f"({message}): fix the file in {path.parent}, and a resume takes the calibration "
                                "from there")
    edit(path, green("waist_mm", 0.5))
    said: list[str] = []
    resumed = run_procedure(None, resume=outcome.folder, allow_code=True, say=said.append)
    assert resumed.ran == ["nothing"]  # done again: it may have used the bad model
    assert said[0] == (f"{message.replace(str(path), str(copied))}: this run's copy is kept as "
                       f"{outcome.folder / 'calibration.attempt-1'}; the run goes on with the fixed calibration from "
                       f"{path.parent} and does its 1 finished step(s) again")
    assert copied.read_bytes() == path.read_bytes()
    assert json.loads((outcome.folder / "calibration.attempt-1" / "optical-model.json").read_text())[
        "colours"]["green"]["waist_mm"] == 1e-9
    assert run_procedure(None, resume=outcome.folder, allow_code=True, say=said.append).ran == []  # and it holds


def test_training_through_a_malformed_model_file_is_one_line(tmp_path: Path, small_profile_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    model = tmp_path / "model.json"
    model.write_text(json.dumps({"colours": {"green": {"offset_mm": [0.1]}}}))
    line = one_error_line(capsys, ["train", "--method", "ccnn", "--data", "procedural:2", "--max-steps", "1",
                                   "--colours", "green", "--model-calibration", str(model), "-p",
                                   str(small_profile_path), "--out", str(tmp_path / "t")])
    assert line == (f"benchctl: error: {model.resolve()}: colours.green.offset_mm: expected two numbers [rows, cols], "
                    "got [0.1] (list)")
