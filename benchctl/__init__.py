"""benchctl: holographic-display experiments on an optical bench, real or simulated."""

__version__ = "0.1.0"
