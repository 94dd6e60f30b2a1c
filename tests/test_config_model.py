"""The configuration model: one typed msgspec model per section is the only source of types, bounds and defaults,
and its errors keep the file / key path / value / "did you mean" form."""

from __future__ import annotations

import importlib
import importlib.util
import json
import sys
import typing
from pathlib import Path

import msgspec
import msgspec.inspect as mi
import pytest

from benchctl.errors import BenchctlError
from benchctl.profiles import (
    CameraConfig,
    LaserChannel,
    LaserConfig,
    OpticsConfig,
    ProfileFile,
    SimConfig,
    SLMConfig,
    TemplateProtocol,
    load_profile,
)
from benchctl.runner.procedure import BUILTINS, ProcedureFile, load_procedure
from benchctl.schema import Model

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]

# Only the keys a profile must give: everything else is the models' defaults.
MINIMAL = """\
[optics]
distance_mm = 50
roi = [16, 16]

[slm]
width = 32
height = 32
pitch_um = 8
bit_depth = 8

[laser]
port = "sim://rgb-laser"

[laser.protocol]
set_power = "P{channel} {mw}"
get_power = "P{channel}?"
enable = "E{channel} 1"
disable = "E{channel} 0"

[[laser.channels]]
name = "green"
wavelength_nm = 520
max_power_mw = 10
setpoint_mw = 1

[camera]
"""


def _defaults(model: type[msgspec.Struct]) -> dict[str, object]:
    """The defaults `model` declares, by field name."""
    found = {}
    for field in msgspec.structs.fields(model):
        if field.default is not msgspec.NODEFAULT:
            found[field.name] = field.default
        elif field.default_factory is not msgspec.NODEFAULT:
            found[field.name] = field.default_factory()
    return found


def test_a_minimal_profile_gets_exactly_the_defaults_the_models_declare(tmp_path: Path) -> None:
    path = tmp_path / "minimal.toml"
    path.write_text(MINIMAL)
    profile, raw = load_profile(path), tomllib.loads(MINIMAL)
    sections = [(OpticsConfig, profile.optics, raw["optics"]), (SLMConfig, profile.slm, raw["slm"]),
                (CameraConfig, profile.camera, raw["camera"]), (SimConfig, profile.sim, {}),
                (TemplateProtocol, profile.laser.protocol, raw["laser"]["protocol"]),
                (LaserConfig, profile.laser, raw["laser"]),
                (LaserChannel, profile.channels[0], raw["laser"]["channels"][0])]
    checked = 0
    for model, loaded, given in sections:
        for name, default in _defaults(model).items():
            if name in given:
                continue
            if (model, name) == (LaserChannel, "index"):
                assert loaded.index == 1  # numbered by position when the file gives none
                continue
            assert getattr(loaded, name) == default, f"{model.__name__}.{name}"
            checked += 1
    assert checked > 30
    assert (profile.name, profile.description) == ("minimal", "")
    assert profile.slm.settle_ms == 100.0 and profile.laser.baudrate == 115200  # the documented values
    assert profile.camera.usb_id == "04a9:32a0" and profile.camera.image_timeout_s == 90.0
    assert profile.laser.protocol.error_prefix == "ERR"


def _all_models() -> list[type[Model]]:
    """Every configuration model: the profile's, the procedure file's and every procedure's parameters."""
    for module in [*BUILTINS.values()]:
        importlib.import_module(module)
    spec = importlib.util.spec_from_file_location("grating_shift", REPO / "procedures" / "grating_shift.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    found, stack = [], [Model]
    while stack:
        model = stack.pop()
        found.append(model)
        stack += model.__subclasses__()
    return found


def _unenforced(info: mi.Type, where: str) -> list[str]:
    """Places in a type that msgspec does not check by itself (Any, custom types), where they are."""
    if isinstance(info, mi.AnyType):
        return [where]
    if isinstance(info, mi.CustomType):
        return [] if info.cls is Path else [where]  # Path: decoded by benchctl.schema's hook, strings only
    if isinstance(info, mi.StructType):
        return [bad for field in info.fields for bad in _unenforced(field.type, f"{where}.{field.name}")]
    if isinstance(info, mi.UnionType):
        return [bad for item in info.types for bad in _unenforced(item, where)]
    if isinstance(info, mi.DictType):
        return _unenforced(info.key_type, f"{where}[key]") + _unenforced(info.value_type, f"{where}[]")
    if isinstance(info, (mi.ListType, mi.VarTupleType)):
        return _unenforced(info.item_type, f"{where}[]")
    if isinstance(info, mi.TupleType):
        return [bad for i, item in enumerate(info.item_types) for bad in _unenforced(item, f"{where}[{i}]")]
    return []


def test_every_field_has_a_type_msgspec_enforces() -> None:
    """No silent fallback: each key of every model is checked by msgspec (or is a Path, checked by the hook)."""
    models = _all_models()
    names = {model.__name__ for model in models}
    assert {"ProfileFile", "ColourCaptureParameters", "LutCalibrationParameters", "GratingShiftParameters"} <= names
    for model in models:
        unchecked = _unenforced(mi.type_info(model), model.__name__)
        # The procedure file's [parameters] is decoded a second time, into the procedure's own model.
        assert unchecked in ([], ["ProcedureFile.parameters[]"]), unchecked
        assert model.__struct_config__.forbid_unknown_fields and model.__struct_config__.frozen, model
        for field in msgspec.structs.fields(model):
            base = typing.get_origin(field.type) or field.type
            assert base is not typing.Any, f"{model.__name__}.{field.name}"
    assert _unenforced(mi.type_info(ProcedureFile), "ProcedureFile") == ["ProcedureFile.parameters[]"]
    assert _unenforced(mi.type_info(ProfileFile), "ProfileFile") == []


def edited_profile(tmp_path: Path, small_profile_path: Path, old: str, new: str) -> Path:
    text = small_profile_path.read_text()
    assert old in text
    path = tmp_path / "edited.toml"
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize("old, new, message", [
    # sections are suggested for sections: a misspelt [sim.aberration.<channel>] table names its section
    ("[laser]", "[sim.aberation.green]\ndefocus = 0.1\n\n[laser]",
     "sim.aberation: unknown section (did you mean 'aberration'? known: seed, slm, beam, imaging, aberration, sensor, "
     "focus)"),
    ("[laser]", "[sim.aberration.green]\nfocus = 0.1\n\n[laser]",
     "sim.aberration.green.focus: unknown key (did you mean 'defocus'? known: tilt_vertical, tilt_horizontal"),
    ("roi = [48, 80]", 'roi = [48, 80]\nmodel = 3', "optics.model: expected a file path (a string), got 3 (int)"),
    ("roi = [48, 80]", "roi = [48, 80.5]", "optics.roi[1]: expected an integer, got 80.5 (float)"),
    ("[laser]", "[sim.sensor]\nbit_depth = 7\n\n[laser]", "sim.sensor.bit_depth: must be >= 8, got 7"),
    ("[laser]", "[sim.beam]\nefficiency = 0\n\n[laser]", "sim.beam.efficiency: must be > 0, got 0.0"),
    ("[laser]", "[sim.slm]\nzero_order = 1.5\n\n[laser]", "sim.slm.zero_order: must be <= 1, got 1.5"),
    ("[laser]", "[sim]\nseed = -1\n\n[laser]", "sim.seed: must be >= 0, got -1"),
    ("[laser]", "[sim.imaging]\nrotation_deg = inf\n\n[laser]",
     "sim.imaging.rotation_deg: expected a finite number, got inf (float)"),
    ("[laser]", "[camera]\ntransport = 'wifi'\n\n[laser]",
     "camera.transport: unknown value 'wifi' (choose from usb, sim)"),
    ("[laser]", "[camera]\nimage_timeout_s = 0\n\n[laser]", "camera.image_timeout_s: must be > 0, got 0.0"),
    ("[laser]", "[laser]\nbaudrate = '9600'", "laser.baudrate: expected an integer, got '9600' (str)"),
    ("[laser.protocol]", "[laser.protocol]\nerror_prefix = false",
     "laser.protocol.error_prefix: expected a string, got False (bool)"),
    ("[laser]", "[slm.lut]\ngreen = 5\n\n[laser]", "slm.lut.green: expected a file path (a string), got 5 (int)"),
])
def test_profile_errors_name_file_key_path_value_and_bound(tmp_path: Path, small_profile_path: Path, old: str,
                                                           new: str, message: str) -> None:
    path = edited_profile(tmp_path, small_profile_path, old, new)
    with pytest.raises(BenchctlError) as caught:
        load_profile(path)
    assert str(caught.value).startswith(f"{path}: {message}"), str(caught.value)


def test_paths_in_a_profile_are_relative_to_its_folder(tmp_path: Path, small_profile_path: Path) -> None:
    path = edited_profile(tmp_path, small_profile_path, "roi = [48, 80]", 'roi = [48, 80]\nmodel = "m/model.json"')
    assert load_profile(path).optics.model == (tmp_path / "m" / "model.json").resolve()


@pytest.mark.parametrize("parameters, message", [
    ("gray_steps = 4", "parameters.gray_steps: unknown key (did you mean 'gray_step'? known: colours, setpoints"),
    ("gray_step = 0", "parameters.gray_step: must be >= 1, got 0"),
    ("frames = 1.5", "parameters.frames: expected an integer, got 1.5 (float)"),
    ("colours = 'red'", "parameters.colours: expected a list of strings, got 'red' (str)"),
    ("setpoint = { red = '1mW' }", "parameters.setpoint: unknown section (did you mean 'setpoints'?"),
])
def test_procedure_parameters_are_refused_in_the_same_form(tmp_path: Path, parameters: str, message: str) -> None:
    path = tmp_path / "lut.toml"
    path.write_text(f'procedure = "lut-calibration"\n[parameters]\n{parameters}\n')
    with pytest.raises(BenchctlError) as caught:
        load_procedure(path)
    assert str(caught.value).startswith(f"{path}: {message}"), str(caught.value)


def test_a_procedure_overrides_a_shared_groups_default_and_the_profiles_settle_time(
        tmp_path: Path, small_profile_path: Path) -> None:
    path = tmp_path / "lut.toml"
    path.write_text('procedure = "lut-calibration"\n')
    params = load_procedure(path).params
    assert (params.frames, params.dark_frames, params.gray_step) == (1, 0, 8)  # the lut model's own defaults
    path.write_text('procedure = "colour-capture"\n[parameters]\nsettle_ms = 5\n')
    params = load_procedure(path).params
    assert (params.frames, params.dark_frames, params.targets) == (2, 1, ("chart:bars",))  # the shared group's
    profile = load_profile(small_profile_path)
    assert params.applied_to(profile).slm.settle_ms == 5.0 and profile.slm.settle_ms == 100.0
    assert json.loads(json.dumps(msgspec.to_builtins(params)))["targets"] == ["chart:bars"]  # as run.json has it


def test_a_python_procedure_must_declare_a_parameters_model(tmp_path: Path) -> None:
    path = tmp_path / "old_style.py"
    path.write_text("PARAMETERS = {}\n\n\ndef plan(context):\n    return []\n")
    with pytest.raises(BenchctlError, match="PARAMETERS must be a class deriving from "
                                            "benchctl.runner.api.Parameters, got {}"):
        load_procedure(path)
