"""`benchctl bench console`: the live console's speed, measured from outside as a page sees it.

A real console server is started as a child process on a free port, on an isolated simulated bench (its own state,
lock and cache folders), and driven over HTTP and its WebSocket:
- preview frames per second at the page's size (about 960 x 640 shown pixels), green lit;
- latency from a laser change (emission on/off) and from an SLM change (a grating's period) to the first frame that
  shows it (the frame's header says which SLM frame and lasers it saw; the simulated camera's progressive live view
  shows a change first in coarse light) and to the refined frame after it, each split into command (HTTP there and
  back), device (inside the server, the driver's work and the SLM's settle included), wait (until the live view
  began the frame that shows it; negative when it began before the command returned, e.g. during the settle), render
  (the camera's preview), encode (decode, statistics, JPEG) and delivery (to the client);
- status request latency while a 50-iteration SGD hologram computes.
Besides the seconds, the CPU seconds of the device, render and encode work (each runs on one thread): on a busy
machine the seconds grow with the load, the CPU seconds say what the same work takes on a free core.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchctl.errors import BenchctlError

GOALS = {"fps": 10.0, "latency_ms": 300.0, "status_ms": 100.0}


class _Client:
    """HTTP and WebSocket access to one console, with its token."""

    def __init__(self, url: str, stack: contextlib.ExitStack) -> None:
        from websockets.sync.client import connect

        self.base, token = url.split("/?token=")
        self.headers = {"x-benchctl-token": token, "content-type": "application/json", "origin": self.base}
        self.socket = stack.enter_context(connect(self.base.replace("http://", "ws://") + "/ws",
                                                  additional_headers=self.headers, max_size=None))
        self._beat = 0.0

    def call(self, path: str, body: dict[str, Any] | None = None, timeout_s: float = 600.0) -> dict[str, Any]:
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.base + path, data, self.headers)
        with urllib.request.urlopen(request, timeout=timeout_s) as response:
            return json.loads(response.read())

    def frame(self, timeout_s: float = 30.0) -> tuple[dict[str, Any], float]:
        """The next live-view frame's header and when it arrived (time.time()), acknowledged as the page does."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            message = self.socket.recv(timeout=timeout_s)
            if isinstance(message, bytes):
                arrived = time.time()
                (length,) = struct.unpack(">I", message[:4])
                header = json.loads(message[4:4 + length])
                self.socket.send(f"ack {header['seq']}")
                return header, arrived
            self.socket.send("heartbeat")
        raise BenchctlError(f"console bench: no live-view frame within {timeout_s:g} s")

    def frame_showing(self, wanted: Callable[[dict[str, Any]], bool]) -> tuple[dict[str, Any], float]:
        while True:
            header, arrived = self.frame()
            if wanted(header["source"]):
                return header, arrived


def _start(profile: str | None, folder: Path) -> tuple[subprocess.Popen[str], str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "BENCHCTL_SIM_DIR": str(folder / "sim"),
           "BENCHCTL_LOCK_DIR": str(folder / "locks"), "BENCHCTL_CACHE_DIR": str(folder / "cache")}
    command = [sys.executable, "-m", "benchctl", "console", "--port", "0", "--out", str(folder / "runs"),
               "--deadman", "60"] + (["--profile", profile] if profile else [])
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    stdout = process.stdout
    assert stdout is not None
    lines: list[str] = []
    while True:
        line = stdout.readline()
        if not line:
            raise BenchctlError("console bench: the console did not start: " + " | ".join(lines[-5:]))
        lines.append(line.strip())
        match = re.search(r"http://\S+", line)
        if match:
            threading.Thread(target=lambda: [None for _ in stdout], daemon=True).start()  # keep draining
            return process, match.group(0)


def _split(t0: float, t1: float, reply: dict[str, Any], header: dict[str, Any], arrived: float) -> dict[str, float]:
    device = reply["server_s"]
    return {"total_ms": (arrived - t0) * 1e3, "command_ms": (t1 - t0 - device) * 1e3, "device_ms": device * 1e3,
            "wait_ms": (header["render_started"] - t1) * 1e3, "render_ms": header["render_s"] * 1e3,
            "encode_ms": header["encode_s"] * 1e3, "delivery_ms": (arrived - header["published"]) * 1e3,
            "device_cpu_ms": reply["server_cpu_s"] * 1e3, "render_cpu_ms": header["render_cpu_s"] * 1e3,
            "encode_cpu_ms": header["encode_cpu_s"] * 1e3}


def _change(client: _Client, path: str, body: dict[str, Any], shows: Callable[[dict[str, Any], dict[str, Any]], bool],
            ) -> tuple[dict[str, float], dict[str, float]]:
    """POST `body` to `path` and time it to the first frame whose source `shows(reply, source)` the change (the
    live view's coarse first light: progressive preview) and to the refined frame after it (`_split` each)."""
    t0 = time.time()
    reply = client.call(path, body)
    t1 = time.time()

    def wanted(source: dict[str, Any]) -> bool:
        return shows(reply, source)

    header, arrived = client.frame_showing(wanted)
    first = _split(t0, t1, reply, header, arrived)
    while header["source"].get("coarse"):
        header, arrived = client.frame_showing(wanted)
    return first, _split(t0, t1, reply, header, arrived)


def _median(rows: list[dict[str, float]]) -> dict[str, float]:
    return {key: round(statistics.median(row[key] for row in rows), 1) for key in rows[0]}


def run_console_bench(profile: str | None = None, seconds: float = 10.0, repeats: int = 5,
                      out: Path | None = None, say: Callable[[str], None] = print) -> dict[str, Any]:
    """Measure the console (see the module docstring); prints the figures against the goals and returns them."""
    with tempfile.TemporaryDirectory(prefix="benchctl-console-bench-") as scratch:
        process, url = _start(profile, Path(scratch))
        try:
            with contextlib.ExitStack() as stack:
                load = os.getloadavg()[0]
                say(f"machine: {os.cpu_count()} cores, load average {load:.1f} (1 min) at the start")
                figures = _measure(_Client(url, stack), seconds, repeats, say)
                figures["load"] = [round(load, 2), round(os.getloadavg()[0], 2)]
                say(f"load average {figures['load'][1]:.1f} at the end")
        finally:
            process.terminate()  # the console switches emission off and stops; a starved one is killed after 60 s
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "console.json").write_text(json.dumps(figures, indent=2) + "\n")
        say(f"figures: {out / 'console.json'}")
    return figures


def _measure(client: _Client, seconds: float, repeats: int, say: Callable[[str], None]) -> dict[str, Any]:
    channel = "green"
    client.call(f"/api/laser/{channel}/power", {"power": "5%"})
    client.call("/api/slm", {"kind": "grating", "period_px": 8, "channel": channel})
    client.call(f"/api/laser/{channel}/emission", {"on": True})
    client.frame_showing(lambda source: channel in source.get("lasers_on_w", {}))
    count, started, shape = 0, time.monotonic(), None
    while time.monotonic() - started < seconds:
        header, _ = client.frame()
        count, shape = count + 1, header["shape"]
    fps = count / (time.monotonic() - started)
    assert shape is not None
    say(f"preview: {fps:.1f} fps at {shape[1]} x {shape[0]} shown pixels, {channel} lit "
        f"(goal >= {GOALS['fps']:g} fps)")

    laser_rows: list[tuple[dict[str, float], dict[str, float]]] = []
    slm_rows: list[tuple[dict[str, float], dict[str, float]]] = []
    for index in range(repeats):
        on = index % 2 == 1

        def laser_shown(reply: dict[str, Any], source: dict[str, Any], on: bool = on) -> bool:
            return (channel in source.get("lasers_on_w", {})) == on

        laser_rows.append(_change(client, f"/api/laser/{channel}/emission", {"on": on}, laser_shown))
    client.call(f"/api/laser/{channel}/emission", {"on": True})

    def slm_shown(reply: dict[str, Any], source: dict[str, Any]) -> bool:
        return bool(source.get("slm_frame") == reply["frame"])

    for index in range(repeats):
        grating = {"kind": "grating", "period_px": 10 + 2 * (index % 2), "channel": channel}
        slm_rows.append(_change(client, "/api/slm", grating, slm_shown))
    for label, rows in (("laser emission", laser_rows), ("SLM grating", slm_rows)):
        for index, which in enumerate(("first frame showing it (coarse light)", "the refined frame")):
            m = _median([row[index] for row in rows])
            say(f"latency {label} -> {which}: {m['total_ms']:.0f} ms median of {len(rows)} "
                f"(goal <= {GOALS['latency_ms']:g} ms): command {m['command_ms']:.0f} ms, device "
                f"{m['device_ms']:.0f} ms, wait {m['wait_ms']:.0f} ms, render {m['render_ms']:.0f} ms, encode "
                f"{m['encode_ms']:.0f} ms, delivery {m['delivery_ms']:.0f} ms")
            say(f"  CPU time of that work: device {m['device_cpu_ms']:.0f} ms, render {m['render_cpu_ms']:.0f} ms, "
                f"encode {m['encode_cpu_ms']:.0f} ms (each on one thread: what a free core takes)")

    result: dict[str, Any] = {}

    def hologram() -> None:
        result["reply"] = client.call("/api/slm", {"kind": "hologram", "target": "chart:bars", "method": "sgd",
                                                   "iterations": 50, "channel": channel, "seed": 1})

    worker = threading.Thread(target=hologram)
    worker.start()
    waits = []
    while worker.is_alive():
        t0 = time.perf_counter()
        state = client.call("/api/state")
        if state["job"]["busy"]:
            waits.append((time.perf_counter() - t0) * 1e3)
        client.frame(timeout_s=60)  # the page keeps receiving frames meanwhile
    worker.join()
    if not waits:
        raise BenchctlError("console bench: the SGD hologram finished before a status request could be timed")
    sgd_s = result["reply"]["hologram"]["seconds"]
    say(f"status while a 50-iteration SGD hologram computes ({sgd_s:.1f} s): median {statistics.median(waits):.1f} ms, "
        f"max {max(waits):.1f} ms over {len(waits)} requests (goal < {GOALS['status_ms']:g} ms)")
    return {"fps": round(fps, 2), "shown": shape, "laser_latency": [row[0] for row in laser_rows],
            "laser_refined": [row[1] for row in laser_rows], "slm_latency": [row[0] for row in slm_rows],
            "slm_refined": [row[1] for row in slm_rows],
            "status_ms": [round(w, 2) for w in waits], "sgd_s": sgd_s, "goals": GOALS}
