"""Writing result files so that a crash never leaves a half-written one (temp file in the same folder, then rename),
and reading a user's file with a size cap (a named device or an endless file is refused, never read until memory
runs out)."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import stat
import tempfile
from pathlib import Path
from typing import Any, Iterable, Mapping

from benchctl.errors import BenchctlError

_UMASK = os.umask(0)
os.umask(_UMASK)


# Settings and records a user names or edits: profiles, procedures, calibration files, run records. The largest
# shipped is a few kB; a run's step log grows by about 1 kB a step (its own, larger cap: RECORD_BYTES).
TEXT_BYTES = 16 * 2**20
RECORD_BYTES = 1 << 30
# Images and RAW frames: 64 Mpx (limits.MAX_PIXELS) of 16-bit RGBA stored uncompressed is 512 MiB.
IMAGE_BYTES = 1 << 30


def read_capped(path: str | Path, what: str, limit: int = TEXT_BYTES) -> bytes:
    """The bytes of the file at `path` (a `what`: "hardware profile", "calibration", ...), at most `limit` of them:
    a device (/dev/zero) is refused unread, a larger file unread too, and an endless pipe once the cap is read; each
    a BenchctlError naming it. FileNotFoundError passes through (callers say what was not found); other OS errors are
    one line."""
    path = Path(path)
    too_large = BenchctlError(f"{path}: over {limit / 2**20:g} MiB, read no further ({what} files are smaller: is it "
                              "the file you meant?)")
    try:
        with open(path, "rb") as handle:
            info = os.fstat(handle.fileno())
            if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode):
                raise BenchctlError(f"{path}: is a device, not a file ({what} expected)")
            if stat.S_ISREG(info.st_mode) and info.st_size > limit:
                raise too_large
            data = handle.read(limit + 1)
    except FileNotFoundError:
        raise
    except IsADirectoryError:
        raise BenchctlError(f"{path}: is a folder, not a file ({what} expected)") from None
    except OSError as exc:
        raise BenchctlError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    if len(data) > limit:
        raise too_large
    return data


def ensure_dir(path: Path) -> Path:
    """Create `path` (and parents) or fail with a message that names it."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BenchctlError(f"cannot create output folder {path}: {exc.strerror or exc}") from None
    if not os.access(path, os.W_OK):
        raise BenchctlError(f"output folder {path} is not writable")
    return path


def folder_problem(path: Path) -> str | None:
    """Why folders cannot be created in (or as) `path`, found without writing anything: a file in its place or on
    its way, a folder that is not writable, or a file system without a disk (/proc, /sys); None if they can."""
    existing = Path(path)
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        return f"{existing} is a file, not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{existing} is not writable"
    try:
        stats = os.statvfs(existing)
    except OSError as exc:
        return f"{existing}: {exc.strerror or exc}"
    if stats.f_flag & os.ST_RDONLY:
        return f"{existing} is on a read-only file system"
    if stats.f_blocks == 0:
        return f"{existing} is on a file system without a disk (such as /proc or /sys)"
    return None


def atomic_write_bytes(path: Path, data: bytes, *, overwrite: bool = True) -> Path:
    """Write `data` to `path` atomically (readers see the old file or the new one, never a partial one).
    `overwrite=False`: an existing `path` is never replaced (BenchctlError naming it), even one created meanwhile."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise BenchctlError(f"cannot write {path}: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)  # fails if `path` exists, unlike a rename
            os.unlink(tmp)
    except FileExistsError:
        Path(tmp).unlink(missing_ok=True)
        raise BenchctlError(f"{path} exists; it is kept as it is (choose another name)") from None
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise BenchctlError(f"cannot write {path}: {exc.strerror or exc}") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json(path: Path, data: Any) -> Path:
    """Atomically write `data` as indented JSON (strict: a NaN or infinity is an error, never invalid JSON)."""
    try:
        text = json.dumps(data, indent=2, allow_nan=False)
    except ValueError as exc:
        raise BenchctlError(f"{path}: {exc} (a NaN or infinity cannot be written as JSON)") from None
    return atomic_write_bytes(path, (text + "\n").encode())


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, hex (what run records keep for every captured file)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_csv(path: Path, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Atomically write dict rows as CSV, columns in first-seen order."""
    rows = list(rows)
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return atomic_write_bytes(path, text.getvalue().encode())
