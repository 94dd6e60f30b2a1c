"""The run folder's layout: the one module that names what lies where in a run folder.

    runs/<YYYYmmdd-HHMMSS>-<name>/
      run.json          start record (procedure, versions, command) and, once it ends, the stop record
      profile.toml      the hardware profile as used (bytes copied)
      procedure.toml    the procedure as used (plus the .py file of a Python procedure)
      calibration/      the camera-SLM registration, lookup tables and fitted optical model the run used (their
                        SHA-256 in run.json and the step log: a resume refuses an edited copy); rejected/ holds what
                        the run measured but did not store (calibration.acceptance)
      devices.json      identity of every device the run opened
      steps.jsonl       one JSON line per event of the step log (`record.RunRecord`)
      holograms/        SLM frames exactly as displayed (8-bit PNG)
      raw/<step key>/   each exposure step's RAW frames (frame-000...) and dark frames (dark-000...), exactly as
                        the camera delivered them, never modified
      images/           decoded, registered and merged images (16-bit PNG) and arrays (.npy)
      state/            an iterative procedure's resumable state (CITL: phase and optimiser; each file's SHA-256
                        in the result of the step that wrote it)
      metrics.json, metrics.csv, report.html

Paths here are relative to the run folder, '/'-separated, as step results record them. Procedures never spell
them: the step builders and savers of the procedure API (`benchctl.runner.api`) place every file.
"""

from __future__ import annotations

from pathlib import PurePosixPath

RUN_FILE = "run.json"
PROFILE_COPY = "profile.toml"
PROCEDURE_COPY = "procedure.toml"
CALIBRATION_COPY = "calibration"
DEVICES = "devices.json"
STEP_LOG = "steps.jsonl"
METRICS_JSON = "metrics.json"
METRICS_CSV = "metrics.csv"
REPORT = "report.html"

HOLOGRAMS = "holograms"
RAW = "raw"
IMAGES = "images"
STATE = "state"


def _inside(folder: str, parts: tuple[str, ...]) -> str:
    for part in parts:
        if not part or part in (".", "..") or "\\" in part or part.startswith("/"):
            raise ValueError(f"{part!r} cannot name a file inside the run folder's {folder}/")
    return str(PurePosixPath(folder, *parts))


def hologram_file(*parts: str) -> str:
    """An SLM frame as displayed: holograms/<parts>."""
    return _inside(HOLOGRAMS, parts)


def raw_folder(step_key: str, within: str | None = None) -> str:
    """Where the exposure step `step_key` keeps its RAW frames: raw/<step key>/ (its '/' make sub-folders), or
    raw/<step key>/<within>/ for one of several exposures a step keeps."""
    return _inside(RAW, (*step_key.split("/"), *([within] if within is not None else [])))


def image_file(*parts: str) -> str:
    """A decoded, registered or merged image, or an array: images/<parts>."""
    return _inside(IMAGES, parts)


def state_file(*parts: str) -> str:
    """An iterative procedure's resumable state: state/<parts>."""
    return _inside(STATE, parts)
