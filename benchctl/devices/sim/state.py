"""Where the simulated bench keeps its state between commands, the way hardware keeps it between connections.

One JSON file per simulated device in a folder a user can inspect (`benchctl sim status`) and clear
(`benchctl sim reset`): $BENCHCTL_SIM_DIR, else $XDG_STATE_HOME/benchctl/sim, else ~/.local/state/benchctl/sim.
A device that is open holds its lock (benchctl.devices.lock), so a second program opening it is told who holds it.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

from benchctl.devices.errors import DeviceError
from benchctl.devices.lock import DeviceLock
from benchctl.files import atomic_write_bytes, ensure_dir

STATE_ENV = "BENCHCTL_SIM_DIR"
CAMERA_STATE = "sim-camera"  # the simulated camera's file counter and faults
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


def state_dir() -> Path:
    """The folder holding the simulated devices' state (created on demand)."""
    if os.environ.get(STATE_ENV):
        return Path(os.environ[STATE_ENV])
    base = Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state")
    return base / "benchctl" / "sim"


def _checked(name: str) -> str:
    if not _NAME.match(name):
        raise DeviceError(f"simulated device name {name!r} must be letters, digits, '.', '_' or '-'")
    return name


def load_state(name: str) -> dict[str, Any]:
    """The saved state of simulated device `name` ({} if it has none yet)."""
    path = state_dir() / f"{_checked(name)}.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise DeviceError(f"{path}: simulator state unreadable ({exc}); `benchctl sim reset` clears it") from None


def save_state(name: str, state: dict[str, Any]) -> Path:
    """Atomically replace the saved state of simulated device `name`."""
    folder = ensure_dir(state_dir())
    return atomic_write_bytes(folder / f"{_checked(name)}.json", (json.dumps(state, indent=2) + "\n").encode())


def device_file(name: str) -> Path:
    """A path in the state folder for a device's bulk data (e.g. the frame a simulated SLM shows)."""
    return ensure_dir(state_dir()) / _checked(name)


def sim_lock(name: str, label: str | None = None) -> DeviceLock:
    """The lock of simulated device `name` (one per state folder: each folder is one simulated bench)."""
    return DeviceLock(f"sim:{state_dir().resolve()}/{_checked(name)}", label or f"simulated device {name!r}")


def list_states() -> dict[str, dict[str, Any]]:
    """Every simulated device's saved state, by name."""
    folder = state_dir()
    if not folder.is_dir():
        return {}
    return {path.stem: load_state(path.stem) for path in sorted(folder.glob("*.json"))}


def reset_states() -> list[Path]:
    """Forget every simulated device's state; returns what was removed."""
    folder = state_dir()
    removed = []
    if folder.is_dir():
        for path in sorted(folder.iterdir()):
            if path.is_file():
                path.unlink()
                removed.append(path)
    return removed
