"""Procedure files: what one says, and the procedure module (built-in or a user's Python file) it names.

A procedure file is TOML:

    name = "colour-capture"            # names the run folder
    procedure = "colour-capture"       # a built-in (see BUILTINS) or a Python file in this file's folder
    description = "..."                # optional
    [parameters]                       # decoded into the procedure's PARAMETERS model
    targets = ["chart:bars"]

or a Python file given directly (its parameters then all take their defaults). A Python procedure is written on
the procedure API (`benchctl.runner.api`): DESCRIPTION, PARAMETERS and plan(context) -> list[Step].

A TOML file is data: the Python file it names must lie in its own folder (no absolute path, nothing reached through
`..` or a link out of it) and runs only with `allow_code` (`benchctl run --allow-code`); so does the Python code a
resumed run kept, since a run folder may come from anywhere. A Python file named on the command line is code by
the user's own choice.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Annotated, Any

import msgspec
from msgspec import Meta

from benchctl.errors import BenchctlError, did_you_mean
from benchctl.files import read_capped
from benchctl.runner.context import Context, Parameters, Step, check_exposures
from benchctl.runner.layout import PROCEDURE_COPY
from benchctl.schema import Model, decode

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

BUILTINS = {
    "colour-capture": "benchctl.runner.builtin.colour_capture",
    "registration": "benchctl.runner.builtin.registration",
    "lut-calibration": "benchctl.runner.builtin.lut_calibration",
    "power-sweep": "benchctl.runner.builtin.power_sweep",
    "model-calibration": "benchctl.runner.builtin.model_calibration",
    "citl": "benchctl.runner.builtin.citl.procedure",
    "focus-calibration": "benchctl.runner.builtin.focus_calibration",
    "focal-stack": "benchctl.runner.builtin.focal_stack",
}

MAX_STEPS = 100_000  # a plan longer than this is a mistake (repeats = 1000000), not an experiment


class ProcedureFile(Model, kw_only=True):
    """What a procedure file (.toml) says."""

    name: Annotated[str, Meta(max_length=100)] | None = None  # names the run folder; default: the file's name
    procedure: str  # a built-in (see BUILTINS) or a Python file in this file's folder
    description: str = ""  # default: the procedure's DESCRIPTION
    # Decoded into the procedure's PARAMETERS once the procedure is known.
    parameters: dict[str, Any] = msgspec.field(default_factory=dict)


@dataclass(frozen=True)
class Procedure:
    """A loaded procedure: its module (built-in or user file), checked parameters and the files as read."""

    name: str
    kind: str
    description: str
    module: ModuleType
    params: Parameters
    files: dict[str, bytes]  # run-folder file name -> bytes, to keep as used

    def plan(self, context: Context) -> list[Step]:
        steps = self.module.plan(context)
        if len(steps) > MAX_STEPS:
            raise BenchctlError(f"procedure {self.name!r} plans {len(steps):,} steps, above the limit of {MAX_STEPS:,} "
                                "(split it into several runs)")
        repeated = {key for key, count in Counter(step.key for step in steps).items() if count > 1}
        if repeated:
            raise BenchctlError(f"procedure {self.name!r} plans step(s) {sorted(repeated)} more than once")
        check_exposures(steps, context.profile)
        return steps


ALLOW_CODE = "--allow-code"


def _code_path(kind: str, base: Path, where: str, allow_code: bool) -> Path:
    """The Python file a TOML procedure file in folder `base` names: inside `base`, and allowed to run."""
    if Path(kind).suffix != ".py":
        raise BenchctlError(f"{where}: unknown procedure {kind!r}{did_you_mean(kind, BUILTINS)} (built-ins: "
                            f"{', '.join(BUILTINS)}; or a .py file beside the procedure file)")
    path = base / kind
    if Path(kind).is_absolute() or not path.resolve().is_relative_to(base.resolve()):
        raise BenchctlError(f"{where}: {kind!r} is outside the procedure file's folder {base}: a TOML procedure names "
                            "a built-in or a Python file in its own folder")
    if not allow_code:
        raise BenchctlError(f"{where}: {kind!r} is Python code, which would run with your rights: add {ALLOW_CODE} "
                            "if you trust it")
    return path


def _resumed_code(path: Path, allow_code: bool) -> Path:
    """A resumed run's own copy of its Python procedure, allowed to run."""
    if not allow_code:
        raise BenchctlError(f"{path.parent}: this run's procedure is Python code ({path.name}), which a resume runs "
                            f"with your rights: add {ALLOW_CODE} if you trust it")
    return path


def _import(path: Path) -> tuple[ModuleType, dict[str, bytes]]:
    """The module of a Python procedure file, run from the bytes it returns (the run keeps and hashes what ran)."""
    try:
        source = read_capped(path, "procedure")
    except FileNotFoundError:
        raise BenchctlError(f"{path}: procedure file not found") from None
    spec = importlib.util.spec_from_file_location(f"benchctl_procedure_{path.stem}", path)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its models' annotations are resolved in its namespace
    try:
        exec(compile(source, str(path), "exec"), module.__dict__)
    except Exception as exc:
        del sys.modules[spec.name]
        hint = (" (PARAMETERS is a msgspec Struct: give a list parameter a tuple default, e.g. grays: tuple[int, ...] "
                "= (64, 128))" if isinstance(exc, TypeError) and "mutable collection" in str(exc) else "")
        raise BenchctlError(f"{path}: cannot load procedure: {type(exc).__name__}: {exc}{hint}") from exc
    for attribute in ("PARAMETERS", "plan"):
        if not hasattr(module, attribute):
            raise BenchctlError(f"{path}: a Python procedure must define {attribute} (see benchctl.runner.api)")
    return _with_parameters(module, str(path)), {path.name: source}


def _with_parameters(module: ModuleType, where: str) -> ModuleType:
    """`module`, whose PARAMETERS must be a Parameters model."""
    model = module.PARAMETERS
    if not (isinstance(model, type) and issubclass(model, Parameters)):
        raise BenchctlError(f"{where}: PARAMETERS must be a class deriving from benchctl.runner.api.Parameters, "
                            f"got {model!r}")
    return module


def load_procedure(path: str | Path, *, copies: Path | None = None, allow_code: bool = False) -> Procedure:
    """Read and check a procedure file (.toml, or .py with default parameters). Errors name the file and key.

    `copies`: the run folder being resumed, whose copies are used. `allow_code`: the Python file a TOML names, or a
    resumed run's, may run (a .py named here is the caller's own choice).
    """
    path = Path(path)
    if path.suffix == ".py":
        module, files = _import(_resumed_code(path, allow_code) if copies is not None else path)
        params = decode({}, module.PARAMETERS, path, "parameters")
        return Procedure(path.stem, path.name, getattr(module, "DESCRIPTION", ""), module, params, files)
    try:
        data = read_capped(path, "procedure")
    except FileNotFoundError:
        raise BenchctlError(f"{path}: procedure file not found{_near(path)}") from None
    try:
        raw = tomllib.loads(data.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BenchctlError(f"{path}: TOML syntax error: {exc}") from None
    top = decode(raw, ProcedureFile, path)
    where = f"{path}: procedure"
    if top.procedure in BUILTINS:
        module, files = _with_parameters(importlib.import_module(BUILTINS[top.procedure]), where), {}
    elif copies is not None:
        module, files = _import(_resumed_code(copies / Path(top.procedure).name, allow_code))
    else:
        module, files = _import(_code_path(top.procedure, path.parent, where, allow_code))
    params = decode(top.parameters, module.PARAMETERS, path, "parameters")
    files = {PROCEDURE_COPY: data, **files}
    return Procedure(top.name or path.stem, top.procedure, top.description or getattr(module, "DESCRIPTION", ""),
                     module, params, files)


def _near(path: Path) -> str:
    """" (did you mean 'procedures/citl.toml'?)" for a misspelt procedure file beside others."""
    folder = path.parent
    if not folder.is_dir():
        return ""
    known = [str(folder / other.name) for other in folder.iterdir() if other.suffix in (".toml", ".py")]
    return did_you_mean(str(path), known, key=lambda name: Path(name).name)
