"""The console's web application (Starlette): the page, its JSON API and the live-view socket.

Every route sits behind `AccessMiddleware` (token, Host, Origin). Device work runs on worker threads
(`run_in_threadpool`), never on the event loop. The socket carries frames to the page (binary: a 4-byte header
length, the JSON header, the frame's JPEG, then the zoom's JPEG if any) and state twice a second (text, JSON). The
page answers each frame it has drawn with `ack <seq>` (the server keeps at most FRAMES_IN_FLIGHT frames
unacknowledged, so a slow page never gets a backlog) and each state with `heartbeat`; every message it sends is a
heartbeat for the laser's dead-man switch, so the page's heartbeats need no timer of its own (a browser slows a
hidden tab's timers down to once a minute). The page's ALL OFF goes over the same socket (`all-off`, answered with
`{"all_off": ...}`): the open socket is the console's reserved channel, which no flood of new connections can
starve (connections.py); ALL OFF runs on a thread of its own, never waiting for the worker threads.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import json
import struct
import threading
import time
from collections.abc import Awaitable, Callable
from importlib import resources
from typing import Any, TypeVar, get_args

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from benchctl.console.core import Console
from benchctl.console.security import Access, AccessMiddleware
from benchctl.console.slm import ZernikeName, parse_pattern
from benchctl.errors import BadValueError, BenchctlError

STATIC = {"console.js": "text/javascript", "console.css": "text/css", "index.html": "text/html"}
STATE_PERIOD_S = 0.5
FRAMES_IN_FLIGHT = 2  # frames sent to a page and not yet acknowledged, at most
MAX_JSON_BYTES = 64 * 1024
Handler = Callable[[Request], Awaitable[Response]]
T = TypeVar("T")


def create_app(console: Console, access: Access) -> AccessMiddleware:
    """The application for one console start, wrapped in its access checks."""

    def api(handler: Callable[[Request], Awaitable[Any]]) -> Handler:
        """A JSON endpoint: its result as JSON (a command's with `server_s`, the seconds it took inside the server,
        device work included, and `server_cpu_s`, the CPU seconds of its work on a worker thread); a BenchctlError
        as 400 with its one line (nothing else changed)."""

        async def endpoint(request: Request) -> Response:
            started, cpu = time.perf_counter(), _CPU.set([0.0])
            try:
                result = await handler(request)
            except BenchctlError as exc:
                return JSONResponse({"error": str(exc)}, status_code=400)
            finally:
                spent = _CPU.get()[0]
                _CPU.reset(cpu)
            if request.method == "POST" and isinstance(result, dict):
                result = {**result, "server_s": round(time.perf_counter() - started, 6),
                          "server_cpu_s": round(spent, 6)}
            return JSONResponse(result)

        return endpoint

    async def body(request: Request) -> dict[str, Any]:
        raw = await _capped(request, MAX_JSON_BYTES, "request body")
        try:
            data = json.loads(raw or b"{}")
        except ValueError:
            raise BadValueError("request body is not JSON") from None
        if not isinstance(data, dict):
            raise BadValueError("request body must be a JSON object")
        return data

    async def page(request: Request) -> Response:
        return _static("index.html")

    async def static(request: Request) -> Response:
        name = request.path_params["name"]
        if name not in STATIC:
            return Response("not found\n", status_code=404, media_type="text/plain")
        return _static(name)

    async def state(request: Request) -> dict[str, Any]:
        return console.state()

    async def info(request: Request) -> dict[str, Any]:
        return await _in_thread(_info, console)

    async def power(request: Request) -> dict[str, Any]:
        text = (await body(request)).get("power")
        if not isinstance(text, str):
            raise BadValueError('give the power as {"power": "5mW"} or {"power": "10%"}')
        return await _in_thread(console.set_power, request.path_params["channel"], text)

    async def emission(request: Request) -> dict[str, Any]:
        on = (await body(request)).get("on")
        if not isinstance(on, bool):
            raise BadValueError('give emission as {"on": true} or {"on": false}')
        if on and console.procedures.active:
            raise BenchctlError("a procedure holds the laser; stop it first")
        await _in_thread(console.set_emission, request.path_params["channel"], on)
        return {"ok": True}

    async def all_off(request: Request) -> dict[str, Any]:
        return await _on_own_thread(console.emission_off)

    async def slm(request: Request) -> dict[str, Any]:
        pattern = parse_pattern(await body(request))
        return await _in_thread(console.show, pattern)

    async def thumbnail(request: Request) -> Response:
        if console.slm is None:
            return Response("no SLM\n", status_code=404, media_type="text/plain")
        png = await _in_thread(console.slm.thumbnail)
        return Response(png, media_type="image/png", headers={"cache-control": "no-store"})

    async def upload(request: Request) -> dict[str, Any]:
        console.uploads.check_room()
        data = await _capped(request, console.uploads.max_bytes, "upload")
        name = request.query_params.get("name", "image")
        upload_id = await _in_thread(console.uploads.add, data, name)
        console.say(f"uploaded {name!r} as upload:{upload_id}")
        return {"target": f"upload:{upload_id}"}

    async def view(request: Request) -> dict[str, Any]:
        data = await body(request)
        console.set_view(data.get("mode"), data.get("zoom"), "zoom" in data and data["zoom"] is None)
        return console.view

    async def capture(request: Request) -> dict[str, Any]:
        frames = (await body(request)).get("frames")
        if frames is not None and (isinstance(frames, bool) or not isinstance(frames, int)):
            raise BadValueError(f"frames must be a whole number, got {frames!r}")
        return await _in_thread(console.capture, frames)

    async def connect(request: Request) -> dict[str, Any]:
        return await _in_thread(console.connect, str((await body(request)).get("device")))

    async def dry_run(request: Request) -> dict[str, Any]:
        name = (await body(request)).get("name")
        return {"lines": await _in_thread(console.procedures.dry_run, str(name))}

    async def start(request: Request) -> dict[str, Any]:
        name = (await body(request)).get("name")
        await _in_thread(console.procedures.start, str(name))
        return {"ok": True}

    async def stop(request: Request) -> dict[str, Any]:
        await _in_thread(console.procedures.stop)
        return {"ok": True}

    async def report(request: Request) -> Response:
        path = console.procedures.report()
        if path is None:
            return Response("no report yet\n", status_code=404, media_type="text/plain")
        return FileResponse(path, media_type="text/html")

    async def socket(websocket: WebSocket) -> None:
        await websocket.accept()
        loop = asyncio.get_running_loop()
        page = _Page()
        stop_listening = console.listen(lambda: loop.call_soon_threadsafe(page.wake.set))
        console.pages += 1
        if console.laser is not None:
            console.laser.heartbeat()
        sender = asyncio.create_task(_send(websocket, console, page))
        try:
            while True:
                message = await websocket.receive_text()
                if console.laser is not None:
                    console.laser.heartbeat()
                if message.startswith("ack "):
                    page.ack(message[4:])
                elif message == "all-off":
                    page.answer(await _all_off_answer(console))
        except WebSocketDisconnect:
            pass
        finally:
            console.pages -= 1
            stop_listening()
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
                await sender

    routes = [
        Route("/", page), Route("/static/{name}", static), Route("/api/state", api(state)),
        Route("/api/info", api(info)), Route("/api/laser/off", api(all_off), methods=["POST"]),
        Route("/api/laser/{channel}/power", api(power), methods=["POST"]),
        Route("/api/laser/{channel}/emission", api(emission), methods=["POST"]),
        Route("/api/slm", api(slm), methods=["POST"]), Route("/api/slm/thumbnail.png", thumbnail),
        Route("/api/upload", api(upload), methods=["POST"]), Route("/api/view", api(view), methods=["POST"]),
        Route("/api/capture", api(capture), methods=["POST"]), Route("/api/connect", api(connect), methods=["POST"]),
        Route("/api/procedures/dry-run", api(dry_run), methods=["POST"]),
        Route("/api/procedures/start", api(start), methods=["POST"]),
        Route("/api/procedures/stop", api(stop), methods=["POST"]),
        Route("/api/procedures/report", report), WebSocketRoute("/ws", socket),
    ]
    return AccessMiddleware(Starlette(routes=routes), access)


class _Page:
    """One page's socket: the frames it has not acknowledged yet, and the event that wakes its sender (a new frame,
    an acknowledgement)."""

    def __init__(self) -> None:
        self.unacked: list[int] = []
        self.answers: list[str] = []  # text messages to send before anything else (ALL OFF's answer)
        self.wake = asyncio.Event()

    def answer(self, message: dict[str, Any]) -> None:
        self.answers.append(json.dumps(message))
        self.wake.set()

    def ack(self, text: str) -> None:
        """The page has shown frame `text` (a number; anything else is only a heartbeat)."""
        if text.isdigit():
            self.unacked = [seq for seq in self.unacked if seq > int(text)]
            self.wake.set()


async def _send(websocket: WebSocket, console: Console, page: _Page) -> None:
    """Frames as they come, the latest only and at most FRAMES_IN_FLIGHT not yet acknowledged (a slow page skips
    frames instead of queueing them), and the state every STATE_PERIOD_S."""
    sent = 0
    next_state = 0.0
    loop = asyncio.get_running_loop()
    while True:
        page.wake.clear()  # before looking: a wake-up that comes while this sends is kept for the wait below
        while page.answers:
            await websocket.send_text(page.answers.pop(0))
        shown = console.latest
        if shown is not None and shown.seq != sent and len(page.unacked) < FRAMES_IN_FLIGHT:
            sent = shown.seq
            page.unacked.append(sent)
            header = json.dumps({**shown.header, "zoom_bytes": len(shown.zoom or b""), "sent": time.time()}).encode()
            await websocket.send_bytes(struct.pack(">I", len(header)) + header + shown.jpeg + (shown.zoom or b""))
        if loop.time() >= next_state:
            next_state = loop.time() + STATE_PERIOD_S
            await websocket.send_text(json.dumps(console.state()))
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(page.wake.wait(), timeout=max(0.01, next_state - loop.time()))


async def _capped(request: Request, limit: int, what: str) -> bytes:
    """The request's body, read no further than `limit` bytes (BadValueError beyond: a declared length is refused
    before anything is read)."""
    declared = request.headers.get("content-length")
    if declared is not None and (not declared.isdigit() or int(declared) > limit):
        raise BadValueError(f"{what} of {declared} bytes is above the limit of {limit:,}")
    data = bytearray()
    async for chunk in request.stream():
        data += chunk
        if len(data) > limit:
            raise BadValueError(f"{what} is above the limit of {limit:,} bytes")
    return bytes(data)


_CPU: contextvars.ContextVar[list[float]] = contextvars.ContextVar("console_request_cpu")


async def _in_thread(function: Callable[..., T], *args: Any) -> T:
    """`function(*args)` on a worker thread (never on the event loop), its CPU seconds added to the request's."""

    def timed() -> T:
        start = time.thread_time()
        try:
            return function(*args)
        finally:
            spent = _CPU.get(None)  # the request's, copied into this thread's context
            if spent is not None:
                spent[0] += time.thread_time() - start

    return await run_in_threadpool(timed)


async def _all_off_answer(console: Console) -> dict[str, Any]:
    """ALL OFF from the page's socket: its result, or its one-line error."""
    try:
        return {"all_off": await _on_own_thread(console.emission_off)}
    except BenchctlError as exc:
        return {"all_off": {"error": str(exc)}}


async def _on_own_thread(function: Callable[[], T]) -> T:
    """`function()` on a thread started for it: ALL OFF never queues behind other requests' device work."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[T] = loop.create_future()

    def settle(outcome: tuple[T] | BaseException) -> None:
        if not done.done():
            if isinstance(outcome, BaseException):
                done.set_exception(outcome)
            else:
                done.set_result(outcome[0])

    def run() -> None:
        try:
            outcome: tuple[T] | BaseException = (function(),)
        except BaseException as exc:  # noqa: BLE001 - handed to the awaiting request
            outcome = exc
        loop.call_soon_threadsafe(settle, outcome)

    threading.Thread(target=run, name="console ALL OFF", daemon=True).start()
    return await done


def _static(name: str) -> Response:
    data = (resources.files("benchctl.console") / "static" / name).read_bytes()
    return Response(data, media_type=STATIC[name], headers={"cache-control": "no-store"})


def _info(console: Console) -> dict[str, Any]:
    """What the page's forms offer: channels and their limits, patterns, targets, methods, checkpoints,
    procedures."""
    from benchctl.holograms.scene import usable_methods
    from benchctl.targets import list_targets

    profile = console.profile
    return {
        "profile": profile.name,
        "channels": [{"name": c.name, "wavelength_nm": c.wavelength_nm, "limit_mw": c.max_power_mw,
                      "setpoint_mw": c.setpoint_mw} for c in profile.channels],
        "zernike": list(get_args(ZernikeName)),
        "targets": list(list_targets()),
        "methods": usable_methods(profile) if console.slm is not None else [],
        "checkpoints": list(console.slm.checkpoints) if console.slm else [],
        "procedures": list(console.procedures.files()),
        "deadman_s": console.laser.deadman_s if console.laser else None,
    }
