"""Typed configuration models for TOML tables (hardware profiles, procedure files), decoded strictly.

Each section is one `Model` (a frozen msgspec Struct that forbids unknown fields): its annotations state the type,
`Annotated[..., msgspec.Meta(ge=.., gt=.., le=.., min_length=..)]` the bounds, `Literal[...]` the choices, and its
field defaults are the only defaults. `decode` turns a parsed TOML table into the model; every failure is a
BenchctlError naming the file, the key path (`laser.channels[1].wavelength_nm`), the bad value and, for an
unknown key, the closest known one (sections suggested for sections, keys for keys).

msgspec rather than pydantic v2: `benchctl laser off` loads a profile and must start about as fast as
`python -c "import serial, numpy"`. Measured with `python -X importtime` after `import serial, numpy` (median of 7,
same loaded machine): msgspec 57 ms of imports, pydantic's BaseModel 285 ms; msgspec's error messages are
translated below into benchctl's own form either way.
"""

from __future__ import annotations

import difflib
import math
import operator
import re
import sys
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, Union

import msgspec

from benchctl.errors import BenchctlError

if sys.version_info >= (3, 11):
    from typing import dataclass_transform
else:
    from typing_extensions import dataclass_transform

T = TypeVar("T", bound=msgspec.Struct)


# msgspec's subclasses inherit frozen=True, but a type checker reads each subclass by PEP 681, where frozen is a
# per-class default: frozen_default says what msgspec does, so subclasses need not repeat it.
@dataclass_transform(frozen_default=True, field_specifiers=(msgspec.field,))
class Model(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Base of every configuration section: immutable, and an unknown key is an error, never ignored.

    Subclasses say `kw_only=True` too (msgspec does not inherit it), so required and defaulted fields can stand in
    the order the file documents them. A field typed `Path` takes a string, relative to the file's folder."""


def fail(path: Path, key: str, problem: str) -> BenchctlError:
    """The error for a bad key: names the file, the key path and the problem."""
    return BenchctlError(f"{path}: {key}: {problem}")


def decode(raw: Mapping[str, Any], model: type[T], path: Path, prefix: str = "") -> T:
    """`raw` (a parsed TOML table of the file at `path`, found at key `prefix`) as a `model`, checked."""
    _check_finite(raw, prefix, path)
    try:
        return msgspec.convert(raw, model, strict=True, dec_hook=_paths_beside(path))
    except msgspec.ValidationError as exc:
        raise _translated(str(exc), raw, model, path, prefix) from None


def _paths_beside(path: Path) -> Callable[[type, Any], Any]:
    """msgspec's hook for the one non-native type used: a `Path` is a string relative to the file's folder."""
    def hook(kind: type, value: Any) -> Any:
        if kind is Path:
            if not isinstance(value, str):
                raise TypeError("expected a file path")
            return (path.parent / value).resolve()
        raise NotImplementedError(f"no decoder for {kind!r}")

    return hook


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _check_finite(value: Any, key: str, path: Path) -> None:
    """TOML allows nan and inf; no setting takes them (msgspec would let them through a float without bounds)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise fail(path, key, f"expected a finite number, got {value!r} (float)")
    if isinstance(value, dict):
        for name, item in value.items():
            _check_finite(item, _join(key, name), path)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_finite(item, f"{key}[{i}]", path)


# -- types: unwrapping annotations, describing them to people --------------------------------------------------------


def _unwrap(kind: Any) -> tuple[Any, list[msgspec.Meta]]:
    """The type without Annotated layers and without `| None` (TOML has no null), and the Meta constraints."""
    metas: list[msgspec.Meta] = []
    while True:
        origin = typing.get_origin(kind)
        if origin is Annotated:
            kind, *extra = typing.get_args(kind)
            metas += [m for m in extra if isinstance(m, msgspec.Meta)]
        elif origin in (Union, types.UnionType):
            rest = [k for k in typing.get_args(kind) if k is not type(None)]
            if len(rest) != 1:
                return kind, metas
            kind = rest[0]
        else:
            return kind, metas


def _is_struct(kind: Any) -> bool:
    return isinstance(kind, type) and issubclass(kind, msgspec.Struct)


def _items(kind: Any) -> tuple[Any, ...]:
    """A container type's item types: (element,) of a list or tuple[X, ...], all of a fixed tuple, (key, value)
    of a dict."""
    args = typing.get_args(kind)
    return args[:1] if len(args) == 2 and args[1] is Ellipsis else args


def _is_fixed_tuple(kind: Any) -> bool:
    return typing.get_origin(kind) is tuple and Ellipsis not in typing.get_args(kind)


def _is_table(kind: Any) -> bool:
    """Whether a field's type is written as a TOML table or array of tables (a section, not a key)."""
    kind, _ = _unwrap(kind)
    origin = typing.get_origin(kind)
    if _is_struct(kind) or origin is dict:
        return True
    return origin in (list, tuple) and not _is_fixed_tuple(kind) and _is_struct(_unwrap(_items(kind)[0])[0])


_COUNTS = {2: ("two", "[rows, cols]"), 3: ("three", "[r, g, b]")}


def _describe(kind: Any, key: str) -> str:
    """What a value of `kind` at `key` looks like, for "expected ..." messages."""
    kind, _ = _unwrap(kind)
    origin = typing.get_origin(kind)
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(member, key) for member in typing.get_args(kind) if member is not type(None))
    simple = {int: "an integer", float: "a finite number", bool: "true or false", str: "a string",
              Path: "a file path (a string)"}
    if kind in simple:
        return simple[kind]
    if origin is Literal:
        return "one of " + ", ".join(repr(v) for v in typing.get_args(kind))
    if _is_struct(kind):
        return f"a [{key}] table"
    if _is_fixed_tuple(kind):
        items = [_unwrap(item)[0] for item in typing.get_args(kind)]
        count, layout = _COUNTS.get(len(items), (str(len(items)), ""))
        noun = "integers" if all(item is int for item in items) else "numbers"
        return f"{count} {noun} {layout}".rstrip()
    if origin in (list, tuple):
        item = _unwrap(_items(kind)[0])[0]
        if _is_struct(item):
            return f"an array of tables ([[{key}]])"
        return "a list of strings" if item is str else f"a list, each {_describe(item, key)}"
    if origin is dict:
        value = _unwrap(typing.get_args(kind)[1])[0]
        if value is Any:
            return f"a [{key}] table"
        if value is str:
            return "a table of strings"
        if _is_struct(value) or typing.get_origin(value) is dict:
            return f"a table of [{key}.<name>] tables"
        return f"a table whose entries are each {_describe(value, key)}"
    return repr(kind)


def _fits(kind: Any, value: Any) -> bool:
    """Whether `value` has the shape of `kind` (item types are checked where they are, one level down)."""
    kind, _ = _unwrap(kind)
    origin = typing.get_origin(kind)
    if origin in (Union, types.UnionType):
        return any(_fits(member, value) for member in typing.get_args(kind) if member is not type(None))
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind in (str, Path):
        return isinstance(value, str)
    if origin is Literal:
        return value in typing.get_args(kind)
    if _is_struct(kind) or origin is dict:
        return isinstance(value, dict)
    if _is_fixed_tuple(kind):
        return isinstance(value, list) and len(value) == len(typing.get_args(kind))
    if origin in (list, tuple):
        return isinstance(value, list)
    return True


# -- translating msgspec's ValidationError ---------------------------------------------------------------------------

_MESSAGE = re.compile(r"(?P<message>.*?)(?: - at (?:`(?P<in_key>key)` in )?`\$(?P<where>[^`]*)`)?", re.S)
_SEGMENT = re.compile(r"\.(\w+)|\[(\d+)\]|\[(\.\.\.)\]")


def _translated(text: str, raw: Any, model: type, path: Path, prefix: str) -> BenchctlError:
    """msgspec's "Expected `int`, got `str` - at `$.slm.width`" as "<file>: slm.width: expected an integer, got
    '96' (str)", found by following the path through the model's types and the raw table side by side."""
    match = _MESSAGE.fullmatch(text)
    assert match is not None
    message, where = match["message"], match["where"] or ""
    try:
        return _explained(message, where, bool(match["in_key"]), raw, model, path, prefix)
    except (KeyError, IndexError, TypeError, StopIteration):  # a message this translation does not know
        key = prefix + where if where.startswith("[") else _join(prefix, where.lstrip("."))
        return fail(path, key or "(top level)", message[:1].lower() + message[1:])


def _explained(message: str, where: str, in_key: bool, raw: Any, model: type, path: Path,
               prefix: str) -> BenchctlError:
    """The error for msgspec's `message` at `where` (its path): the key it names, then what is wrong there."""
    kind, value, key = model, raw, prefix
    hook = _paths_beside(path)
    for name, index, _entry in _SEGMENT.findall(where):
        kind, _ = _unwrap(kind)
        if name:
            kind = next(f.type for f in msgspec.structs.fields(kind) if f.name == name)
            value, key = value[name], _join(key, name)
        elif index:
            items = typing.get_args(kind)
            kind = items[int(index)] if _is_fixed_tuple(kind) else items[0]
            value, key = value[int(index)], f"{key}[{index}]"
        else:  # a dict entry; msgspec does not say which: the first in order that fails on its own
            kind = typing.get_args(kind)[1]
            name = next(k for k, v in value.items() if not _converts(v, kind, hook))
            value, key = value[name], _join(key, name)
    if in_key:  # a dict key outside its Literal choices (e.g. a Zernike term)
        key_kind = typing.get_args(_unwrap(kind)[0])[0]
        known = typing.get_args(_unwrap(key_kind)[0])
        name = next(k for k in value if k not in known)
        return fail(path, _join(key, name), _unknown(name, list(known), list(known)))
    unknown = re.fullmatch(r"Object contains unknown field `(.*)`", message)
    if unknown:
        name = unknown[1]
        fields = msgspec.structs.fields(_unwrap(kind)[0])
        table = isinstance(value[name], dict) or (isinstance(value[name], list) and value[name]
                                                   and isinstance(value[name][0], dict))
        alike = [f.name for f in fields if _is_table(f.type) == table]
        problem = _unknown(name, alike, [f.name for f in fields], "section" if table else "key")
        return fail(path, _join(key, name), problem)
    missing = re.fullmatch(r"Object missing required field `(.*)`", message)
    if missing:
        field = next(f for f in msgspec.structs.fields(_unwrap(kind)[0]) if f.name == missing[1])
        return fail(path, _join(key, field.name), f"missing required {'section' if _is_table(field.type) else 'key'}")
    return fail(path, key or "(top level)", _problem(kind, value, key) or message[:1].lower() + message[1:])


def _converts(value: Any, kind: Any, hook: Callable[[type, Any], Any]) -> bool:
    try:
        msgspec.convert(value, kind, strict=True, dec_hook=hook)
    except msgspec.ValidationError:
        return False
    return True


def _unknown(name: str, alike: list[str], known: list[str], what: str = "key") -> str:
    close = difflib.get_close_matches(name, alike, n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    return f"unknown {what} ({hint}known: {', '.join(known)})"


_BOUNDS = (("gt", ">", operator.gt), ("ge", ">=", operator.ge), ("lt", "<", operator.lt), ("le", "<=", operator.le))


def _problem(kind: Any, value: Any, key: str) -> str | None:
    """What is wrong with `value` as a `kind`: the type, a choice, a bound or a length (None: none of those)."""
    base, metas = _unwrap(kind)
    if typing.get_origin(base) in (Union, types.UnionType):  # judged as the member whose shape it has
        member = next((m for m in typing.get_args(base) if m is not type(None) and _fits(_unwrap(m)[0], value)), None)
        if member is not None:
            return _problem(member, value, key)
    if typing.get_origin(base) is Literal and isinstance(value, str):
        choices = typing.get_args(base)
        if value not in choices:
            return f"unknown value {value!r} (choose from {', '.join(choices)})"
    if not _fits(base, value):
        return f"expected {_describe(base, key)}, got {value!r} ({type(value).__name__})"
    shown = float(value) if base is float else value
    for meta in metas:
        for bound, sign, holds in _BOUNDS:
            limit = getattr(meta, bound)
            if limit is not None and not holds(value, limit):
                return f"must be {sign} {limit:g}, got {shown!r}"
        if meta.min_length is not None and len(value) < meta.min_length:
            return f"at least {meta.min_length} entry required, got {len(value)}"
        if meta.max_length is not None and len(value) > meta.max_length:
            unit = "characters" if isinstance(value, str) else "entries"
            return f"at most {meta.max_length} {unit}, got {len(value)}"
    return None
