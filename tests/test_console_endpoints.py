"""The console's endpoints one at a time: each is a module-level function that finds its console in
`request.app.state`, called here with a request built by hand (no application, no routing, no access middleware), on
the small simulated bench."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_bench import call, laser_channel, make_console

from benchctl.console import app
from benchctl.console.core import Console
from benchctl.devices.errors import SafetyError
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import load_profile


@pytest.fixture
def console(bench_profile_path: Path, tmp_path: Path) -> Iterator[Console]:
    console = make_console(load_profile(bench_profile_path), tmp_path)
    yield console
    console.close()


def test_the_power_endpoint_alone_sets_and_reads_back(console: Console) -> None:
    assert call(app.power, console, {"power": "3mW"}, channel="green") == {"setpoint_mw": 3.0}
    assert laser_channel(2)["setpoint_w"] == pytest.approx(0.003)
    with pytest.raises(SafetyError, match="above the profile's limit 40 mW"):
        call(app.power, console, {"power": "41mW"}, channel="green")
    assert laser_channel(2)["setpoint_w"] == pytest.approx(0.003)  # nothing sent
    with pytest.raises(BadValueError, match='give the power as {"power": "5mW"}'):
        call(app.power, console, {"power": 3}, channel="green")


def test_the_emission_and_all_off_endpoints_alone(console: Console) -> None:
    assert call(app.emission, console, {"on": True}, channel="blue") == {"ok": True}
    assert laser_channel(3)["emission"] is True
    state = call(app.state, console)
    assert [ch["emission"] for ch in state["laser"]["channels"]] == [False, False, True]
    assert call(app.all_off, console) == {"ok": True}
    assert laser_channel(3)["emission"] is False and console.laser is not None and not console.laser.emitting
    with pytest.raises(BadValueError, match="give emission as"):
        call(app.emission, console, {"on": "yes"}, channel="blue")


def test_the_view_and_connect_endpoints_alone(console: Console) -> None:
    view = {"mode": "linear", "zoom": (0.25, 0.5), "region": (0.1, 0.2, 0.5, 0.6)}
    assert call(app.view, console, {"mode": "linear", "zoom": [0.25, 0.5], "region": [0.1, 0.2, 0.5, 0.6]}) == view
    with pytest.raises(BadValueError, match="view mode must be 'gamma' or 'linear', got 'log'"):
        call(app.view, console, {"mode": "log", "region": None})
    with pytest.raises(BadValueError, match=r"region must be \[x0, y0, x1, y1\] .* got \[0.5, 0.2, 0.1, 0.6\]"):
        call(app.view, console, {"mode": "gamma", "region": [0.5, 0.2, 0.1, 0.6]})
    assert console.view == view  # a refused view changes nothing
    assert call(app.view, console, {"region": None})["region"] is None
    assert call(app.connect, console, {"device": "camera"}) == {"connected": True, "error": None}
    with pytest.raises(BenchctlError, match="no device 'focus' to connect"):
        call(app.connect, console, {"device": "focus"})


def test_the_application_is_its_routes_and_the_console_it_serves(console: Console) -> None:
    from benchctl.console.security import Access

    wrapped = app.create_app(console, Access("t" * 20, 8765))
    assert wrapped.app.state.console is console and wrapped.app.routes == app.ROUTES


def test_state_answers_while_a_device_hangs(console: Console, monkeypatch: pytest.MonkeyPatch) -> None:
    """A laser that stops answering in the middle of a command holds that command's worker thread, never the event
    loop: /api/state answers meanwhile (from what the console last read), and the command ends when the device does."""
    import threading

    from console_bench import ORIGIN, TOKEN, access
    from starlette.testclient import TestClient

    from benchctl.devices.serial_link import SerialLink

    entered, released = threading.Event(), threading.Event()
    exchange = SerialLink._exchange

    def hanging(self: SerialLink, line: str, read: Any) -> Any:
        if line.startswith("CH2:POW"):
            entered.set()
            released.wait(30)
        return exchange(self, line, read)

    monkeypatch.setattr(SerialLink, "_exchange", hanging)
    with TestClient(app.create_app(console, access()), base_url=ORIGIN) as client:
        client.headers.update({"x-benchctl-token": TOKEN, "origin": ORIGIN})
        answers: dict[str, Any] = {}
        command = threading.Thread(target=lambda: answers.update(
            power=client.post("/api/laser/green/power", json={"power": "2mW"})))
        command.start()
        assert entered.wait(10)
        reader = threading.Thread(target=lambda: answers.update(state=client.get("/api/state")))
        reader.start()
        reader.join(10)
        hung = not released.is_set() and command.is_alive()
        released.set()
        command.join(10)
    assert hung and answers["state"].status_code == 200 and answers["state"].json()["profile"] == "bench"
    assert answers["power"].json()["setpoint_mw"] == 2.0


def test_the_page_is_served_from_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    """The event loop reads no file for the page: its files are read once, the first time they are asked for."""
    from importlib import resources

    first = {name: asyncio.run(app.static(request_for(name))).body for name in app.STATIC}
    monkeypatch.setattr(resources, "files", lambda package: pytest.fail(f"{package} read again"))
    assert {name: asyncio.run(app.static(request_for(name))).body for name in app.STATIC} == first
    assert b"benchctl console" in first["index.html"] and asyncio.run(app.page(request_for(""))).body == first[
        "index.html"]


def request_for(name: str) -> Any:
    from starlette.requests import Request

    return Request({"type": "http", "method": "GET", "path": f"/static/{name}", "query_string": b"", "headers": [],
                    "path_params": {"name": name}})
