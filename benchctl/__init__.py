"""benchctl: holographic-display experiments on an optical bench, real or simulated."""

from benchctl.provenance import release_version

__version__ = release_version()
