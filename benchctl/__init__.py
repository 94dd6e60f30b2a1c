"""benchctl: holographic-display experiments on an optical bench, real or simulated."""

from pathlib import Path
from typing import Any

SOURCE_ROOT = Path(__file__).resolve().parent.parent
"""The folder that holds the package: in a source checkout the repository, whose hardware_profiles/ and
checkpoints/ are found after the working folder's."""


def __getattr__(name: str) -> Any:
    """`benchctl.__version__`, read from the installed metadata only when asked (it costs an import that the
    emergency `benchctl laser off` should not pay)."""
    if name == "__version__":
        from benchctl.provenance import release_version

        return release_version()
    raise AttributeError(f"module 'benchctl' has no attribute {name!r}")
