"""A stored calibration is never replaced by a worse one: a new optical model, lookup table or registration is stored
only when it passes its acceptance test (signal, improvement on its start, a residual bound, no worse than the stored
one on the same captures); a failed one is kept beside the store and in the run, the old one stays, the run ends with
one error line (rc 2) and its report says so; `accept = "always"` stores it anyway. Learning rates are bounded, and
a fit that diverges is refused instead of a NaN traceback."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from conftest import SMALL_BENCH, truly_registered
from test_model_calibration import ABERRATED, HIDDEN, PROCEDURE, rendered

from benchctl.calibration.setups import optical_setup
from benchctl.calibration.store import Calibration
from benchctl.cli import main
from benchctl.optics.fitted import FitDiverged, FittedOptics, calibration_patterns, fit_optics, model_residual
from benchctl.profiles import Profile
from benchctl.runner.builtin import model_calibration

pytestmark = pytest.mark.slow  # procedure runs: seconds each


@pytest.fixture
def profile(make_bench_profile: Callable[..., Profile]) -> Profile:
    """The aberrated small bench (green) with its true registration stored."""
    return truly_registered(make_bench_profile(SMALL_BENCH, ABERRATED))


def run_cli(capsys: pytest.CaptureFixture[str], procedure: Path, profile: Profile, out: Path) -> tuple[int, str]:
    """`benchctl run`: its exit code and its last stderr line (progress lines come before it), never a traceback."""
    code = main(["run", str(procedure), "--profile", str(profile.path), "--out", str(out)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err.splitlines()[-1] if err else ""


def fit_results(out: Path) -> dict:
    (folder,) = out.iterdir()
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    return {event["step"]: event["result"] for event in events if event["event"] == "done"}


def test_captures_without_light_never_replace_a_good_model(tmp_path: Path, profile: Profile,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """The red team's case: light that never reached the camera (residual 0.999 -> 0.998) replaced a stored model
    of residual 0.20 with rc 0. Now the stored model stays, the new one is kept beside the store and in the run's
    calibration, the run ends with one error line, and the report shows both residuals and why."""
    store = Calibration.store(profile)
    good = FittedOptics(tuple(HIDDEN.items()), 0.5e-3, (0.05e-3, -0.08e-3))
    store.save_model("green", {**good.to_dict(), "residual": 0.2, "initial_residual": 0.58, "patterns": 3})
    before = (store.folder / "optical-model.json").read_bytes()
    procedure = tmp_path / "model.toml"
    procedure.write_text((PROCEDURE % "0.00001mW").replace("fit_steps = 90", "fit_steps = 20"))
    code, line = run_cli(capsys, procedure, profile, tmp_path / "runs")
    assert code == 2 and line.startswith("benchctl: error: green: new optical model not stored (no light reached "
                                         "the camera: the brightest 0.1 % of a capture at "), line
    assert "the stored one stays; the new one is kept as " in line and 'accept = "always"' in line
    assert (store.folder / "optical-model.json").read_bytes() == before
    (folder,) = (tmp_path / "runs").iterdir()
    kept = store.folder / "rejected" / f"{folder.name}-optical-model-green.json"
    candidate = json.loads(kept.read_text())
    assert candidate["acceptance"]["failures"][0].startswith("no light reached the camera")
    assert candidate["model"]["residual"] > 0.9
    assert (folder / "calibration" / "rejected" / kept.name).read_bytes() == kept.read_bytes()
    assert (folder / "calibration" / "optical-model.json").read_bytes() == before  # the copy the run used
    record = fit_results(tmp_path / "runs")["model/fit/green"]["calibration"]
    assert record["stored"] is False and record["new"] > 0.9 and record["old"] > 0.9  # both on these (dark) captures
    assert record["stored_fit_residual"] == 0.2 and record["signal"] < model_calibration.MIN_SIGNAL
    info = json.loads((folder / "run.json").read_text())
    assert info["stop"]["status"] == "finished" and info["stop"]["not_stored"][0].startswith("green: new optical")
    report = (folder / "report.html").read_text()
    assert "stored only if it passes its acceptance test" in report and "no light reached the camera" in report
    assert "<b>Warnings</b>" in report and "green: residual 1.000 -&gt; 0.998" not in report
    assert not list(store.folder.glob("*rejected*.json"))  # kept only in rejected/, which later runs do not copy


def test_a_fit_no_better_than_no_model_is_not_stored(tmp_path: Path, profile: Profile,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """learning_rate = 1.0 (the bound) leaves the fit no better than the ideal model, or makes it diverge, depending
    on the last bits of the arithmetic (measured: 0.587 -> 0.590, and divergence at step 11): either way, with nothing
    stored before, nothing is stored (the ideal model is what it would replace), and the run ends with rc 2."""
    procedure = tmp_path / "model.toml"
    procedure.write_text(PROCEDURE % "0.4mW" + "learning_rate = 1.0\n")
    code, line = run_cli(capsys, procedure, profile, tmp_path / "refused")
    assert code == 2 and line.startswith("benchctl: error: green: new optical model not stored (the fit "), line
    assert "the fit did not improve on the ideal model: " in line or "the fit diverged at step " in line
    assert not (Calibration.store(profile).folder / "optical-model.json").exists()
    refused = fit_results(tmp_path / "refused")["model/fit/green"]
    assert refused["calibration"]["stored"] is False and refused["calibration"]["replaces"] == "ideal model"


def test_patterns_without_points_are_refused_before_anything_runs(tmp_path: Path, profile: Profile,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """The red team's first calibration with patterns that held no points fitted defocus -0.19 waves (truth +0.30)
    and was stored; a spacing that leaves under MIN_POINTS points per pattern is refused by the dry run."""
    procedure = tmp_path / "model.toml"
    procedure.write_text(PROCEDURE % "0.4mW" + "spacing_px = 1000\n")
    code = main(["run", str(procedure), "--profile", str(profile.path), "--dry-run"])
    line = capsys.readouterr().err.splitlines()[-1]
    assert code == 2 and line == (f"benchctl: error: {procedure}: parameters.spacing_px: 1000 leaves about 0.00384 "
                                  "point(s) per pattern on the 48 x 80 ROI, too few to measure the wavefront (at least "
                                  "20): at most 13"), line


def test_a_fit_that_explains_only_its_own_captures_is_not_stored(tmp_path: Path, profile: Profile,
                                                                 capsys: pytest.CaptureFixture[str],
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """A fit claiming residual 0.60 -> 0.10 on its own captures with the defocus the red team's no-point patterns gave
    (-0.25 waves, truth +0.30) is judged on the held-out pattern: there it explains no more than the ideal model,
    so it is not stored (before, its own residual was all acceptance looked at). A pattern that focuses no point
    fails the verdict too."""
    from benchctl.optics.fitted import FitResult

    wrong = FittedOptics((("defocus", -0.25),))
    monkeypatch.setattr(model_calibration, "fit_optics", lambda *args, **kwargs: FitResult(wrong, 0.1, 0.6, [0.6, 0.1]))
    patterns = model_calibration.calibration_patterns

    def first_without_points(*args, **kwargs):  # the first fitted pattern (seed 0) focuses no point
        phases = patterns(*args, **kwargs)
        return torch.cat([torch.zeros_like(phases[:1]), phases[1:]]) if kwargs["seed"] == 0 else phases

    monkeypatch.setattr(model_calibration, "calibration_patterns", first_without_points)
    procedure = tmp_path / "model.toml"
    procedure.write_text(PROCEDURE % "0.4mW")
    code, line = run_cli(capsys, procedure, profile, tmp_path / "runs")
    assert code == 2 and line.startswith("benchctl: error: green: new optical model not stored (no information: "
                                         "calibration pattern(s) 1 focus no point (spacing_px 6); on the held-out "
                                         "capture(s) the fit explains no more than the ideal model: residual "), line
    record = fit_results(tmp_path / "runs")["model/fit/green"]["calibration"]
    assert record["measure"] == "held-out residual" and record["replaces"] == "ideal model" and record["held_out"] == 1
    assert record["new"] > model_calibration.MIN_IMPROVEMENT * record["old"] and record["fit_residual"] == 0.1
    assert not (Calibration.store(profile).folder / "optical-model.json").exists()


def test_accept_always_stores_a_calibration_that_fails_and_says_so(tmp_path: Path, profile: Profile,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "model.toml"
    procedure.write_text((PROCEDURE % "0.00001mW").replace("fit_steps = 90", "fit_steps = 20") + 'accept = "always"\n')
    code, _ = run_cli(capsys, procedure, profile, tmp_path / "forced")
    assert code == 0
    fit = fit_results(tmp_path / "forced")["model/fit/green"]
    assert fit["calibration"]["stored"] and fit["calibration"]["forced"]
    stored = json.loads((Calibration.store(profile).folder / "optical-model.json").read_text())["colours"]["green"]
    assert stored["residual"] == fit["residual"] > 0.9
    (folder,) = (tmp_path / "forced").iterdir()
    report = (folder / "report.html").read_text()
    assert "stored although it failed its acceptance test (accept = &quot;always&quot;): no light reached" in report
    assert "yes, forced" in report


def test_a_better_fit_replaces_the_stored_model_with_both_residuals_reported(
        tmp_path: Path, profile: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    """A stored model without the beam (worse than the truth) is replaced by the fit, whose residual is lower on the
    same captures; both residuals are in the step's result and the report."""
    store = Calibration.store(profile)
    store.save_model("green", {**FittedOptics(tuple(HIDDEN.items())).to_dict(), "residual": 0.3,
                               "initial_residual": 0.58, "patterns": 3})
    procedure = tmp_path / "model.toml"
    procedure.write_text(PROCEDURE % "0.4mW")
    code, _ = run_cli(capsys, procedure, profile, tmp_path / "runs")
    assert code == 0
    record = fit_results(tmp_path / "runs")["model/fit/green"]["calibration"]
    assert record["stored"] is True and record["new"] < 0.5 * record["old"], record  # on the held-out pattern
    stored = json.loads((store.folder / "optical-model.json").read_text())["colours"]["green"]
    assert stored["held_out_residual"] == record["new"] and stored["residual"] == record["fit_residual"]
    (folder,) = (tmp_path / "runs").iterdir()
    assert "stored only if it passes its acceptance test" in (folder / "report.html").read_text()


def test_the_residual_of_a_given_model_is_the_fits_own(make_bench_profile: Callable[..., Profile]) -> None:
    """model_residual of the fitted model (with the fit's camera blur) is the residual fit_optics reports, so the
    stored model and the new fit are compared on one scale."""
    profile = make_bench_profile(SMALL_BENCH, ABERRATED)
    setup = optical_setup(profile, "green")
    phases = calibration_patterns(setup.slm_propagator(), setup.roi, 2, seed=1)
    captured, shown = rendered(profile, phases)
    fit = fit_optics(setup.target_propagator(), setup.roi, shown, captured, iterations=30, learning_rate=0.03,
                     crosstalk=False)
    again = model_residual(setup.target_propagator(), setup.roi, shown, captured, fit.model,
                           camera_blur_px=fit.camera_blur_px)
    assert again == pytest.approx(fit.residual, rel=2e-3)
    ideal = model_residual(setup.target_propagator(), setup.roi, shown, captured, FittedOptics())
    assert ideal > 3 * fit.residual


def test_a_diverging_fit_stops_with_its_step_instead_of_a_nan_traceback(
        make_bench_profile: Callable[..., Profile]) -> None:
    """learning_rate 5 (the red team's >= 3) drove the fit's parameters to NaN, and the propagation then raised
    ValueError('field contains NaN or inf'); now the fit stops at the first non-finite loss and says where."""
    profile = make_bench_profile(SMALL_BENCH, ABERRATED)
    setup = optical_setup(profile, "green")
    phases = calibration_patterns(setup.slm_propagator(), setup.roi, 2, seed=1)
    captured, shown = rendered(profile, phases)
    diverged = r"the fit diverged at step \d+/40 \(its (loss became nan|model's field became non-finite)\)"
    with pytest.raises(FitDiverged, match=diverged) as caught:
        fit_optics(setup.target_propagator(), setup.roi, shown, captured, iterations=40, learning_rate=5.0)
    assert caught.value.step < 40 and all(torch.isfinite(torch.tensor(caught.value.losses)))


def test_a_diverged_fit_in_the_procedure_is_reported_and_not_stored(tmp_path: Path, profile: Profile,
                                                                    capsys: pytest.CaptureFixture[str],
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A fit that diverges within the bounded learning rate (forced here by running the real fit at 5) ends the
    run with one line that names the learning rate; the report is written; nothing is stored."""
    fit = model_calibration.fit_optics
    monkeypatch.setattr(model_calibration, "fit_optics", lambda *args, **kwargs: fit(*args, **{
        **kwargs, "learning_rate": 5.0}))
    procedure = tmp_path / "model.toml"
    procedure.write_text((PROCEDURE % "0.4mW").replace("fit_steps = 90", "fit_steps = 40"))
    code, line = run_cli(capsys, procedure, profile, tmp_path / "runs")
    assert code == 2 and "green: new optical model not stored (the fit diverged at step " in line, line
    assert "with learning_rate 0.03: lower it" in line
    assert not (Calibration.store(profile).folder / "optical-model.json").exists()
    (folder,) = (tmp_path / "runs").iterdir()
    assert "the fit diverged" in (folder / "report.html").read_text()


@pytest.mark.parametrize("procedure, value", [("model-calibration", "3.0"), ("citl", "1e30"),
                                              ("model-calibration", "0")])
def test_learning_rates_are_bounded_before_anything_runs(tmp_path: Path, profile: Profile, procedure: str, value: str,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(f'procedure = "{procedure}"\n[parameters]\nlearning_rate = {value}\n')
    code, line = run_cli(capsys, path, profile, tmp_path / "runs")
    assert code == 2 and str(path) in line and "learning_rate" in line, line
    assert ("<= 1" in line) if value != "0" else ("> 0" in line)
    assert not (tmp_path / "runs").exists()


LUT = """\
procedure = "lut-calibration"
[parameters]
colours = ["green"]
setpoints = { green = "%s" }
gray_step = 16
"""


def test_a_lookup_table_measured_without_light_keeps_the_stored_one(
        tmp_path: Path, make_bench_profile: Callable[..., Profile], capsys: pytest.CaptureFixture[str]) -> None:
    """A first table is measured and stored (on the gray levels it was not read from it beats the linear one: this
    bench's response is not linear); gratings without light then give no table: the stored one stays, the run says
    why in one line."""
    profile = truly_registered(make_bench_profile(SMALL_BENCH))
    procedure = tmp_path / "lut.toml"
    procedure.write_text(LUT % "2mW")
    code, _ = run_cli(capsys, procedure, profile, tmp_path / "first")
    assert code == 0
    first = fit_results(tmp_path / "first")["lut/green/fit"]["calibration"]
    assert first["stored"] and first["new"] < 0.1 * first["old"] and first["replaces"] == "linear table", first
    store = Calibration.store(profile)
    table = (store.folder / "lut-green.csv").read_bytes()

    procedure.write_text(LUT % "0.00001mW")
    code, line = run_cli(capsys, procedure, profile, tmp_path / "dark")
    assert code == 2 and line.startswith("benchctl: error: green: new lookup table not stored (no light reached the "
                                         "camera: the gray-0 grating's zero order at "), line
    assert "no table could be read: " in line
    assert (store.folder / "lut-green.csv").read_bytes() == table
    (folder,) = (tmp_path / "dark").iterdir()
    report = (folder / "report.html").read_text()
    assert "stored only if it passes its acceptance test" in report and "no table could be read" in report


def test_a_lookup_table_is_judged_on_gray_levels_it_was_not_read_from(tmp_path: Path, profile: Profile,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """On this bench green's true response is the linear table. A table read from every signal follows them by
    construction (misfit 0), so "no worse than before" could not fail and it replaced the linear table, said as
    "0.2942 (stored) -> 0 (new)" with nothing stored. Judged on the gray levels it was not read from, it is no better
    than the linear table, which stays; the line says what it was compared with."""
    procedure = tmp_path / "lut.toml"
    procedure.write_text(LUT % "2mW")
    code, line = run_cli(capsys, procedure, profile, tmp_path / "runs")
    assert code == 2 and line.startswith("benchctl: error: green: new lookup table not stored (held-out signal misfit "
                                         ), line
    assert "is above the linear table's " in line and "on the same captures); the linear table stays; " in line, line
    record = fit_results(tmp_path / "runs")["lut/green/fit"]["calibration"]
    assert record["replaces"] == "linear table" and 0 < record["old"] < record["new"] < 0.01, record
    assert not (Calibration.store(profile).folder / "lut-green.csv").exists()


def test_verdicts_say_what_they_compare_with() -> None:
    from benchctl.calibration.acceptance import Verdict, rejection_line

    first = Verdict("registration", "green", "median error px", 0.31, None)
    assert first.residuals() == "median error px 0.31 (new); nothing to compare with"
    table = Verdict("lookup table", "green", "held-out signal misfit", 0.004, 0.2942, replaces="linear table")
    assert table.residuals() == ("held-out signal misfit 0.004 (new) against 0.2942 (linear table), on the same "
                                 "captures")
    table.check(False, "a failure")
    assert rejection_line(table.record(False, [])) == ("green: new lookup table not stored (a failure); the linear "
                                                       "table stays")


REGISTRATION = """\
procedure = "registration"
[parameters]
colours = ["green"]
setpoints = { green = "2mW" }
max_rms_target_px = %s
"""


def test_a_refused_registration_keeps_the_stored_one_or_is_captured_again(
        tmp_path: Path, make_bench_profile: Callable[..., Profile], capsys: pytest.CaptureFixture[str]) -> None:
    """A fit above its RMS limit is not stored: with a stored registration that one stays (rc 2 once the run is
    done); without one the run stops and a resume captures the dots again (not the same refused fit forever)."""
    profile = truly_registered(make_bench_profile())  # the 128 x 192 bench: room for the dot grid
    store = Calibration.store(profile)
    before = (store.folder / "registration.json").read_bytes()
    procedure = tmp_path / "registration.toml"
    procedure.write_text(REGISTRATION % "0.0001")
    code, line = run_cli(capsys, procedure, profile, tmp_path / "kept")
    assert code == 2 and "green: new registration not stored (registration refused: " in line, line
    assert (store.folder / "registration.json").read_bytes() == before

    (store.folder / "registration.json").unlink()
    code, line = run_cli(capsys, procedure, profile, tmp_path / "none")
    assert code == 2 and "benchctl: error: green: registration refused: " in line, line
    (folder,) = (tmp_path / "none").iterdir()
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    assert [(e["event"], e["step"]) for e in events][-2:] == [("failed", "registration/fit/green"),
                                                             ("invalid", "registration/capture/green")]
    assert main(["run", "--resume", str(folder)]) == 2  # the run's own copy refuses the fit again, on a new capture
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    assert [(e["event"], e["step"]) for e in events][-5:] == [
        ("start", "registration/capture/green"), ("done", "registration/capture/green"),
        ("start", "registration/fit/green"), ("failed", "registration/fit/green"),
        ("invalid", "registration/capture/green")]
