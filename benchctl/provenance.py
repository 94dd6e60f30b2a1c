"""Which code produced a result: the release version, a hash of the package's source, and the git state.

The release version comes from one place, the `version` in pyproject.toml, through the installed package's
metadata. It alone cannot tell an edited method from the released one, so results that are reused later
(the hologram cache) are keyed by `source_hash()`, which changes with any edit to any module, and run
records carry `code_identity()`, which adds the git commit and whether the work tree had local changes.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import subprocess
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent


def release_version() -> str:
    """The version pyproject.toml declares, as installed; "0+unknown" when benchctl runs uninstalled."""
    try:
        return importlib.metadata.version("benchctl")
    except importlib.metadata.PackageNotFoundError:
        return "0+unknown"


@functools.lru_cache(maxsize=1)
def source_hash() -> str:
    """SHA-256 (first 16 hex digits) over the path and bytes of every .py file of the package, in path order."""
    digest = hashlib.sha256()
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        digest.update(path.relative_to(PACKAGE_DIR).as_posix().encode() + b"\0")
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", *args], cwd=PACKAGE_DIR, capture_output=True, text=True, timeout=5,
                              check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.lru_cache(maxsize=1)
def code_identity() -> dict[str, object]:
    """Release version, source hash and, when the package lives in a git work tree, commit and dirty flag."""
    identity: dict[str, object] = {"version": release_version(), "source_sha256": source_hash()}
    commit = _git("rev-parse", "HEAD")
    if commit:
        status = _git("status", "--porcelain", "--untracked-files=no", "--", ".")
        identity["git_commit"] = commit
        identity["git_dirty"] = bool(status)
    return identity
