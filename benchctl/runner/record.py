"""The run record: a run folder's start and stop records, its step log and how a run is resumed (what lies where
in the folder: `runner.layout`).

Every file is written atomically and every step-log line is on disk before the next action. A folder is never
reused for a new run; `open_run` reopens one to resume it: it repairs a log line cut by a crash, and a step
recorded as finished is never run again unless a file it captured for later steps no longer matches its checksum.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shutil
import sys
from dataclasses import dataclass, field
from datetime import datetime
from importlib import metadata
from pathlib import Path, PurePosixPath
from typing import Any

import msgspec

from benchctl.devices.lock import DeviceHeld, DeviceLock
from benchctl.errors import BenchctlError
from benchctl.files import RECORD_BYTES, atomic_write_bytes, ensure_dir, file_sha256, read_capped, write_json
from benchctl.provenance import code_identity
from benchctl.runner.layout import RUN_FILE, STEP_LOG
from benchctl.schema import decode, fail

PACKAGES = ("benchctl", "torch", "numpy", "pyserial", "pyusb", "opencv-contrib-python-headless", "rawpy")


def package_versions() -> dict[str, object]:
    """Versions of Python and of the packages a run's numbers depend on, and which benchctl code ran."""
    versions: dict[str, object] = {"python": platform.python_version(), "benchctl_code": code_identity()}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def _now() -> str:
    return datetime.now().isoformat(timespec="milliseconds")


RUN_FOLDER = re.compile(r"\d{8}-\d{6}-[A-Za-z0-9_.-]+")  # create_run's names: <YYYYmmdd-HHMMSS>-<name>[-<n>]
Checksums = dict[str, str]  # run-relative path -> SHA-256


class _Record(msgspec.Struct, frozen=True, kw_only=True):
    """What benchctl reads back from a run's records to resume it, checked before use (unlike a configuration
    `Model`, further keys are allowed and kept as they are: only these are interpreted)."""


class StartRecord(_Record, frozen=True, kw_only=True):
    """run.json, as a resume reads it."""

    procedure_file: str | None = None  # the procedure as used, a file of the run folder (a resume needs both)
    profile_path: str | None = None
    procedure_sha256: Checksums = {}
    calibration_sha256: Checksums = {}
    resumed: list[dict[str, Any]] = []


class StepResult(_Record, frozen=True, kw_only=True):
    checksums: Checksums = {}  # files later steps read
    archived: Checksums = {}  # files kept only as a record


class Event(_Record, frozen=True, kw_only=True):
    """One line of steps.jsonl."""

    event: str
    step: str | None = None  # every event but "calibration" names its step
    attempt: int = 1
    result: StepResult = StepResult()
    checksums: Checksums = {}  # a "calibration" event's files
    replaces: bool = False  # a "calibration" event's files are all the copy has (a new copy)
    redo: str | None = None
    diverged: bool = False


def _checked(data: Any, model: type[_Record], where: Path) -> None:
    """`data` (a JSON value read from a run's record) checked against `model`: one line naming the file, the key and
    the value when it is not an object of that shape, or when a checksum names a file outside the run folder."""
    if not isinstance(data, dict):
        raise fail(where, "(top level)", f"expected a JSON object {{...}}, got {type(data).__name__}")
    checked = decode(data, model, where)
    tables = {"": checked} if not isinstance(checked, Event) else {"": checked, "result.": checked.result}
    for prefix, part in tables.items():
        for key in ("checksums", "archived", "procedure_sha256", "calibration_sha256"):
            for name in getattr(part, key, {}):
                pure = PurePosixPath(name)
                if not name or pure.is_absolute() or ".." in pure.parts or "\\" in name:
                    raise fail(where, f"{prefix}{key}", f"{name!r} is not a file inside the run folder")
    name = checked.procedure_file if isinstance(checked, StartRecord) else None
    if name is not None and (Path(name).name != name or name in ("", ".", "..")):
        raise fail(where, "procedure_file", f"{name!r} is not a file name of the run folder")


@dataclass
class RunRecord:
    """An open run folder: paths inside it, the step log, the start and stop records."""

    folder: Path
    done: dict[str, dict[str, Any]] = field(default_factory=dict)  # finished step key -> its result
    attempts: dict[str, int] = field(default_factory=dict)  # step key -> times it was started
    invalidated: list[str] = field(default_factory=list)  # why finished steps must be re-done (open_run)
    damaged: list[str] = field(default_factory=list)  # records found changed, their steps standing (open_run)
    divergences: dict[str, int] = field(default_factory=dict)  # step key -> times a later step found it diverged
    calibration: dict[str, str] = field(default_factory=dict)  # the run's calibration copy: file name -> SHA-256

    @property
    def name(self) -> str:
        return self.folder.name

    def path(self, *parts: str) -> Path:
        """A path inside the run folder (parent folders are created)."""
        target = self.folder.joinpath(*parts)
        ensure_dir(target.parent)
        return target

    def info(self) -> dict[str, Any]:
        """The start (and stop) record: a JSON object (BenchctlError naming the file when it is not one)."""
        path = self.folder / RUN_FILE
        try:
            data = json.loads(read_capped(path, "run record"))
        except FileNotFoundError:
            raise BenchctlError(f"{self.folder}: not a benchctl run folder (no {RUN_FILE})") from None
        except ValueError as exc:  # not UTF-8, or not JSON
            raise BenchctlError(f"{path}: not a run record (JSON): {exc}") from None
        if not isinstance(data, dict):
            raise fail(path, "(top level)", f"expected a JSON object {{...}}, got {type(data).__name__}")
        return data

    def finish(self, status: str, **extra: Any) -> None:
        """Write the stop record: "finished", "failed" or "interrupted", with when and anything else given."""
        info = self.info()
        info["stop"] = {"status": status, "time": _now(), **extra}
        write_json(self.folder / RUN_FILE, info)

    # -- the step log -----------------------------------------------------------------------------------------

    def is_done(self, key: str) -> bool:
        return key in self.done

    def result(self, key: str) -> dict[str, Any]:
        """The result a finished step recorded; an error if it has not finished. A key the reader needs and the
        result lacks (a damaged or hand-made step log) is one line naming the step and the key."""
        try:
            return Recorded(self.done[key], f"{self.folder / STEP_LOG}: step {key!r}")
        except KeyError:
            raise BenchctlError(f"{self.folder}: step {key!r} has not finished") from None

    def started(self, key: str) -> int:
        """Log that `key` starts; returns which attempt this is (1 for the first)."""
        self.attempts[key] = self.attempts.get(key, 0) + 1
        self._log({"event": "start", "step": key, "attempt": self.attempts[key]})
        return self.attempts[key]

    def finished(self, key: str, seconds: float, result: dict[str, Any]) -> None:
        self.done.pop(key, None)  # keeps `done` in the order steps last finished
        self.done[key] = result
        self._log({"event": "done", "step": key, "seconds": round(seconds, 4), "result": result})

    def failed(self, key: str, seconds: float, error: BaseException, redo: str | None = None,
               diverged: bool = False) -> None:
        """Log that `key` failed; `redo`: the step the run goes back to (`invalidate`), `diverged` counted for it."""
        kind = "interrupted" if isinstance(error, KeyboardInterrupt) else "failed"
        extra = {"redo": redo, "diverged": diverged} if redo is not None else {}
        if redo is not None and diverged:
            self.divergences[redo] = self.divergences.get(redo, 0) + 1
        self._log({"event": kind, "step": key, "seconds": round(seconds, 4),
                   "error": f"{type(error).__name__}: {error}", **extra})

    def invalidate(self, key: str, reason: str) -> list[str]:
        """Log finished step `key`, and every step that finished after it (it may have used its work), "invalid", so
        they are done again. Returns the keys (none if `key` has not finished)."""
        steps = list(self.done)
        later = steps[steps.index(key):] if key in self.done else []
        for step in later:
            del self.done[step]
            self._log({"event": "invalid", "step": step, "reason": reason if step == key else
                       f"step {step!r} finished after {key!r}, which is done again"})
        return later

    def writer_of(self, relative: str) -> tuple[str, str] | None:
        """(step key, SHA-256) of the finished step that recorded the file `relative` for later steps to read (result
        "checksums"); None if none did."""
        for key in reversed(self.done):
            digest = self.done[key].get("checksums", {}).get(relative)
            if digest is not None:
                return key, digest
        return None

    def calibration_written(self, checksums: dict[str, str], step: str | None = None, replace: bool = False) -> None:
        """Record the SHA-256 of each file of the run's calibration copy as the run wrote it (in the start record when
        no step has run yet, else in the step log, under `step`: the step that wrote it): a resume refuses a copy that
        changed since (`changed_calibration`). `replace`: these are all the copy's files now (a new copy)."""
        if replace:
            self.calibration.clear()
        self.calibration.update(checksums)
        if not self.attempts:
            info = self.info()
            info["calibration_sha256"] = dict(self.calibration)
            write_json(self.folder / RUN_FILE, info)
        else:
            self._log({"event": "calibration", "step": step, "checksums": checksums, "replaces": replace})

    def changed_calibration(self, folder: Path) -> str | None:
        """Why the first file of the calibration copy in `folder` differs from what the run wrote (None: none)."""
        return _damaged(folder, self.calibration, "the run wrote it")

    def recheck_files(self) -> list[str]:
        """Compare the files finished steps captured for later steps to read with the checksums they recorded
        (result "checksums": run-relative path -> SHA-256). The first step with a missing or changed file, and
        every step that finished after it (it may have used the file), is logged "invalid" and so re-done.
        Returns why."""
        for key in list(self.done):
            problem = _damaged(self.folder, self.done[key].get("checksums", {}))
            if problem:
                reason = f"step {key!r}: {problem}; it is done again"
                return [reason] + [f"step {later!r} finished after it; it is done again"
                                   for later in self.invalidate(key, reason)[1:]]
        return []

    def recheck_records(self) -> list[str]:
        """Compare the files finished steps kept only as a record (result "archived": path -> SHA-256, read by no
        later step, as a CITL iteration's RAW frames) with their checksums. A changed one is logged "damaged"
        and reported; its step stands, since re-doing it could not reproduce what the record recorded."""
        notes = []
        for key, result in self.done.items():
            problem = _damaged(self.folder, result.get("archived", {}))
            if problem:
                note = f"step {key!r}: {problem}; only a record, read by no later step: the step stands"
                self._log({"event": "damaged", "step": key, "reason": note})
                notes.append(note)
        return notes

    def events(self) -> list[dict[str, Any]]:
        """Every logged event, in order."""
        return _read_log(self.folder / STEP_LOG)

    def _log(self, event: dict[str, Any]) -> None:
        """Append one event line and flush it to disk: the log survives a crash right after the event."""
        line = json.dumps({"time": _now(), **event}, default=str) + "\n"
        with open(self.folder / STEP_LOG, "a", encoding="utf-8") as log:
            log.write(line)
            log.flush()
            os.fsync(log.fileno())


class Recorded(dict[str, Any]):
    """A step's recorded result as later steps read it: a missing key, at any depth, is a BenchctlError naming the
    step log, the step and the key (a KeyError traceback before)."""

    def __init__(self, data: dict[str, Any], where: str) -> None:
        super().__init__(data)
        self._where = where

    def __getitem__(self, name: str) -> Any:
        value = super().__getitem__(name)
        return Recorded(value, f"{self._where}, {name!r}") if isinstance(value, dict) else value

    def __missing__(self, name: str) -> Any:
        raise BenchctlError(f"{self._where}: no {name!r} in its recorded result: the step log is damaged (start the "
                            "run anew)")


def _damaged(folder: Path, checksums: dict[str, str], when: str = "it was written") -> str | None:
    """Why the first of `checksums`' files (relative to `folder`) is missing or changed; None if all match."""
    for name, digest in checksums.items():
        problem = file_problem(folder / name, digest, when)
        if problem:
            return f"{name}{problem}"
    return None


def file_problem(path: Path, digest: str, when: str = "it was written") -> str | None:
    """What is wrong with `path` against its recorded SHA-256 (': No such file...', ' changed since ...'); None if it
    matches."""
    try:
        actual = file_sha256(path)
    except OSError as exc:
        return f": {exc.strerror or exc}"
    if actual != digest:
        return f" changed since {when} (SHA-256 {actual[:12]}..., recorded {digest[:12]}...)"
    return None


def repair_log(path: Path) -> Path | None:
    """Make a step log end at a line boundary again after a crash cut its last line: a complete event that only
    lost its newline gets it back; a cut event is moved to `<log>.cut-<n>` (kept, never deleted) and removed from
    the log. Returns where the cut part went (None if there was none)."""
    try:
        data = read_capped(path, "step log", RECORD_BYTES)
    except FileNotFoundError:
        return None
    if not data or data.endswith(b"\n"):
        return None
    start = data.rfind(b"\n") + 1
    tail = data[start:]
    try:
        complete = isinstance(json.loads(tail), dict)
    except ValueError:  # a cut JSON text, or bytes cut inside a UTF-8 character
        complete = False
    with open(path, "r+b") as log:
        if complete:
            log.seek(0, os.SEEK_END)
            log.write(b"\n")
            aside = None
        else:
            aside = _unused(path.with_name(f"{path.name}.cut"))
            atomic_write_bytes(aside, tail)
            log.truncate(start)
        log.flush()
        os.fsync(log.fileno())
    return aside


def _unused(path: Path) -> Path:
    """`path` with the first suffix -1, -2, ... that names no file yet."""
    number = 1
    while path.with_name(f"{path.name}-{number}").exists():
        number += 1
    return path.with_name(f"{path.name}-{number}")


def _read_log(path: Path) -> list[dict[str, Any]]:
    """The events of a step log, each checked (`Event`); a last line cut short by a crash is ignored."""
    if not path.is_file():
        return []
    events = []
    lines = read_capped(path, "step log", RECORD_BYTES).splitlines()
    for number, line in enumerate(lines, 1):
        try:
            event = json.loads(line)
        except ValueError:  # not JSON, or not UTF-8
            if number < len(lines):
                raise BenchctlError(f"{path}: line {number} is not a JSON event; the step log is damaged") from None
            continue
        _checked(event, Event, Path(f"{path}, line {number}"))
        if event["event"] != "calibration" and event.get("step") is None:
            raise fail(Path(f"{path}, line {number}"), "step", "missing: a step's event names its step")
        events.append(event)
    return events


def create_run(out: Path, name: str, start: dict[str, Any], files: dict[str, bytes]) -> RunRecord:
    """A new run folder `out/<timestamp>-<name>` (a suffix -2, -3, ... if that exists; never reused) with the
    start record and the given files (profile and procedure as used)."""
    ensure_dir(out)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    safe = "".join(c if c.isalnum() or c in "-_." else "-" for c in name) or "run"
    for suffix in range(1, 1000):
        folder = out / (f"{stamp}-{safe}" + (f"-{suffix}" if suffix > 1 else ""))
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        except OSError as exc:
            raise BenchctlError(f"cannot create run folder {folder}: {exc.strerror or exc}") from None
        break
    else:
        raise BenchctlError(f"{out}: cannot create a new run folder for {name!r}")
    record = RunRecord(folder)
    for file_name, data in files.items():
        atomic_write_bytes(record.path(file_name), data)
    write_json(folder / RUN_FILE, {
        "name": name, "start": _now(), "command": sys.argv, "host": platform.node(),
        "versions": package_versions(), "resumed": [], **start,
    })
    return record


def open_run(folder: Path) -> RunRecord:
    """Reopen a run folder to resume it: its finished steps and attempt counts come from the step log."""
    folder = Path(folder)
    if not (folder / RUN_FILE).is_file():
        raise BenchctlError(f"{folder}: not a benchctl run folder (no {RUN_FILE})")
    record = RunRecord(folder)
    _checked(record.info(), StartRecord, folder / RUN_FILE)
    repair_log(folder / STEP_LOG)
    record.calibration.update(record.info().get("calibration_sha256", {}))
    for event in record.events():
        if event.get("event") == "calibration":  # written by a step, or (step None) between steps
            if event.get("replaces"):
                record.calibration.clear()
            record.calibration.update(event.get("checksums", {}))
            continue
        key = event["step"]  # every other event of the step log names its step
        if event.get("event") == "start":
            record.attempts[key] = max(record.attempts.get(key, 0), int(event.get("attempt", 1)))
        elif event.get("event") == "done":
            record.done.pop(key, None)  # keeps `done` in the order steps last finished
            record.done[key] = event.get("result", {})
        elif event.get("event") == "invalid":
            record.done.pop(key, None)
        if event.get("diverged") and event.get("redo"):
            record.divergences[event["redo"]] = record.divergences.get(event["redo"], 0) + 1
    record.invalidated = record.recheck_files()
    record.damaged = record.recheck_records()
    info = record.info()
    info.setdefault("resumed", []).append({"time": _now(), "command": sys.argv, "finished_steps": len(record.done)})
    info.pop("stop", None)
    write_json(folder / RUN_FILE, info)
    return record


def run_folder_lock(folder: Path) -> DeviceLock:
    """The lock that gives a run folder one writer (a device lock, keyed by the folder's resolved path: released by
    the kernel when the holder ends, however it ends); taken, or BenchctlError naming who holds it."""
    lock = DeviceLock(f"run:{Path(folder).resolve()}", f"run folder {folder}")
    try:
        return lock.acquire()
    except DeviceHeld as exc:
        holder = exc.holder or "by another process"
        raise BenchctlError(f"{folder}: this run is being written already, {holder}; a run folder has one writer: "
                            "wait for it to end, or stop it") from None


def set_aside(folder: Path) -> Path | None:
    """Move what an unfinished attempt left in `folder` to `<folder>.attempt-<n>`, the first n free (kept, never
    deleted), so the next attempt starts clean. Returns where it went, or None if there was nothing."""
    if not folder.exists() or not any(folder.iterdir()):
        return None
    target = _unused(folder.with_name(f"{folder.name}.attempt"))
    shutil.move(str(folder), str(target))
    return target

