"""The capture button: RAW frames of what the bench shows now, into a new run folder with the settings beside them.

A capture is a run folder like any (`runner.record`: `<root>/<timestamp>-capture/`, `-2`, `-3`, ... when that name
exists; created, never reused), so `benchctl runs` lists it and `runs remove` removes it: `run.json` names the
procedure "console capture" and the profile and ends with its stop record, `steps.jsonl` holds its one step with the
SHA-256 of every file it wrote and its headline, and the folder is locked while it is written. It holds the RAW
frames exactly as the camera delivered them (`frame-000.dng`, ...), the SLM frame as displayed (`slm-frame.png`) and
`settings.json`: the laser channels as read back, what the SLM shows and how it encodes, the camera's identity and
capture settings, the profile and benchctl's version.
"""

from __future__ import annotations

import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

import benchctl
from benchctl.devices.camera import Camera
from benchctl.files import file_sha256, write_json
from benchctl.images import write_png
from benchctl.profiles import Profile
from benchctl.runner.record import create_run, run_folder_lock

PROCEDURE = "console capture"  # what `benchctl runs` lists as its procedure
STEP = "capture"


def capture(root: Path, profile: Profile, camera: Camera, frames: int | None, settings: dict[str, Any],
            slm_frame: np.ndarray | None) -> dict[str, Any]:
    """Capture into a new run folder under `root`; `settings` (laser, SLM) are written with the camera's own.
    Returns what was written."""
    record = create_run(root, "capture", {"procedure": PROCEDURE, "profile": profile.name,
                                          "profile_path": str(profile.path)}, {})
    started = time.monotonic()
    with run_folder_lock(record.folder):
        record.started(STEP)
        try:
            captured = camera.capture(record.folder, frames, stem="frame")
            write_json(record.folder / "settings.json", {
                **settings,
                "camera": {**camera.identity(), "exposure_s": camera.config.exposure_s, "iso": camera.config.iso,
                           "frames": [{"file": frame.path.name if frame.path else None,
                                       "camera_file": frame.file_name, "format": frame.format,
                                       "bytes": len(frame.data), **frame.metadata} for frame in captured]},
                "benchctl_version": benchctl.__version__,
                "captured": datetime.now().isoformat(timespec="milliseconds"),
            })
            if slm_frame is not None:
                write_png(record.folder / "slm-frame.png", slm_frame)
        except BaseException as exc:
            record.failed(STEP, time.monotonic() - started, exc)
            record.finish("interrupted" if isinstance(exc, KeyboardInterrupt) else "failed", error=str(exc))
            raise
        files = sorted(path.name for path in record.folder.iterdir() if path.name.startswith(("frame-", "slm-",
                                                                                               "settings")))
        headline = [f"{len(captured)} RAW frame(s) from the console"]
        record.finished(STEP, time.monotonic() - started, {
            "headline": headline, "sha256": {name: file_sha256(record.folder / name) for name in files}})
        record.finish("finished")
    return {"folder": str(record.folder), "files": files}
