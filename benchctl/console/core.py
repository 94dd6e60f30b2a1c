"""The console's one process: the devices it holds, the live view, the SLM patterns, captures and procedures.

Threads: the live view renders frames on its own thread while a page is open; laser status is read on another
twice a second, so a page's status request never waits for a device; commands and captures run on the server's
worker threads, each device used by one thread at a time (`Held`); holograms are computed in a worker process
(`holograms.HologramWorker`). The server's event loop only moves bytes.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchctl.console import capture, preview
from benchctl.console.devices import Held
from benchctl.console.laser import DEADMAN_S, LaserControl
from benchctl.console.procedures import Procedures
from benchctl.console.slm import Pattern, SlmControl
from benchctl.console.uploads import Uploads
from benchctl.devices.camera import Camera, open_camera
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import Profile

STATUS_PERIOD_S = 0.5
EVENTS_KEPT = 200


class Console:
    """Everything one `benchctl console` holds; `start()` connects, `close()` switches emission off and lets go."""

    def __init__(self, profile: Profile, out: Path, *, deadman_s: float = DEADMAN_S,
                 procedures_dir: Path | None = None) -> None:
        from benchctl.calibration.calibrated import Calibrated

        if profile.slm is not None and profile.optics is not None:
            profile = Calibrated.stored(profile).profile  # measured tables and fitted model, as a run
        self.profile = profile
        self.out = Path(out)
        self.events: deque[str] = deque(maxlen=EVENTS_KEPT)
        self.laser = LaserControl(profile, self.say, deadman_s) if profile.laser is not None else None
        self.uploads = Uploads()
        self.slm = (SlmControl(profile, self.uploads, self._checkpoints())
                    if profile.slm is not None and profile.optics is not None else None)
        self.camera: Held[Camera] | None = (Held("camera", lambda: open_camera(profile), Camera.close)
                                            if profile.camera is not None else None)
        self.procedures = Procedures(profile, procedures_dir, self.out, self._release_for_run, self._reconnect,
                                     self.say)
        self.view: dict[str, Any] = {"mode": "gamma", "zoom": None}
        self.job: dict[str, Any] = {"busy": None, "progress": None, "error": None, "started": None}
        self.laser_status: dict[str, Any] = self.laser.status() if self.laser else {"channels": []}
        self.preview_error: str | None = None
        self.latest: preview.Shown | None = None
        self.pages = 0
        self.keep_previewing = False  # render frames with no page open (benchmarks)
        self._seq = 0
        self._frame_times: deque[float] = deque(maxlen=30)
        self._listeners: list[Callable[[], object]] = []
        self._busy = threading.Lock()  # one long job (hologram, capture) at a time
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._preview_loop, name="console live view", daemon=True),
                         threading.Thread(target=self._status_loop, name="console laser status", daemon=True)]

    # -- life ------------------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Connect every device the profile has (one that is held elsewhere is said, not fatal), start the threads."""
        if self.laser is not None:
            self.laser.connect()
        for held in (self.slm.held if self.slm else None, self.camera):
            if held is not None and not held.connect():
                self.say(f"{held.name}: {held.error}")
        self._read_slm("at start")
        self.refresh_laser()
        for thread in self._threads:
            thread.start()
        self.say(f"console started on profile {self.profile.name!r}")

    def close(self) -> str | None:
        """Emission off and the laser closed first, then everything else; what the SLM shows stays. Returns None
        when emission is known to be off, else why it is not (to be said loudly: the laser may still emit)."""
        self._stop.set()
        self.procedures.stop(wait_s=15.0)
        unknown = None
        try:
            if self.laser is not None:
                self.laser.close()
                unknown = self.laser.unknown
            if self.procedures.active:
                unknown = f"procedure {self.procedures.running} still holds the laser after SIGTERM"
        finally:
            for held in (self.slm.held if self.slm else None, self.camera):
                if held is not None:
                    held.release()
            if self.slm is not None:
                self.slm.worker.close()
            for thread in self._threads:
                if thread.is_alive() and thread is not threading.current_thread():
                    thread.join(timeout=5.0)
            self.uploads.remove_all()
        return unknown

    def emergency_off(self) -> None:
        """Emission off and the laser let go now (a termination signal): `benchctl laser off` waits for that. A
        switch-off that cannot be confirmed is kept in `laser.unknown` for `close` to report."""
        if self.laser is not None:
            self.laser.close()

    def say(self, line: str) -> None:
        """Note an event (the page shows the latest ones)."""
        self.events.append(f"{datetime.now().strftime('%H:%M:%S')} {line}")

    # -- laser -----------------------------------------------------------------------------------------------------

    def _laser(self) -> LaserControl:
        if self.laser is None:
            raise BenchctlError(f"profile {self.profile.name!r} has no [laser]")
        return self.laser

    def set_power(self, channel: str, power: str) -> dict[str, Any]:
        try:
            watts = self._laser().set_power(channel, power)
        finally:
            self.refresh_laser()
        return {"setpoint_mw": round(watts * 1e3, 4)}

    def set_emission(self, channel: str, on: bool) -> None:
        try:
            self._laser().set_emission(channel, on)
        finally:
            self.refresh_laser()

    def all_off(self) -> None:
        try:
            self._laser().all_off()
        finally:
            self.refresh_laser()

    def emission_off(self) -> dict[str, Any]:
        """ALL OFF: a procedure that holds the laser is stopped (SIGTERM: the runner switches emission off), else
        emission off on every channel, read back."""
        if self.procedures.active:
            self.procedures.stop()
            return {"ok": True, "stopped": "procedure"}
        self.all_off()
        return {"ok": True}

    def refresh_laser(self) -> None:
        """Read the laser's state now (also done twice a second)."""
        if self.laser is not None:
            self.laser_status = self.laser.status()

    def _status_loop(self) -> None:
        while not self._stop.wait(STATUS_PERIOD_S):
            self.refresh_laser()

    # -- SLM -------------------------------------------------------------------------------------------------------

    def _slm(self) -> SlmControl:
        if self.slm is None:
            raise BenchctlError(f"profile {self.profile.name!r} has no [slm] and [optics]")
        return self.slm

    def show(self, pattern: Pattern) -> dict[str, Any]:
        """Compute (off the event loop: this is called on a worker thread) and display `pattern`."""
        slm = self._slm()
        label = pattern.kind if pattern.kind not in ("hologram", "dots") else f"{pattern.kind} {pattern.method}"
        with self._job(f"SLM: {label}"):
            phase = slm.phase(pattern, progress=self._progress)
            return slm.show(pattern, phase)

    def _progress(self, label: str, done: int, total: int) -> None:
        self.job["progress"] = {"label": label, "done": done, "total": total}

    def _job(self, name: str) -> _Job:
        if not self._busy.acquire(blocking=False):
            raise BenchctlError(f"busy with {self.job['busy']}; try again when it is done")
        return _Job(self, name)

    # -- camera ----------------------------------------------------------------------------------------------------

    def _camera(self) -> Held[Camera]:
        if self.camera is None:
            raise BenchctlError(f"profile {self.profile.name!r} has no [camera]")
        return self.camera

    def capture(self, frames: int | None) -> dict[str, Any]:
        """RAW frames of what is shown now into a new folder under `out`, with the settings beside them."""
        if frames is not None and not 1 <= frames <= 100:
            raise BadValueError(f"frames must be 1..100, got {frames}")
        with self._job("capture"), self._camera().use() as camera:
            settings = {"profile": {"name": self.profile.name, "path": str(self.profile.path)},
                        "laser": self.laser.status() if self.laser else None,
                        "slm": self._slm_settings()}
            result = capture.capture(self.out, self.profile, camera, frames, settings,
                                     self.slm.frame if self.slm else None)
        self.say(f"captured {len(result['files'])} files into {result['folder']}")
        return result

    def _slm_settings(self) -> dict[str, Any] | None:
        if self.slm is None or not self.slm.held.connected:
            return None
        with self.slm.device() as slm:
            return {"shows": self.slm.shown, "info": slm.info(), "displayed_frame": slm.displayed_frame()}

    def set_view(self, mode: str | None, zoom: list[float] | None, clear_zoom: bool) -> None:
        if mode is not None:
            if mode not in ("gamma", "linear"):
                raise BadValueError(f"view mode must be 'gamma' or 'linear', got {mode!r}")
            self.view["mode"] = mode
        if clear_zoom:
            self.view["zoom"] = None
        elif zoom is not None:
            if len(zoom) != 2 or not all(isinstance(v, (int, float)) and 0 <= v <= 1 for v in zoom):
                raise BadValueError(f"zoom centre must be [x, y] fractions of the frame, got {zoom!r}")
            self.view["zoom"] = (float(zoom[0]), float(zoom[1]))

    def _preview_loop(self) -> None:
        while not self._stop.is_set():
            if self.camera is None or (self.pages == 0 and not self.keep_previewing):
                self._stop.wait(0.1)
                continue
            try:
                self._publish(self._next_frame())
                self.preview_error = None
            except BenchctlError as exc:
                self.preview_error = str(exc)
                self._stop.wait(1.0)

    def _next_frame(self) -> preview.Shown:
        assert self.camera is not None
        centre = self.view["zoom"]
        with self.camera.use() as camera:
            started, clock, cpu = time.time(), time.perf_counter(), time.thread_time()
            frame = camera.preview()
            zoom = None
            if centre is not None and camera.windowed_preview and frame.full_shape is not None:
                zoom = camera.preview(preview.ZOOM_SIZE, preview.zoom_window(frame.full_shape, centre))
            render = (time.perf_counter() - clock, time.thread_time() - cpu)
        self._seq += 1
        return preview.shown_frame(self._seq, frame, zoom, mode=self.view["mode"], zoom_centre=centre,
                                   render_started=started, render_s=render)

    def _publish(self, shown: preview.Shown) -> None:
        shown.header["overlay"] = self.registration_overlay(shown.header["full_shape"])
        self.latest = shown
        self._frame_times.append(time.monotonic())
        for listener in list(self._listeners):
            listener()

    def listen(self, listener: Callable[[], object]) -> Callable[[], None]:
        """Call `listener` (from the live-view thread) after every new frame; returns the function that stops it."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener)

    @property
    def fps(self) -> float:
        times = list(self._frame_times)
        if len(times) < 2 or time.monotonic() - times[-1] > 2.0:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    def registration_overlay(self, full_shape: list[int] | tuple[int, int] | None) -> dict[str, list[list[float]]]:
        """Per colour with a stored registration: the target rectangle (ROI corners through its homography) as
        fractions of the frame, for the page to draw; nothing while the frame's size on the sensor is unknown."""
        if full_shape is None or self.profile.slm is None or self.profile.optics is None:
            return {}
        from benchctl.calibration.store import Calibration
        from benchctl.capture.registration import apply_homography

        (h, w), (rh, rw) = self.profile.slm.shape, self.profile.optics.roi
        top, left = (h - rh) / 2 - 0.5, (w - rw) / 2 - 0.5
        corners = np.array([[left, top], [left + rw, top], [left + rw, top + rh], [left, top + rh]])
        rows, cols = full_shape
        overlay = {}
        for colour, entry in Calibration.store(self.profile).registrations().items():
            points = apply_homography(np.array(entry["homography"]), corners)
            overlay[colour] = [[round(x / cols, 5), round(y / rows, 5)] for x, y in points]
        return overlay

    # -- procedures ------------------------------------------------------------------------------------------------

    def _release_for_run(self, devices: list[str]) -> None:
        """Let go of the devices a run will use (emission off first): one holder per device."""
        if "laser" in devices and self.laser is not None and not self.laser.let_go():
            raise BenchctlError(f"laser: {self.laser.unknown}; the procedure was not started")
        for name, held in (("slm", self.slm.held if self.slm else None), ("camera", self.camera)):
            if name in devices and held is not None:
                held.release()

    def _reconnect(self) -> None:
        """Take the devices back after a procedure, and say when it changed what the SLM shows."""
        for held in (self.laser.held if self.laser else None, self.slm.held if self.slm else None, self.camera):
            if held is not None and not held.connected:
                held.connect()
        self._read_slm(f"after procedure {self.procedures.running}")

    def connect(self, name: str) -> dict[str, Any]:
        """Connect device `name` (laser, slm or camera) again, e.g. after it was lost or held elsewhere."""
        devices = {"laser": self.laser.held if self.laser else None, "slm": self.slm.held if self.slm else None,
                   "camera": self.camera}
        held = devices.get(name)
        if held is None:
            raise BadValueError(f"no device {name!r} to connect (laser, slm or camera)")
        if self.procedures.active:
            raise BenchctlError("a procedure holds the devices; wait for it or stop it")
        if name == "laser" and self.laser is not None:
            self.laser.connect()
        elif held.connect() and name == "slm":
            self._read_slm("connected again")
        return {"connected": held.connected, "error": held.error}

    def _read_slm(self, when: str) -> None:
        if self.slm is not None:
            try:
                changed = self.slm.read_device()
            except BenchctlError as exc:
                changed = str(exc)
            if changed:
                self.say(f"{when}: {changed}")

    # -- state -----------------------------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """What the page shows besides the frames (cheap: no device is asked)."""
        slm = self.slm
        return {
            "profile": self.profile.name,
            "laser": self.laser_status,
            "slm": None if slm is None else {"connected": slm.held.connected, "error": slm.held.error,
                                             "shows": slm.shown, "channels": slm.channels},
            "camera": None if self.camera is None else {"connected": self.camera.connected,
                                                        "error": self.camera.error or self.preview_error},
            "view": self.view, "fps": round(self.fps, 2), "job": self.job,
            "procedure": self.procedures.state(), "events": list(self.events)[-30:],
            "uploads": dict(self.uploads.names), "time": time.time(),
        }

    def _checkpoints(self) -> dict[str, str]:
        folder = Path("checkpoints") / self.profile.name
        return {path.stem: str(path) for path in sorted(folder.glob("*.pt"))} if folder.is_dir() else {}


class _Job:
    """The console's one long job at a time: its name and progress in `state()`, its error kept for the page."""

    def __init__(self, console: Console, name: str) -> None:
        self.console = console
        console.job = {"busy": name, "progress": None, "error": None, "started": time.time()}

    def __enter__(self) -> _Job:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        job = self.console.job
        self.console.job = {"busy": None, "progress": None, "started": None,
                            "error": f"{job['busy']}: {exc}" if exc is not None else None,
                            "last": job["busy"], "seconds": round(time.time() - job["started"], 3)}
        self.console._busy.release()
