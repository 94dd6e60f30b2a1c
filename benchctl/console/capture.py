"""The capture button: RAW frames of what the bench shows now, into a new folder with the settings beside them.

`<root>/<timestamp>-capture/` (`-2`, `-3`, ... when that name exists: a folder is created, never reused) holds the
RAW frames exactly as the camera delivered them (`frame-000.dng`, ...), the SLM frame as displayed
(`slm-frame.png`) and `settings.json`: the laser channels as read back, what the SLM shows and how it encodes, the
camera's identity and capture settings, the profile and benchctl's version.
"""

from __future__ import annotations

import os
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

import benchctl
from benchctl.devices.camera import Camera
from benchctl.files import ensure_dir, write_json
from benchctl.images import write_png


def new_folder(root: Path, name: str) -> Path:
    """A folder `<root>/<timestamp>-<name>` created now; a suffix -2, -3, ... where one exists already."""
    ensure_dir(root)
    stem = f"{datetime.now().strftime('%Y%m%d-%H%M%S')}-{name}"
    for number in range(1, 1000):
        folder = root / (stem if number == 1 else f"{stem}-{number}")
        try:
            os.mkdir(folder)
        except FileExistsError:
            continue
        return folder
    raise FileExistsError(f"{root}: a thousand folders named {stem}-N exist")


def capture(root: Path, camera: Camera, frames: int | None, settings: dict[str, Any],
            slm_frame: np.ndarray | None) -> dict[str, Any]:
    """Capture into a new folder under `root`; `settings` (laser, SLM) are written with the camera's own. Returns
    what was written."""
    folder = new_folder(root, "capture")
    captured = camera.capture(folder, frames, stem="frame")
    record = {
        **settings,
        "camera": {**camera.identity(), "exposure_s": camera.config.exposure_s, "iso": camera.config.iso,
                   "frames": [{"file": frame.path.name if frame.path else None, "camera_file": frame.file_name,
                               "format": frame.format, "bytes": len(frame.data), **frame.metadata}
                              for frame in captured]},
        "benchctl_version": benchctl.__version__,
        "captured": datetime.now().isoformat(timespec="milliseconds"),
    }
    if slm_frame is not None:
        write_png(folder / "slm-frame.png", slm_frame)
    write_json(folder / "settings.json", record)
    return {"folder": str(folder), "files": sorted(path.name for path in folder.iterdir())}
