"""A colour capture's report.html as a browser shows it (Debian's headless Chromium) at 1400 and 1000 px: target,
simulation and capture side by side without a sideways scroll, bordered previews, each colour's capture and error maps,
the run's own lookup tables and registration, readable Devices and Versions tables that agree with 'Calibration used',
and warnings that are true."""

from __future__ import annotations

from pathlib import Path

import pytest
import test_console_browser
from selenium import webdriver
from selenium.webdriver.common.by import By

from benchctl.runner.engine import run_procedure

pytestmark = pytest.mark.slow  # a procedure run and a browser
browser = test_console_browser.browser  # the console tests' headless Chromium (a fixture)


@pytest.fixture
def report(tmp_path: Path, bench_profile_path: Path) -> Path:
    """A first colour capture: it measures the lookup tables and registers first; automatic exposure leaves every
    colour short of its goal (the bench's lasers at their 40 mW limit)."""
    procedure = tmp_path / "capture.toml"
    procedure.write_text('procedure = "colour-capture"\n')
    outcome = run_procedure(procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda line: None)
    assert outcome.folder is not None
    return outcome.folder / "report.html"


def section_text(browser: webdriver.Chrome, heading: str) -> str:
    """The text between an h2 and the next."""
    return browser.execute_script("""
        const h = [...document.querySelectorAll('h2')].find(e => e.textContent === arguments[0]);
        let text = '', node = h.nextElementSibling;
        while (node && node.tagName !== 'H2') { text += node.innerText + '\\n'; node = node.nextElementSibling; }
        return text;""", heading)


@pytest.mark.parametrize("width", [1400, 1000])
def test_the_report_reads_well_at_both_widths(report: Path, browser: webdriver.Chrome, width: int) -> None:
    browser.set_window_size(width, 1000)
    browser.get(report.as_uri())
    page = browser.execute_script("const e = document.documentElement; return [e.scrollWidth, e.clientWidth];")
    assert page[0] <= page[1], f"the page scrolls sideways at {width} px: {page}"
    rows = browser.find_elements(By.CSS_SELECTOR, ".row")
    first = rows[0].find_elements(By.TAG_NAME, "figure")
    assert [f.find_element(By.TAG_NAME, "figcaption").text for f in first] == [
        "target (sRGB)", "simulated reconstruction", "merged capture"]
    assert len({f.location["y"] for f in first}) == 1, "target, simulation and capture are not side by side"
    assert all(f.size["width"] > 0.28 * rows[0].size["width"] for f in first)
    captions = [c.text for c in browser.find_elements(By.TAG_NAME, "figcaption")]
    for caption in ("red captured", "green captured", "blue captured", "capture: error against the target",
                    "red: the dots seen through the fit"):
        assert any(c.startswith(caption) for c in captions), (caption, captions)
    for image in browser.find_elements(By.CSS_SELECTOR, "figure img"):
        assert image.value_of_css_property("border-top-width") == "1px"
        assert image.size["width"] <= rows[0].size["width"]
    warnings = browser.find_element(By.CSS_SELECTOR, ".warn").text
    assert "No warnings." not in browser.page_source
    for colour in ("red", "green", "blue"):
        assert f"bars: {colour} peaked at " in warnings and "short of its 70% exposure goal" in warnings
    calibration, devices = section_text(browser, "Calibration used"), section_text(browser, "Devices")
    assert calibration.count("measured 20") == 3 and "linear" not in devices
    versions = section_text(browser, "Versions")
    for text in (devices, versions, section_text(browser, "Parameters")):
        assert "{" not in text and "null" not in text
    assert "git commit" in versions and "Canon EOS M10 (benchctl simulation)" in devices
    assert len(browser.find_elements(By.CSS_SELECTOR, "svg")) == 2  # the run's own lookup tables
    for plot in browser.find_elements(By.CSS_SELECTOR, "svg"):  # drawn whole, scaled to fit, never clipped
        drawn, shown = browser.execute_script("""
            const svg = arguments[0], box = svg.getBBox(), rect = svg.getBoundingClientRect();
            const view = svg.viewBox.baseVal, scale = view && view.width ? rect.width / view.width : 1;
            return [(box.x + box.width) * scale, rect.width];""", plot)
        assert drawn <= shown + 0.5, f"a lookup-table plot is cut off at {width} px: {drawn:.0f} > {shown:.0f} px"
