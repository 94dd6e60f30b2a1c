"""The console's page in a real browser: Debian's headless Chromium driven by Selenium through Debian's chromedriver,
against the real server (uvicorn, WebSocket) on the small simulated bench."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import uvicorn
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select

from benchctl.console.app import create_app
from benchctl.console.core import Console
from benchctl.console.server import listen
from benchctl.devices.sim.slm import read_displayed
from benchctl.profiles import load_profile
from console_bench import TOKEN, access, laser_channel, make_console

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1500,1000"]


@pytest.fixture
def served(bench_profile_path: Path, tmp_path: Path) -> Iterator[tuple[Console, str]]:
    """A console on the small bench behind a real uvicorn server on a free port; its URL with the token."""
    console = make_console(load_profile(bench_profile_path), tmp_path)
    sock = listen("127.0.0.1", 0)
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(create_app(console, access(port)), log_level="warning", lifespan="off"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        yield console, f"http://127.0.0.1:{port}/?token={TOKEN}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()
        console.close()


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
