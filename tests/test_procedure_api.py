"""The procedure API (`benchctl.runner.api`): one import is enough to write a procedure, the run-folder layout
is benchctl's alone, and every exposure a step makes is declared, checked against the profile and enforced."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest
from conftest import one_error_line, truly_registered

from benchctl.calibration.store import Calibration
from benchctl.devices.sim import physics
from benchctl.devices.sim.state import load_state
from benchctl.errors import BenchctlError
from benchctl.profiles import load_profile
from benchctl.runner import layout
from benchctl.runner.engine import run_procedure

REPO = Path(__file__).resolve().parents[1]
PROCEDURE_FILES = sorted((REPO / "benchctl" / "runner" / "builtin").rglob("*.py")) + [
    REPO / "procedures" / "grating_shift.py"]

# A step that declares green at 1 mW and then tries more, or another colour.
UNDECLARED = """\
import numpy as np

from benchctl.runner.api import Expose, ExposureParameters, Step, channels, measure

PARAMETERS = ExposureParameters


def plan(context):
    green, red, blue = (next(c for c in channels(context) if c.name == name) for name in ("green", "red", "blue"))

    def action(context):
        frame = np.zeros(context.profile.slm.shape, np.uint8)
        return measure(context, %s, %s, frame, frames=1, dark_frames=0).record

    return [Step("expose", "expose", action, (Expose("green", 1e-3, 1, 0), Expose("red", None, 1, 0)))]
"""

# A plan that declares red above its max_power_mw (40 mW on the test bench).
TOO_BRIGHT = """\
from benchctl.runner.api import Expose, ExposureParameters, Step

PARAMETERS = ExposureParameters


def plan(context):
    return [Step("blinding", "too bright", lambda context: {}, (Expose("red", 0.05, 1, 0),))]
"""


def _benchctl_imports(path: Path) -> list[str]:
    """The benchctl modules a file imports (`from X import` and `import X`)."""
    modules = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("benchctl"):
            modules.append(node.module)
        elif isinstance(node, ast.Import):
            modules += [alias.name for alias in node.names if alias.name.startswith("benchctl")]
    return modules


@pytest.mark.parametrize("path", PROCEDURE_FILES, ids=lambda p: p.name if p.parent.name != "citl" else f"citl/{p.name}")
def test_procedures_use_only_the_front_door_of_the_runner(path: Path) -> None:
    runner = [m for m in _benchctl_imports(path) if m.startswith("benchctl.runner")]
    allowed = {"benchctl.runner.api", "benchctl.runner.builtin"} | {  # built-ins building on built-ins
        f"benchctl.runner.builtin.{name}" for name in ("citl.report",)}
    assert set(runner) <= allowed, (path, runner)


def test_the_example_imports_benchctl_once() -> None:
    assert _benchctl_imports(REPO / "procedures" / "grating_shift.py") == ["benchctl.runner.api"]


@pytest.mark.parametrize("path", [*PROCEDURE_FILES, *sorted((REPO / "benchctl" / "runner").glob("*.py"))],
                         ids=lambda p: p.name)
def test_only_the_layout_module_spells_the_run_folders(path: Path) -> None:
    if path.name == "layout.py":
        return
    spelt = re.findall(r"""(?<!\[)["'](?:raw|holograms|images|state)(?:/|["'])""", path.read_text())
    assert spelt == [], path


def test_the_readme_example_runs(tmp_path: Path, make_bench_profile, capsys: pytest.CaptureFixture[str]) -> None:
    """The procedure the README shows, run as it is on a bench with a stored registration for each colour, then from
    a TOML file that gives its list parameter and its power in mW; a list default is one line that says what to write
    instead (it was msgspec's own TypeError)."""
    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("### Writing a procedure"):]
    code = section[section.index("```python") + len("```python"):section.index("```", section.index("```python") + 9)]
    (tmp_path / "flat.py").write_text(code)
    profile = make_bench_profile()
    for colour in ("red", "green", "blue"):
        Calibration.store(profile).save_registration(colour, {"homography": physics.camera_homography(profile).tolist(),
                                                              "rms_px": 0.0})
    outcome = run_procedure(tmp_path / "flat.py", profile=str(profile.path), out=tmp_path / "runs",
                            say=lambda _: None)
    assert outcome.folder is not None and outcome.ran[-1] == "report" and outcome.headline == ["6 flat frames"]
    metrics = json.loads((outcome.folder / layout.METRICS_JSON).read_text())
    assert [(row["colour"], row["gray"]) for row in metrics["rows"]] == [
        (colour, gray) for colour in ("red", "green", "blue") for gray in (64, 192)]
    assert all(row["mean"] > 0.005 for row in metrics["rows"]), metrics
    assert (outcome.folder / layout.raw_folder("flat/green/64") / "frame-000.dng").is_file()
    assert "Flat frames" in (outcome.folder / layout.REPORT).read_text()

    toml = tmp_path / "flat.toml"
    toml.write_text('procedure = "flat.py"\n[parameters]\ncolours = ["green"]\ngrays = [100]\npower = "2mW"\n')
    outcome = run_procedure(toml, profile=str(profile.path), out=tmp_path / "runs", allow_code=True,
                            say=lambda _: None)
    assert outcome.ran == ["flat/green/100", "report"]
    assert outcome.folder is not None
    events = [json.loads(line) for line in (outcome.folder / "steps.jsonl").read_text().splitlines()]
    assert next(e for e in events if e["event"] == "done")["result"]["setpoint_w"] == pytest.approx(2e-3)
    toml.write_text('procedure = "flat.py"\n[parameters]\npower = "2"\n')
    line = one_error_line(capsys, ["run", str(toml), "-p", str(profile.path), "--dry-run", "--allow-code"])
    assert line.startswith(f"benchctl: error: {toml}: parameters.power: power '2' has no unit (W, mW or %?)"), line
    (tmp_path / "flat.py").write_text(code.replace("tuple[int, ...] = (64, 192)", "list[int] = [64, 192]"))
    line = one_error_line(capsys, ["run", str(tmp_path / "flat.py"), "-p", str(profile.path), "--dry-run"])
    assert line.endswith("(PARAMETERS is a msgspec Struct: give a list parameter a tuple default, e.g. grays: "
                         "tuple[int, ...] = (64, 128))"), line


@pytest.mark.parametrize("channel, power, message", [
    ("green", "2e-3", "step 'expose' exposes green at 2 mW, 1 frame(s) + 0 dark, which it did not declare "
                      "(declared: green alone at 1 mW, 1 frame(s) + 0 dark; red alone at a power chosen when the "
                      "step runs, 1 frame(s) + 0 dark)"),
    ("blue", "1e-3", "step 'expose' exposes blue at 1 mW"),
    ("red", "0.05", "step 'expose' exposes red at 50 mW, above the channel's max_power_mw 40 mW"),
])
def test_an_exposure_the_step_did_not_declare_is_refused_before_the_laser_is_touched(
        tmp_path: Path, bench_profile_path: Path, channel: str, power: str, message: str) -> None:
    (tmp_path / "undeclared.py").write_text(UNDECLARED % (channel, power))
    with pytest.raises(BenchctlError, match=re.escape(message)):
        run_procedure(tmp_path / "undeclared.py", profile=str(bench_profile_path), out=tmp_path / "runs",
                      say=lambda _: None)
    assert load_state("rgb-laser") == {}  # never connected: no setpoint, no emission


def test_a_declared_exposure_above_the_channels_limit_is_refused_when_planning(
        tmp_path: Path, bench_profile_path: Path) -> None:
    (tmp_path / "bright.py").write_text(TOO_BRIGHT)
    with pytest.raises(BenchctlError, match=r"step 'blinding': red at 50 mW is outside 0..max_power_mw 40 mW"):
        run_procedure(tmp_path / "bright.py", profile=str(bench_profile_path), out=tmp_path / "runs",
                      dry_run=True, say=lambda _: None)
    assert not (tmp_path / "runs").exists()


def test_the_dry_run_states_the_power_automatic_exposure_may_reach_and_a_procedure_caps_it(
        tmp_path: Path, bench_profile_path: Path) -> None:
    """The dry run said "green ... at most 2 mW" (the probe's setpoint) and the run then exposed green at 27.4 mW: now
    it states the bound automatic exposure works under, the channel's limit or the procedure's max_exposure_power,
    and the run stays within it."""
    procedure = tmp_path / "capture.toml"
    text = ('procedure = "colour-capture"\n[parameters]\ntargets = ["chart:bars"]\ncolours = ["green"]\n'
            'lut_calibration = "skip"\n')
    procedure.write_text(text)
    truly_registered(load_profile(bench_profile_path), "green")
    lines: list[str] = []
    run_procedure(procedure, profile=str(bench_profile_path), dry_run=True, say=lines.append)
    assert ". probe/bars/green: probe exposure bars  [green alone at 2 mW, 1 frame(s) + 0 dark]" in "\n".join(lines)
    assert (". capture/bars/green: expose bars  [green alone at a power chosen when the step runs (at most 40 mW), "
            "2 frame(s) + 1 dark]") in "\n".join(lines)
    assert ("  green: 2 exposure(s), at most 40 mW (1 at a power chosen at run time, up to 40 mW, the channel's "
            "limit); limit 40 mW") in lines
    procedure.write_text(text + 'max_exposure_power = "3mW"\n')
    lines.clear()
    run_procedure(procedure, profile=str(bench_profile_path), dry_run=True, say=lines.append)
    assert "  green: 2 exposure(s), at most 3 mW (1 at a power chosen at run time, up to 3 mW); limit 40 mW" in lines
    outcome = run_procedure(procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=lines.append)
    assert outcome.folder is not None
    events = [json.loads(line) for line in (outcome.folder / "steps.jsonl").read_text().splitlines()]
    done = {event["step"]: event["result"] for event in events if event["event"] == "done"}
    choice = done["probe/bars/green"]["auto_exposure"]
    assert choice["power_w"] == pytest.approx(3e-3) and choice["limited_by_max"], choice  # it wanted more
    assert done["capture/bars/green"]["setpoint_w"] == pytest.approx(3e-3)
    assert "      auto exposure green: peak " in "\n".join(lines) and "-> 3 mW (the procedure's max_exposure_power)" \
        in "\n".join(lines)


@pytest.mark.parametrize("cap, message", [
    ('"20"', "parameters.max_exposure_power: power '20' has no unit (W, mW or %?)"),
    ('"50mW"', "parameters.max_exposure_power: 50 mW is above the channel's max_power_mw 40 mW"),
    ('{ green = "1mW" }', "parameters.max_exposure_power.green: 1 mW is below green's probe at 2 mW (its setpoint): "
                          "lower the setpoint too"),
    ('{ grene = "1mW" }', "parameters.max_exposure_power.grene: no laser channel 'grene' (known: blue, green, red)"),
])
def test_a_bad_exposure_cap_is_one_line_naming_the_key(tmp_path: Path, bench_profile_path: Path, cap: str,
                                                       message: str, capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "capture.toml"
    procedure.write_text(f'procedure = "colour-capture"\n[parameters]\ncolours = ["green"]\nlut_calibration = "skip"\n'
                         f"max_exposure_power = {cap}\n")
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert line.startswith(f"benchctl: error: {procedure}: {message}"), line


@pytest.mark.parametrize("part", ["", "..", "a\\b", "/etc"])
def test_layout_refuses_names_outside_its_folders(part: str) -> None:
    with pytest.raises(ValueError, match="cannot name a file inside the run folder"):
        layout.image_file("x", part)
