"""Strict validation of TOML tables against a declared schema (hardware profiles, procedure files).

A schema is a mapping of key -> `Field` (kind, required, default, bounds, nested fields). Unknown keys are
errors that suggest the closest known key, never silently ignored; every error is a BenchctlError naming the
file, the key path (`laser.channels[1].wavelength_nm`) and the bad value.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchctl.errors import BenchctlError


@dataclass(frozen=True)
class Field:
    """One key of the schema: its kind, whether it is required, its default and its numeric bounds."""

    # "float", "int", "bool", "str", "str_list", "names" (one string or a list of them), "int_pair", "float_pair",
    # "str_map",
    # "triple_map" (name -> three numbers),
    # "table" (fields), "tables" (array) or "table_map" (name -> a table of `fields`, e.g. one per laser channel)
    kind: str
    required: bool = True
    default: Any = None
    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    fields: Mapping[str, Field] | None = None
    min_items: int = 0
    choices: tuple[str, ...] | None = None


def fail(path: Path, key: str, problem: str) -> BenchctlError:
    """The error for a bad key: names the file, the key path and the problem."""
    return BenchctlError(f"{path}: {key}: {problem}")


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def check_table(raw: Mapping[str, Any], fields: Mapping[str, Field], prefix: str, path: Path) -> dict[str, Any]:
    """Check one table against its fields: no unknown keys (a close match is suggested), no missing required ones;
    fill defaults. Returns the checked values in their Python form."""
    for key, value in raw.items():
        if key not in fields:
            # Suggest sections for sections and keys for keys: `[camera]` is not a misspelt `name`.
            is_table = isinstance(value, dict) or (isinstance(value, list) and value and isinstance(value[0], dict))
            what = "section" if is_table else "key"
            alike = [name for name, field in fields.items() if (field.kind in ("table", "tables")) == is_table]
            close = difflib.get_close_matches(key, alike, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise fail(path, _join(prefix, key), f"unknown {what} ({hint}known: {', '.join(fields)})")
    checked: dict[str, Any] = {}
    for key, field in fields.items():
        if key in raw:
            checked[key] = _check_value(raw[key], field, _join(prefix, key), path)
        elif field.required:
            what = "section" if field.kind == "table" else "key"
            raise fail(path, _join(prefix, key), f"missing required {what}")
        elif field.default is not None:
            checked[key] = field.default
    return checked


def _check_value(value: Any, field: Field, key: str, path: Path) -> Any:
    """Check one value's type and bounds; return it in its Python form (float, int, tuple, dict, list)."""
    def wrong(expected: str) -> BenchctlError:
        return fail(path, key, f"expected {expected}, got {value!r} ({type(value).__name__})")

    if field.kind == "table":
        if not isinstance(value, dict):
            raise wrong("a [section] table")
        return check_table(value, field.fields or {}, key, path)
    if field.kind == "table_map":
        if not isinstance(value, dict) or not all(isinstance(item, dict) for item in value.values()):
            raise wrong("a table of [section.<name>] tables")
        return {name: check_table(item, field.fields or {}, f"{key}.{name}", path) for name, item in value.items()}
    if field.kind == "tables":
        if not isinstance(value, list) or not all(isinstance(item, dict) for item in value):
            raise wrong(f"an array of tables ([[{key}]])")
        if len(value) < field.min_items:
            raise fail(path, key, f"at least {field.min_items} entry required, got {len(value)}")
        return [check_table(item, field.fields or {}, f"{key}[{i}]", path) for i, item in enumerate(value)]
    if field.kind == "names" and isinstance(value, str):
        return _check_value(value, Field("str", choices=field.choices), key, path)
    if field.kind in ("str_list", "names"):
        if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise wrong("a list of strings" if field.kind == "str_list" else "a string or a list of strings")
        if len(value) < field.min_items:
            raise fail(path, key, f"at least {field.min_items} entry required, got {len(value)}")
        for i, item in enumerate(value):
            if field.choices is not None and item not in field.choices:
                raise fail(path, f"{key}[{i}]", f"unknown value {item!r} (choose from {', '.join(field.choices)})")
        return list(value)
    if field.kind == "str":
        if not isinstance(value, str):
            raise wrong("a string")
        if field.choices is not None and value not in field.choices:
            raise fail(path, key, f"unknown value {value!r} (choose from {', '.join(field.choices)})")
        return value
    if field.kind == "bool":
        if not isinstance(value, bool):
            raise wrong("true or false")
        return value
    if field.kind == "str_map":
        if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
            raise wrong("a table of strings")
        return dict(value)
    if field.kind == "triple_map":
        if not isinstance(value, dict):
            raise wrong("a table of [r, g, b] number triples")
        triples = {}
        for name, triple in value.items():
            if not (isinstance(triple, list) and len(triple) == 3 and all(_is_number(v) for v in triple)):
                raise fail(path, f"{key}.{name}", f"expected three numbers [r, g, b], got {triple!r}")
            triples[name] = tuple(_check_bounds(float(v), field, f"{key}.{name}[{i}]", path)
                                  for i, v in enumerate(triple))
        return triples
    if field.kind == "float_pair":
        if not (isinstance(value, list) and len(value) == 2 and all(_is_number(v) for v in value)):
            raise wrong("two numbers [rows, cols]")
        return tuple(float(v) for v in value)
    if field.kind == "int_pair":
        if not (isinstance(value, list) and len(value) == 2 and all(_is_int(v) for v in value)):
            raise wrong("two integers [rows, cols]")
        return tuple(_check_bounds(v, field, f"{key}[{i}]", path) for i, v in enumerate(value))
    if field.kind == "int":
        if not _is_int(value):
            raise wrong("an integer")
        return _check_bounds(value, field, key, path)
    if not _is_number(value):
        raise wrong("a finite number")
    return _check_bounds(float(value), field, key, path)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_bounds(value: float, field: Field, key: str, path: Path) -> Any:
    if field.gt is not None and not value > field.gt:
        raise fail(path, key, f"must be > {field.gt:g}, got {value!r}")
    if field.ge is not None and not value >= field.ge:
        raise fail(path, key, f"must be >= {field.ge:g}, got {value!r}")
    if field.le is not None and not value <= field.le:
        raise fail(path, key, f"must be <= {field.le:g}, got {value!r}")
    return value
