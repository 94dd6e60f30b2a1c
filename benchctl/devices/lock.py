"""One holder per device: a lock file per device, held while a command has the device open.

The holder writes who it is (command, pid, since) into the lock file, so a second user is told who holds the
device and `benchctl laser off` can reach the holder. The lock is an flock: the kernel drops it when the
holding process ends, however it ends (kill -9 included), so a stale file never blocks anyone.

Lock files live in $BENCHCTL_LOCK_DIR, else $XDG_RUNTIME_DIR/benchctl/locks, else a per-user folder in the
temporary directory. Several users sharing one bench point BENCHCTL_LOCK_DIR at one folder they can all write.

POSIX only, on purpose: the lock is half of the emergency stop (`benchctl laser off` reads the holder's pid here
and sends it SIGTERM, which the holder turns into emission off, benchctl.devices.safety). Windows has no SIGTERM a
process can handle (os.kill there is TerminateProcess, which skips every cleanup and would leave a laser
emitting), so a portable lock alone would promise a safety that benchctl cannot keep on Windows. Port names such
as COM3 are only pyserial URLs to this module: a key like any other.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import BinaryIO

from benchctl.devices.errors import DeviceBusy
from benchctl.files import ensure_dir

LOCK_ENV = "BENCHCTL_LOCK_DIR"
_command = Path(sys.argv[0]).name or "python"


def lock_dir() -> Path:
    """The folder holding the device lock files (created on demand)."""
    if os.environ.get(LOCK_ENV):
        return Path(os.environ[LOCK_ENV])
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "benchctl" / "locks"
    return Path(tempfile.gettempdir()) / f"benchctl-locks-{os.getuid()}"


def set_command(command: str) -> None:
    """How this process is named to other users of a device it holds, e.g. "benchctl run"."""
    global _command
    _command = command


@dataclass(frozen=True)
class Holder:
    """Who holds a device, as its lock file says."""

    command: str
    pid: int
    since: str

    def __str__(self) -> str:
        return f"held by `{self.command}` (pid {self.pid}) since {self.since}"


class DeviceHeld(DeviceBusy):
    """Another process holds the device's lock; `holder` says who (None if it has not written that yet)."""

    def __init__(self, message: str, holder: Holder | None) -> None:
        super().__init__(message)
        self.holder = holder


class DeviceLock:
    """Exclusive hold on one device, named by `key` (its port, device file or USB id), for as long as it is open.
    `label` names the device in messages ("SLM (framebuffer /dev/fb1)")."""

    def __init__(self, key: str, label: str) -> None:
        slug = re.sub(r"[^A-Za-z0-9._-]+", "_", key).strip("_")[-60:]
        digest = hashlib.sha256(key.encode()).hexdigest()[:10]
        self.key = key
        self.label = label
        self.path = lock_dir() / f"{slug}-{digest}.lock"
        self._handle: BinaryIO | None = None

    @property
    def held(self) -> bool:
        """Whether this object holds the lock now."""
        return self._handle is not None

    def acquire(self) -> DeviceLock:
        """Take the lock and record this process as its holder; DeviceHeld (saying who holds it) if taken."""
        if self._handle is not None:
            return self
        ensure_dir(self.path.parent)
        handle = open(self.path, "a+b")
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            holder = self.holder()
            raise DeviceHeld(f"{self.label} busy: {holder or 'held by another program'}", holder) from None
        handle.truncate(0)
        handle.write(json.dumps({"command": _command, "pid": os.getpid(),
                                 "since": datetime.now().isoformat(timespec="seconds")}).encode())
        handle.flush()
        self._handle = handle
        return self

    def release(self) -> None:
        """Give the lock up (idempotent)."""
        handle, self._handle = self._handle, None
        if handle is not None:
            handle.truncate(0)
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
            handle.close()

    def holder(self) -> Holder | None:
        """Who holds the lock according to its file (None: nobody, or the holder has not written it yet)."""
        try:
            data = json.loads(self.path.read_bytes() or b"null")
            return Holder(str(data["command"]), int(data["pid"]), str(data["since"])) if data else None
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def wait_free(self, timeout_s: float, poll_s: float = 0.05) -> bool:
        """Wait until nobody holds the lock (True) or `timeout_s` passed (False); takes nothing."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.acquire()
            except DeviceHeld:
                if time.monotonic() >= deadline:
                    return False
                time.sleep(poll_s)
            else:
                self.release()
                return True

    def __enter__(self) -> DeviceLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
