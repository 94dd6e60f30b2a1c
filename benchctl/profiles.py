"""Hardware profiles: one TOML file per bench, validated against a declared schema, loaded as frozen dataclasses.

The schema (SCHEMA below) lists every section and key with its type and bounds in one place; adding a section
means adding an entry there and a dataclass. Validation is strict: an unknown key (a misspelt `pitch` for
`pitch_um`) is an error that suggests the closest known key, never silently ignored. Every error is a
BenchctlError naming the file, the key path (`laser.channels[1].wavelength_nm`) and the bad value.
"""

from __future__ import annotations

import difflib
import math
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchctl.errors import BenchctlError

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

PROFILE_ENV = "BENCHCTL_PROFILE"
PROFILE_DIR = "hardware_profiles"
DEFAULT_PROFILE = "simulated"


@dataclass(frozen=True)
class Field:
    """One key of the schema: its kind, whether it is required, its default and its numeric bounds."""

    kind: str  # "float", "int", "str", "int_pair", "table" (fields) or "tables" (array of tables)
    required: bool = True
    default: Any = None
    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    fields: Mapping[str, Field] | None = None
    min_items: int = 0


_CHANNEL = {
    "name": Field("str"),
    # The laser unit's own channel number, as drivers address it; defaults to the position in the list, from 1.
    "index": Field("int", required=False, ge=0),
    "wavelength_nm": Field("float", gt=0),
    "max_power_mw": Field("float", gt=0),
    "setpoint_mw": Field("float", ge=0),
}

SCHEMA: Mapping[str, Field] = {
    "name": Field("str", required=False),
    "description": Field("str", required=False, default=""),
    "optics": Field("table", fields={
        "distance_mm": Field("float", gt=0),
        "roi": Field("int_pair", gt=0),
        "iris_fraction": Field("float", required=False, gt=0),
    }),
    "slm": Field("table", fields={
        "width": Field("int", gt=0),
        "height": Field("int", gt=0),
        "pitch_um": Field("float", gt=0),
        "bit_depth": Field("int", ge=1, le=16),
    }),
    "laser": Field("table", fields={
        "channels": Field("tables", fields=_CHANNEL, min_items=1),
    }),
}


@dataclass(frozen=True)
class OpticsConfig:
    """Propagation geometry: SLM-to-target distance and the centred target region (ROI) in SLM pixels."""

    distance_mm: float
    roi: tuple[int, int]  # (rows, cols), centred in the SLM grid
    # Fourier-plane iris of the relay: radius as a fraction of the SLM's Nyquist frequency (None: no iris).
    # A physical iris of diameter D behind a lens of focal length f gives D * pitch / (wavelength * f).
    iris_fraction: float | None = None

    @property
    def distance_m(self) -> float:
        return self.distance_mm * 1e-3


@dataclass(frozen=True)
class SLMConfig:
    """Phase SLM: grid size, pixel pitch and gray-level bit depth."""

    width: int
    height: int
    pitch_um: float
    bit_depth: int

    @property
    def pitch_m(self) -> float:
        return self.pitch_um * 1e-6

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W), the shape of fields and holograms."""
        return self.height, self.width


@dataclass(frozen=True)
class LaserChannel:
    """One wavelength of the laser unit, with its power limit and the setpoint the bench uses."""

    name: str
    index: int
    wavelength_nm: float
    max_power_mw: float
    setpoint_mw: float

    @property
    def wavelength_m(self) -> float:
        return self.wavelength_nm * 1e-9


@dataclass(frozen=True)
class Profile:
    """A validated hardware profile."""

    path: Path
    name: str
    description: str
    optics: OpticsConfig
    slm: SLMConfig
    channels: tuple[LaserChannel, ...]

    def channel(self, name: str) -> LaserChannel:
        """The laser channel called `name`."""
        for ch in self.channels:
            if ch.name == name:
                return ch
        known = ", ".join(ch.name for ch in self.channels)
        raise BenchctlError(f"{self.path}: no laser channel {name!r}; known channels: {known}")

    def describe(self) -> str:
        """Multi-line summary for people: grid, pitch, distance, ROI and every laser channel."""
        slm, optics = self.slm, self.optics
        lines = [f"Hardware profile {self.name!r} ({self.path})"]
        if self.description:
            lines.append(f"  {self.description}")
        lines += [
            f"  SLM grid      {slm.height} x {slm.width} px (rows x cols), pitch {slm.pitch_um:g} um, "
            f"{slm.bit_depth} bit",
            f"  Distance      {optics.distance_mm:g} mm",
            f"  ROI           {optics.roi[0]} x {optics.roi[1]} px (rows x cols), centred",
            "  Laser channels:",
        ]
        width = max(len(ch.name) for ch in self.channels)
        for ch in self.channels:
            share = 100.0 * ch.setpoint_mw / ch.max_power_mw
            lines.append(
                f"    {ch.name:<{width}}  #{ch.index}  {ch.wavelength_nm:g} nm  max {ch.max_power_mw:g} mW  "
                f"setpoint {ch.setpoint_mw:g} mW ({share:.0f} %)"
            )
        return "\n".join(lines)


def resolve_profile_path(path_or_name: str | Path | None = None) -> Path:
    """Where a profile lives: a path, a bare name (hardware_profiles/<name>.toml) or None for the default.

    None means $BENCHCTL_PROFILE if set, else the simulated bench. Bare names are looked up in
    ./hardware_profiles first, then in the hardware_profiles folder of the repository next to the package.
    """
    origin = ""
    if path_or_name is None:
        env = os.environ.get(PROFILE_ENV)
        path_or_name = env or DEFAULT_PROFILE
        origin = f" (from ${PROFILE_ENV})" if env else ""
    text = str(path_or_name)
    if isinstance(path_or_name, Path) or text.endswith(".toml") or "/" in text or os.sep in text:
        return Path(path_or_name)
    file_name = f"{text}.toml"
    candidates = [Path(PROFILE_DIR) / file_name, Path(__file__).resolve().parents[1] / PROFILE_DIR / file_name]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    searched = ", ".join(str(c) for c in candidates)
    raise BenchctlError(f"hardware profile {text!r}{origin} not found (looked for {searched})")


def load_profile(path_or_name: str | Path | None = None) -> Profile:
    """Read, validate and return a hardware profile (see resolve_profile_path for how it is found)."""
    path = resolve_profile_path(path_or_name)
    try:
        with path.open("rb") as f:
            raw = tomllib.load(f)
    except FileNotFoundError:
        raise BenchctlError(f"{path}: hardware profile not found") from None
    except OSError as exc:
        raise BenchctlError(f"{path}: cannot read hardware profile: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BenchctlError(f"{path}: TOML syntax error: {exc}") from None
    return _build(path, _check_table(raw, SCHEMA, "", path))


def _fail(path: Path, key: str, problem: str) -> BenchctlError:
    return BenchctlError(f"{path}: {key}: {problem}")


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _check_table(raw: Mapping[str, Any], fields: Mapping[str, Field], prefix: str, path: Path) -> dict[str, Any]:
    """Check one table against its fields: no unknown keys, no missing required ones; fill defaults."""
    for key, value in raw.items():
        if key not in fields:
            # Suggest sections for sections and keys for keys: `[camera]` is not a misspelt `name`.
            is_table = isinstance(value, dict) or (isinstance(value, list) and value and isinstance(value[0], dict))
            what = "section" if is_table else "key"
            alike = [name for name, field in fields.items() if (field.kind in ("table", "tables")) == is_table]
            close = difflib.get_close_matches(key, alike, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise _fail(path, _join(prefix, key), f"unknown {what} ({hint}known: {', '.join(fields)})")
    checked: dict[str, Any] = {}
    for key, field in fields.items():
        if key in raw:
            checked[key] = _check_value(raw[key], field, _join(prefix, key), path)
        elif field.required:
            what = "section" if field.kind == "table" else "key"
            raise _fail(path, _join(prefix, key), f"missing required {what}")
        elif field.default is not None:
            checked[key] = field.default
    return checked


def _check_value(value: Any, field: Field, key: str, path: Path) -> Any:
    """Check one value's type and bounds; return it in its Python form (float, int, tuple, dict, list)."""
    def wrong(expected: str) -> BenchctlError:
        return _fail(path, key, f"expected {expected}, got {value!r} ({type(value).__name__})")

    if field.kind == "table":
        if not isinstance(value, dict):
            raise wrong("a [section] table")
        return _check_table(value, field.fields or {}, key, path)
    if field.kind == "tables":
        if not isinstance(value, list) or not all(isinstance(item, dict) for item in value):
            raise wrong(f"an array of tables ([[{key}]])")
        if len(value) < field.min_items:
            raise _fail(path, key, f"at least {field.min_items} entry required, got {len(value)}")
        return [_check_table(item, field.fields or {}, f"{key}[{i}]", path) for i, item in enumerate(value)]
    if field.kind == "str":
        if not isinstance(value, str):
            raise wrong("a string")
        return value
    if field.kind == "int_pair":
        if not (isinstance(value, list) and len(value) == 2 and all(_is_int(v) for v in value)):
            raise wrong("two integers [rows, cols]")
        return tuple(_check_bounds(v, field, f"{key}[{i}]", path) for i, v in enumerate(value))
    if field.kind == "int":
        if not _is_int(value):
            raise wrong("an integer")
        return _check_bounds(value, field, key, path)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise wrong("a finite number")
    return _check_bounds(float(value), field, key, path)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_bounds(value: float, field: Field, key: str, path: Path) -> Any:
    if field.gt is not None and not value > field.gt:
        raise _fail(path, key, f"must be > {field.gt:g}, got {value!r}")
    if field.ge is not None and not value >= field.ge:
        raise _fail(path, key, f"must be >= {field.ge:g}, got {value!r}")
    if field.le is not None and not value <= field.le:
        raise _fail(path, key, f"must be <= {field.le:g}, got {value!r}")
    return value


def _build(path: Path, data: Mapping[str, Any]) -> Profile:
    """Cross-key checks the schema cannot express, then the dataclasses."""
    optics = OpticsConfig(**data["optics"])
    slm = SLMConfig(**data["slm"])
    rows, cols = optics.roi
    if rows > slm.height or cols > slm.width:
        raise _fail(
            path, "optics.roi",
            f"{[rows, cols]} is larger than the SLM grid {slm.height} x {slm.width} (slm.height x slm.width)",
        )
    channels = []
    first_seen: dict[tuple[str, Any], str] = {}
    for i, entry in enumerate(data["laser"]["channels"]):
        key = f"laser.channels[{i}]"
        channel = LaserChannel(**{"index": i + 1, **entry})
        if not channel.name.strip():
            raise _fail(path, f"{key}.name", f"channel name must not be empty, got {channel.name!r}")
        for attr in ("name", "index"):
            value = getattr(channel, attr)
            if (attr, value) in first_seen:
                also = first_seen[attr, value]
                raise _fail(path, f"{key}.{attr}", f"duplicate channel {attr} {value!r} (also {also})")
            first_seen[attr, value] = f"{key}.{attr}"
        if channel.setpoint_mw > channel.max_power_mw:
            raise _fail(
                path, f"{key}.setpoint_mw",
                f"{channel.setpoint_mw:g} mW is above max_power_mw {channel.max_power_mw:g} mW",
            )
        channels.append(channel)
    return Profile(
        path=path,
        name=data.get("name", path.stem),
        description=data["description"],
        optics=optics,
        slm=slm,
        channels=tuple(channels),
    )
