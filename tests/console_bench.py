"""Helpers for the console's tests (not a test module): a console on the small simulated bench, its access rules,
and the simulated devices' state as the emulators keep it."""

from __future__ import annotations

import asyncio
import json
import struct
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from benchctl.console.core import Console
from benchctl.console.security import Access
from benchctl.devices.sim.state import load_state
from benchctl.profiles import Profile

PORT = 8765
TOKEN = "test-token-0123456789"
ORIGIN = f"http://127.0.0.1:{PORT}"
WS = f"ws://127.0.0.1:{PORT}/ws"
POWER_SWEEP = """name = "sweep"
procedure = "power-sweep"

[parameters]
colours = ["green"]
levels = ["1%", "2%"]
frames = 1
dark_frames = 1
"""


def make_console(profile: Profile, tmp_path: Path, deadman_s: float = 30.0) -> Console:
    """A started console on `profile`, captures under tmp_path/runs, procedures from tmp_path/procedures."""
    procedures = tmp_path / "procedures"
    procedures.mkdir(exist_ok=True)
    (procedures / "sweep.toml").write_text(POWER_SWEEP)
    console = Console(profile, tmp_path / "runs", deadman_s=deadman_s, procedures_dir=procedures)
    console.start()
    return console


def access(port: int = PORT) -> Access:
    return Access(TOKEN, port)


def laser_channel(index: int) -> dict[str, Any]:
    """What the simulated RGB laser unit holds for channel `index` (1 red, 2 green, 3 blue)."""
    return load_state("rgb-laser")["channels"][str(index)]


def unpack_frame(message: bytes) -> tuple[dict[str, Any], bytes, bytes]:
    """A live-view message: its header, the frame's JPEG and the zoom's JPEG (b"" when none)."""
    (length,) = struct.unpack(">I", message[:4])
    header = json.loads(message[4:4 + length])
    rest = message[4 + length:]
    zoom = header["zoom_bytes"]
    return header, rest[:len(rest) - zoom], rest[len(rest) - zoom:]


def next_frame(page: Any) -> tuple[dict[str, Any], bytes, bytes]:
    """The next live-view frame a test client's socket gets (`unpack_frame`), acknowledged as the page does."""
    while True:
        message = page.receive()
        if message.get("bytes"):
            header, jpeg, zoom = unpack_frame(message["bytes"])
            page.send_text(f"ack {header['seq']}")
            return header, jpeg, zoom


def expected_phase_frame(profile: Profile, phase: np.ndarray, channel: str) -> np.ndarray:
    """The gray frame the SLM driver shows for `phase` on `channel` (its own encoding, outside the console)."""
    from benchctl.devices.slm import slm_for

    return slm_for(profile).encode(phase, channel)


def call(handler: Any, console: Console, payload: dict[str, Any] | None = None, **path_params: str) -> Any:
    """A console endpoint (benchctl.console.app) awaited alone with a request that carries `payload` as its JSON body,
    as Starlette would hand it over: no application, routing or access middleware."""
    from starlette.requests import Request

    body = json.dumps(payload).encode() if payload is not None else b""
    messages = [{"type": "http.request", "body": body, "more_body": False}]

    async def receive() -> dict[str, Any]:
        return messages.pop(0) if messages else {"type": "http.disconnect"}

    scope = {"type": "http", "method": "POST", "path": "/", "query_string": b"", "path_params": path_params,
             "headers": [(b"content-length", str(len(body)).encode())],
             "app": SimpleNamespace(state=SimpleNamespace(console=console))}
    return asyncio.run(handler(Request(scope, receive)))
