"""Lookup-table files: the measured gray -> phase response of the SLM at one wavelength.

Calibration measures one table per laser channel and writes it with `save_lut`; the profile names it
(`[slm.lut] red = "luts/red.csv"`). Accepted files:

- CSV / TXT, one phase in radians per line, 2^bit_depth lines in gray order;
- CSV / TXT, two columns `gray,phase` (any order, every gray exactly once; a header line is allowed);
- NPY, a 1-D array of 2^bit_depth phases.

Blank lines and `#` comments are ignored; columns may be separated by commas, semicolons or white space.
Every error names the file and the line (or array index) at fault. The tables become `PhaseLUT`s, the one
phase <-> gray mapping (benchctl.optics.phase_encoding).
"""

from __future__ import annotations

import io
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from benchctl.errors import BenchctlError
from benchctl.files import atomic_write_bytes, ensure_dir, read_capped
from benchctl.optics.phase_encoding import PhaseLUT
from benchctl.profiles import SLMConfig

TEXT_SUFFIXES = (".csv", ".txt")
_SEPARATORS = re.compile(r"[,;\s]+")


def load_lut(path: str | Path, bit_depth: int) -> PhaseLUT:
    """Read a gray -> phase table for an SLM with `bit_depth`-bit gray levels (formats: module docstring)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        return _load_npy(path, 1 << bit_depth)
    if suffix in TEXT_SUFFIXES:
        return _load_text(path, 1 << bit_depth)
    raise BenchctlError(f"{path}: unknown lookup-table format {path.suffix!r} (use .csv, .txt or .npy)")


def save_lut(path: str | Path, lut: PhaseLUT) -> Path:
    """Write `lut` as a two-column `gray,phase_rad` CSV, atomically; floats round-trip exactly."""
    path = Path(path)
    if path.suffix.lower() not in TEXT_SUFFIXES:
        raise BenchctlError(f"{path}: lookup tables are saved as CSV; name the file .csv")
    lines = ["gray,phase_rad"] + [f"{gray},{phase!r}" for gray, phase in enumerate(lut.phases.tolist())]
    ensure_dir(path.parent)
    return atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


def lut_for(config: SLMConfig, channel: str) -> PhaseLUT:
    """The table the SLM uses for `channel`: the profile's file for it, else linear with `two_pi_gray`."""
    path = config.lut.get(channel)
    if path is None:
        return PhaseLUT.linear(config.bit_depth, config.two_pi_gray)
    return load_lut(path, config.bit_depth)


def _read(path: Path) -> bytes:
    try:
        return read_capped(path, "lookup table")
    except FileNotFoundError as exc:
        raise BenchctlError(f"{path}: cannot read lookup table: {exc.strerror or exc}") from None


def _load_npy(path: Path, levels: int) -> PhaseLUT:
    try:
        array = np.load(io.BytesIO(_read(path)), allow_pickle=False)
    except ValueError as exc:
        raise BenchctlError(f"{path}: not a readable .npy lookup table ({exc})") from None
    if array.ndim != 1 or array.dtype.kind not in "iuf":
        raise BenchctlError(
            f"{path}: expected a 1-D array of {levels} phases in radians, got shape {array.shape} {array.dtype}"
        )
    _check_count(path, array.size, levels)
    return _table(path, array.astype(np.float64), lambda gray: f"index {gray}")


def _load_text(path: Path, levels: int) -> PhaseLUT:
    try:
        text = _read(path).decode()
    except UnicodeDecodeError:
        raise BenchctlError(f"{path}: not a text file (a lookup table is CSV/TXT or .npy)") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        content = line.split("#", 1)[0].strip()
        if content:
            rows.append((number, _SEPARATORS.split(content)))
    if rows and not any(_is_float(field) for field in rows[0][1]):
        rows.pop(0)  # a header: no field is a number
    if not rows:
        raise BenchctlError(f"{path}: no phases in lookup table (expected {levels}, one per gray level)")
    columns = len(rows[0][1])
    if columns not in (1, 2):
        raise BenchctlError(f"{path}: line {rows[0][0]}: expected 1 column (phase) or 2 (gray, phase), got {columns}")
    values = []
    for number, fields in rows:
        if len(fields) != columns:
            raise BenchctlError(
                f"{path}: line {number}: expected {columns} columns like the first row, got {len(fields)}"
            )
        if not _is_float(fields[-1]):
            raise BenchctlError(f"{path}: line {number}: phase {fields[-1]!r} is not a number")
        values.append(float(fields[-1]))
    if columns == 1:
        _check_count(path, len(values), levels)
        line_of = [number for number, _ in rows]
    else:
        order = _gray_order(path, rows, levels)
        values = [values[i] for i in order]
        line_of = [rows[i][0] for i in order]
    return _table(path, np.array(values), lambda gray: f"line {line_of[gray]}")


def _gray_order(path: Path, rows: list[tuple[int, list[str]]], levels: int) -> list[int]:
    """Row index holding each gray level 0..levels-1 of a two-column table (every level exactly once)."""
    row_of: dict[int, int] = {}
    for index, (number, fields) in enumerate(rows):
        try:
            gray = int(fields[0])
        except ValueError:
            raise BenchctlError(f"{path}: line {number}: gray level {fields[0]!r} is not an integer") from None
        if not 0 <= gray < levels:
            raise BenchctlError(f"{path}: line {number}: gray level {gray} outside 0..{levels - 1}")
        if gray in row_of:
            first = rows[row_of[gray]][0]
            raise BenchctlError(f"{path}: line {number}: gray level {gray} again (first on line {first})")
        row_of[gray] = index
    missing = [gray for gray in range(levels) if gray not in row_of]
    if missing:
        shown = ", ".join(map(str, missing[:8])) + (", ..." if len(missing) > 8 else "")
        raise BenchctlError(f"{path}: {len(missing)} of {levels} gray levels missing: {shown}")
    return [row_of[gray] for gray in range(levels)]


def _check_count(path: Path, count: int, levels: int) -> None:
    if count != levels:
        raise BenchctlError(
            f"{path}: {count} phases, expected {levels} (one per gray level of a {levels.bit_length() - 1}-bit SLM)"
        )


def _table(path: Path, phases: np.ndarray, where: Callable[[int], str]) -> PhaseLUT:
    """The PhaseLUT of `phases` (indexed by gray), with file errors located by `where(gray)`."""
    bad = np.flatnonzero(~np.isfinite(phases))
    if bad.size:
        gray = int(bad[0])
        raise BenchctlError(f"{path}: {where(gray)}: phase of gray {gray} is {phases[gray]}")
    drops = np.flatnonzero(np.diff(phases) < 0)
    if drops.size:
        gray = int(drops[0]) + 1
        raise BenchctlError(
            f"{path}: {where(gray)}: phase of gray {gray} ({phases[gray]:.6g} rad) is below that of gray {gray - 1} "
            f"({phases[gray - 1]:.6g} rad); the table must be non-decreasing (unwrapped)"
        )
    return PhaseLUT(phases)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
