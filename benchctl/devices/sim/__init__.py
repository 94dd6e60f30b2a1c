"""Simulated devices that speak the real protocols; their state persists between commands (see state.py)."""
