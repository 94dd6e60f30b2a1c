"""The console server's connection limits on a real uvicorn server (configured as `benchctl console` configures it):
connections beyond the limit displace the oldest that has not sent a request, a trickle is closed at its deadline,
and the page's open socket carries ALL OFF however many connections are waiting."""

from __future__ import annotations

import contextlib
import json
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_console_browser import serve

from benchctl.console.connections import Limits
from console_bench import TOKEN, laser_channel

LIMITS = Limits(max_connections=8, request_s=0.6)


def closed_by_server(sock: socket.socket, timeout_s: float) -> bool:
    """Whether the server closes `sock` (EOF or reset) within `timeout_s`."""
    sock.settimeout(timeout_s)
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


@contextlib.contextmanager
def sockets(port: int, count: int) -> Iterator[list[socket.socket]]:
    opened = [socket.create_connection(("127.0.0.1", port)) for _ in range(count)]
    try:
        yield opened
    finally:
        for sock in opened:
            sock.close()


def get_state(port: int) -> int:
    """GET /api/state on a new connection, with the token: the status code."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(f"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nX-Benchctl-Token: {TOKEN}\r\n"
                     "Connection: close\r\n\r\n".encode())
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    return int(reply.split(b" ", 2)[1])


def test_connections_beyond_the_limit_displace_the_oldest_idle_one(bench_profile_path: Path, tmp_path: Path) -> None:
    with serve(bench_profile_path, tmp_path, limits=LIMITS) as (_, url):
        port = int(url.split(":")[2].split("/")[0])
        with sockets(port, LIMITS.max_connections) as idle:
            time.sleep(0.1)
            with sockets(port, 3):
                assert all(closed_by_server(sock, 0.3) for sock in idle[:3])  # the three oldest made room
                assert not any(closed_by_server(sock, 0.05) for sock in idle[3:5])
            assert get_state(port) == 200  # a request on a new connection gets through


def test_a_connection_that_does_not_send_a_request_in_time_is_closed(bench_profile_path: Path,
                                                                    tmp_path: Path) -> None:
    with serve(bench_profile_path, tmp_path, limits=LIMITS) as (_, url):
        port = int(url.split(":")[2].split("/")[0])
        with sockets(port, 2) as (idle, trickle):
            opened = time.monotonic()
            with pytest.raises(OSError):  # broken pipe or reset: the server closed it
                for byte in b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n":  # a byte every 0.1 s
                    trickle.sendall(bytes([byte]))
                    time.sleep(0.1)
            assert LIMITS.request_s <= time.monotonic() - opened < LIMITS.request_s + 1.0
            assert closed_by_server(idle, 0.5)


def test_all_off_goes_over_the_open_socket_while_connections_wait(bench_profile_path: Path, tmp_path: Path) -> None:
    from websockets.sync.client import connect

    with serve(bench_profile_path, tmp_path, limits=LIMITS) as (console, url):
        base = url.split("/?")[0]
        with connect(base.replace("http://", "ws://") + f"/ws?token={TOKEN}", origin=base, max_size=None) as page:
            console.set_power("green", "1mW")
            page.send("heartbeat")
            console.set_emission("green", True)
            assert laser_channel(2)["emission"] is True
            port = int(base.rsplit(":", 1)[1])
            with sockets(port, 3 * LIMITS.max_connections):  # every slot taken, over and over
                started = time.monotonic()
                page.send("all-off")
                message = page.recv(timeout=5)
                while not (isinstance(message, str) and "all_off" in message) and time.monotonic() - started < 5:
                    message = page.recv(timeout=5)
                assert json.loads(message)["all_off"] == {"ok": True}
                assert time.monotonic() - started < 1.0
        assert laser_channel(2)["emission"] is False


@pytest.mark.parametrize("limit, expected", [(20000, 128), (1024, 128), (256, 64), (16, 8)])
def test_the_connection_limit_leaves_descriptors_free(monkeypatch: pytest.MonkeyPatch, limit: int,
                                                     expected: int) -> None:
    import resource

    monkeypatch.setattr(resource, "getrlimit", lambda which: (limit, limit))
    assert Limits.for_this_process().max_connections == expected
