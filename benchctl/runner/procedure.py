"""Procedure files: what one says, and the procedure module (built-in or a user's Python file) it names.

A procedure file is TOML:

    name = "colour-capture"            # names the run folder
    procedure = "colour-capture"       # a built-in (see BUILTINS) or a Python file, relative to this file
    description = "..."                # optional
    [parameters]                       # decoded into the procedure's PARAMETERS model
    targets = ["chart:bars"]

or a Python file given directly (its parameters then all take their defaults). A Python procedure is written on
the procedure API (`benchctl.runner.api`): DESCRIPTION, PARAMETERS and plan(context) -> list[Step].
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import msgspec

from benchctl.errors import BenchctlError
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

    name: str | None = None  # names the run folder; default: the file's name without .toml
    procedure: str  # a built-in (see BUILTINS) or a Python file, relative to this file
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


def _load_module(kind: str, base: Path, where: str, copies: Path | None = None) -> tuple[ModuleType, dict[str, bytes]]:
    """The module for a built-in name or a Python file (relative to `base`; by file name in `copies`, a run
    folder, when given), and the files to keep."""
    if kind in BUILTINS:
        return _with_parameters(importlib.import_module(BUILTINS[kind]), where), {}
    path = copies / Path(kind).name if copies else (base / kind if not Path(kind).is_absolute() else Path(kind))
    if path.suffix != ".py":
        raise BenchctlError(f"{where}: unknown procedure {kind!r} (built-ins: {', '.join(BUILTINS)}; or a .py file)")
    if not path.is_file():
        raise BenchctlError(f"{where}: procedure file {path} not found")
    spec = importlib.util.spec_from_file_location(f"benchctl_procedure_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its models' annotations are resolved in its namespace
    try:
        spec.loader.exec_module(module)
    except Exception as exc:
        del sys.modules[spec.name]
        raise BenchctlError(f"{path}: cannot load procedure: {type(exc).__name__}: {exc}") from exc
    for attribute in ("PARAMETERS", "plan"):
        if not hasattr(module, attribute):
            raise BenchctlError(f"{path}: a Python procedure must define {attribute} (see benchctl.runner.api)")
    return _with_parameters(module, str(path)), {path.name: path.read_bytes()}


def _with_parameters(module: ModuleType, where: str) -> ModuleType:
    """`module`, whose PARAMETERS must be a Parameters model."""
    model = module.PARAMETERS
    if not (isinstance(model, type) and issubclass(model, Parameters)):
        raise BenchctlError(f"{where}: PARAMETERS must be a class deriving from benchctl.runner.api.Parameters, "
                            f"got {model!r}")
    return module


def load_procedure(path: str | Path, *, copies: Path | None = None) -> Procedure:
    """Read and check a procedure file (.toml, or .py with default parameters). Errors name the file and key.

    `copies`: a run folder whose copy of a Python procedure file is used (resuming a run).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise BenchctlError(f"{path}: procedure file not found") from None
    except OSError as exc:
        raise BenchctlError(f"{path}: cannot read procedure: {exc.strerror or exc}") from None
    if path.suffix == ".py":
        module, files = _load_module(path.name, path.parent, str(path))
        params = decode({}, module.PARAMETERS, path, "parameters")
        return Procedure(path.stem, path.name, getattr(module, "DESCRIPTION", ""), module, params, files)
    try:
        raw = tomllib.loads(data.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BenchctlError(f"{path}: TOML syntax error: {exc}") from None
    top = decode(raw, ProcedureFile, path)
    module, files = _load_module(top.procedure, path.parent, f"{path}: procedure", copies)
    params = decode(top.parameters, module.PARAMETERS, path, "parameters")
    files = {PROCEDURE_COPY: data, **files}
    return Procedure(top.name or path.stem, top.procedure, top.description or getattr(module, "DESCRIPTION", ""),
                     module, params, files)
