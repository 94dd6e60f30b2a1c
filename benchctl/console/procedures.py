"""Procedures from the console: `benchctl run` in a child process, its dry run first, its steps followed live.

The console couples to the runner through the command line only (`benchctl run FILE --dry-run`, then
`benchctl run FILE`), so a run started here is exactly the run a shell starts: same plan, same run folder, same
safety on every exit path. Before the run starts the console lets go of its devices (one holder per device: the
run opens them itself) and takes them back when the run ends. Stop sends the run SIGTERM, on which the runner
switches emission off, records where it stopped and exits (`benchctl run --resume` finishes it later).
The page chooses a procedure by name among the files of the console's procedures folder, never by path, and the
console runs only what that folder holds: a file (or symbolic link) that leads outside it is not offered, and a TOML
whose `procedure` names a Python file outside it (an absolute path, `../`) is refused before its dry run, which
would import that file.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import Profile

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

DEVICES = ["laser", "slm", "camera"]
LINES_KEPT = 400
DRY_RUN_TIMEOUT_S = 300.0
_RUN_FOLDER = re.compile(r"^run folder: (?P<folder>.+)$")


class Procedures:
    """The procedure files offered, and the one run the console may have going."""

    def __init__(self, profile: Profile, folder: Path | None, out: Path, release: Callable[[list[str]], None],
                 reconnect: Callable[[], None], say: Callable[[str], None]) -> None:
        self.profile = profile
        self.folder = folder
        self.out = out
        self._release = release
        self._reconnect = reconnect
        self.say = say
        self.lines: deque[str] = deque(maxlen=LINES_KEPT)
        self.running: str | None = None
        self.run_folder: Path | None = None
        self.returncode: int | None = None
        self._process: subprocess.Popen[str] | None = None
        self._lock = threading.Lock()

    def files(self) -> dict[str, Path]:
        """Name -> file of every procedure in the console's procedures folder (.toml and .py; none that leads out
        of it)."""
        if self.folder is None or not self.folder.is_dir():
            return {}
        return {path.name: path for path in sorted(self.folder.iterdir())
                if path.suffix in (".toml", ".py") and path.is_file() and self._inside(path)}

    def _inside(self, path: Path) -> bool:
        assert self.folder is not None
        return path.resolve().is_relative_to(self.folder.resolve())

    def _file(self, name: str) -> Path:
        files = self.files()
        if name not in files:
            raise BadValueError(f"no procedure {name!r} in {self.folder} (known: {', '.join(files) or 'none'})")
        path = files[name]
        if path.suffix == ".toml":
            self._check_code_inside(path)
        return path

    def _check_code_inside(self, path: Path) -> None:
        """BadValueError when the TOML's `procedure` names a Python file outside the procedures folder (a TOML
        that cannot be read is left to the runner's dry run to explain)."""
        try:
            kind = tomllib.loads(path.read_text(encoding="utf-8")).get("procedure")
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            return
        if not isinstance(kind, str) or not (kind.endswith(".py") or "/" in kind or "\\" in kind):
            return  # a built-in procedure's name
        named = Path(kind)
        if named.is_absolute() or ".." in named.parts or not self._inside(path.parent / named):
            raise BadValueError(f"{path.name}: procedure = {kind!r} is outside the console's procedures folder "
                                f"{self.folder}: the console runs only what its folder holds")

    def _command(self, path: Path, *options: str) -> list[str]:
        return [sys.executable, "-m", "benchctl", "run", str(path), "--profile", str(self.profile.path), *options]

    def dry_run(self, name: str) -> list[str]:
        """The steps `benchctl run --dry-run` lists for procedure `name` (it opens no device)."""
        done = subprocess.run(self._command(self._file(name), "--dry-run"), capture_output=True, text=True,
                              timeout=DRY_RUN_TIMEOUT_S, env=_unbuffered())
        lines = (done.stdout + done.stderr).splitlines()
        if done.returncode != 0:
            raise BenchctlError(f"dry run of {name} failed: {lines[-1] if lines else done.returncode}")
        return lines

    def start(self, name: str) -> None:
        """Start procedure `name` after letting go of the devices; its output lines arrive in `lines`."""
        path = self._file(name)
        with self._lock:
            if self._process is not None and self._process.poll() is None:
                raise BenchctlError(f"procedure {self.running} is running; stop it first")
            self._release(DEVICES)
            self.lines.clear()
            self.running, self.run_folder, self.returncode = name, None, None
            self._process = subprocess.Popen(self._command(path, "--out", str(self.out)), stdout=subprocess.PIPE,
                                             stderr=subprocess.STDOUT, text=True, env=_unbuffered())
        self.say(f"procedure {name} started (pid {self._process.pid}); the console let go of its devices")
        threading.Thread(target=self._follow, args=(self._process,), name="console procedure", daemon=True).start()

    def _follow(self, process: subprocess.Popen[str]) -> None:
        assert process.stdout is not None
        for line in process.stdout:
            line = line.rstrip("\n")
            self.lines.append(line)
            match = _RUN_FOLDER.match(line)
            if match:
                self.run_folder = Path(match["folder"])
        self.returncode = process.wait()
        self.say(f"procedure {self.running} ended with exit code {self.returncode}; the console takes its devices "
                 "back")
        self._reconnect()

    def stop(self, wait_s: float = 30.0) -> None:
        """SIGTERM to the run (it switches emission off, records where it stopped and exits), then wait for it."""
        process = self._process
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            self.say(f"procedure {self.running} (pid {process.pid}) did not stop within {wait_s:g} s of SIGTERM")

    @property
    def active(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def report(self) -> Path | None:
        """The last run's report.html, once it exists."""
        path = self.run_folder / "report.html" if self.run_folder is not None else None
        return path if path is not None and path.is_file() else None

    def state(self) -> dict[str, Any]:
        return {"files": list(self.files()), "running": self.running if self.active else None,
                "last": self.running, "returncode": self.returncode,
                "folder": str(self.run_folder) if self.run_folder else None, "report": self.report() is not None,
                "lines": list(self.lines)[-60:]}


def _unbuffered() -> dict[str, str]:
    """The environment for a child benchctl whose output is followed line by line."""
    return {**os.environ, "PYTHONUNBUFFERED": "1"}
