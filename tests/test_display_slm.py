"""The `display` SLM driver on a real X server (Xvfb with two screens, each with its RandR output, the EDIDs of two
real monitors set on them), and the EDID parser on real monitors' EDIDs (tests/data/edid/README.md)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from benchctl.cli import main
from benchctl.devices.errors import DeviceError
from benchctl.devices.slm import save_lut, slm_for
from benchctl.devices.slm.display import DisplaySLM
from benchctl.devices.slm.edid import parse_edid
from benchctl.optics.phase_encoding import PhaseLUT
from benchctl.profiles import load_profile

EDIDS = Path(__file__).with_name("data") / "edid"
SLM_SCREEN = (192, 128)  # screen 1: the SLM; screen 0 is the desktop monitor
pytestmark = pytest.mark.skipif(shutil.which("Xvfb") is None, reason="needs Debian's xvfb (.ci/run installs it)")


@pytest.fixture(scope="module")
def x_display() -> Iterator[str]:
    """Xvfb on a free display number: screen 0 320x240 with the EDID of a Dell P2415Q, screen 1 192x128 with that
    of a Dell E178WFP (-noreset: the EDIDs stay when the client that set them leaves)."""
    from Xlib import X, display

    number = next(n for n in range(90, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists()
                  and not Path(f"/tmp/.X{n}-lock").exists())
    server = subprocess.Popen(["Xvfb", f":{number}", "-screen", "0", "320x240x24", "-screen", "1",
                               f"{SLM_SCREEN[0]}x{SLM_SCREEN[1]}x24", "-nolisten", "tcp", "-noreset"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    name = f":{number}"
    try:
        for _ in range(100):
            if Path(f"/tmp/.X11-unix/X{number}").exists():
                break
            time.sleep(0.05)
        time.sleep(0.2)
        connection = display.Display(name)
        for screen, blob in ((0, "dell-p2415q-hdmi1.4.bin"), (1, "dell-e178wfp-vga.bin")):
            output = connection.screen(screen).root.xrandr_get_screen_resources().outputs[0]
            connection.xrandr_change_output_property(output, connection.intern_atom("EDID"),
                                                     connection.intern_atom("INTEGER"), X.PropModeReplace,
                                                     (8, (EDIDS / blob).read_bytes()))
        connection.sync()
        connection.close()
        yield name
    finally:
        server.terminate()
        server.wait()


def profile_text(x_display: str, **slm: object) -> str:
    keys = {"driver": "display", "x_display": x_display, "width": SLM_SCREEN[0], "height": SLM_SCREEN[1],
            "pitch_um": 8.0, "bit_depth": 8, "settle_ms": 0, **slm}
    lines = "\n".join(f"{key} = {json.dumps(value)}" for key, value in keys.items())  # JSON scalars are TOML
    return f"[slm]\n{lines}\n\n[laser]\nport = \"sim://rgb-laser\"\n\n[laser.protocol]\nset_power = \"P {{mw}}\"\n" \
           f"get_power = \"P?\"\nenable = \"E1\"\ndisable = \"E0\"\n\n[[laser.channels]]\nname = \"green\"\n" \
           f"wavelength_nm = 520\nmax_power_mw = 5\nsetpoint_mw = 1\n"


def read_back(x_display: str, slm: DisplaySLM) -> np.ndarray:
    """The SLM output's pixels as the X server holds them (XGetImage on its screen's root), as (H, W, 4) bytes."""
    from Xlib import X, display

    assert slm.output is not None
    connection = display.Display(x_display)
    try:
        image = connection.screen(slm.output.screen).root.get_image(slm.output.x, slm.output.y, slm.output.width,
                                                                    slm.output.height, X.ZPixmap, 0xFFFFFFFF)
        return np.frombuffer(image.data, np.uint8).reshape(slm.output.height, slm.output.width, 4)
    finally:
        connection.close()


def slm(tmp_path: Path, x_display: str, **keys: object) -> DisplaySLM:
    path = tmp_path / "display.toml"
    path.write_text(profile_text(x_display, **keys))
    driver = slm_for(load_profile(path))
    assert isinstance(driver, DisplaySLM)
    return driver


def test_the_window_lands_on_the_output_named_by_its_edid_and_shows_exact_gray_levels(
        tmp_path: Path, x_display: str) -> None:
    rng = np.random.default_rng(5)
    height, width = SLM_SCREEN[1], SLM_SCREEN[0]
    patterns = [rng.integers(0, 256, (height, width), dtype=np.uint8),
                (np.arange(height * width) % 256).astype(np.uint8).reshape(height, width),
                (np.indices((height, width)).sum(axis=0) % 2 * 255).astype(np.uint8),
                np.full((height, width), 254, np.uint8)]
    with slm(tmp_path, x_display, edid_name="DELL E178WFP") as display_slm:
        assert display_slm.output is not None and display_slm.output.screen == 1
        stamps = []
        for pattern in patterns:
            shown = display_slm.show_gray(pattern)
            pixels = read_back(x_display, display_slm)
            for byte in range(3):  # B, G, R: the gray level, exactly
                assert np.array_equal(pixels[:, :, byte], pattern), byte
            assert np.array_equal(shown, pattern)
            stamps.append(display_slm.presented_at)
        assert len(set(stamps)) == len(patterns) and all(stamp.endswith("+00:00") for stamp in stamps)
        assert display_slm.displayed_frame() == len(patterns)


def test_phases_through_lookup_tables_reach_the_screen_as_encoded(tmp_path: Path, x_display: str) -> None:
    measured = PhaseLUT(np.linspace(0.0, 1.8 * np.pi, 256) ** 1.1 / (1.8 * np.pi) ** 0.1)
    table = save_lut(tmp_path / "green.csv", measured)
    phase = np.random.default_rng(2).uniform(-np.pi, np.pi, (SLM_SCREEN[1], SLM_SCREEN[0])).astype(np.float32)
    for keys in ({}, {"flip_x": True, "grating_period_px": [0, 7]}):
        for lut in ({}, {"lut": {"green": str(table)}}):
            text = profile_text(x_display, edid_serial="G340H86P4FLH", **keys)
            if lut:
                text = text.replace("[laser]", f"[slm.lut]\ngreen = \"{table}\"\n\n[laser]")
            path = tmp_path / "phase.toml"
            path.write_text(text)
            with slm_for(load_profile(path)) as display_slm:
                encoded = display_slm.encode(phase, "green")
                display_slm.show_phase(phase, "green")
                assert np.array_equal(read_back(x_display, display_slm)[:, :, 1], encoded), (keys, lut)


def test_a_missing_output_or_another_mode_is_one_line_naming_what_there_is(tmp_path: Path, x_display: str) -> None:
    outputs = "screen (screen 0): 320x240 at +0+0, DELL P2415Q serial G3D7F68O0LLB; screen (screen 1): 192x128 at " \
              "+0+0, DELL E178WFP serial G340H86P4FLH"
    with pytest.raises(DeviceError) as caught:
        slm(tmp_path, x_display, edid_name="HOLOEYE GAEA-2").open()
    assert str(caught.value) == f"no output of X display {x_display} match slm.edid_name = 'HOLOEYE GAEA-2' " \
                                f"(outputs: {outputs})"
    with pytest.raises(DeviceError) as caught:
        slm(tmp_path, x_display, edid_name="DELL P2415Q").open()
    assert str(caught.value).startswith("screen shows 320x240 but the profile says slm.width x slm.height = 192x128")
    assert outputs in str(caught.value) and "\n" not in str(caught.value)
    with pytest.raises(DeviceError, match="2 outputs of X display .* match slm.output = 'screen'"):
        slm(tmp_path, x_display, output="screen").open()
    with pytest.raises(DeviceError, match=r"^cannot connect to X display ':1999'"):
        slm(tmp_path, ":1999", edid_name="DELL E178WFP").open()


def test_devices_lists_the_desktop_outputs(x_display: str, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DISPLAY", x_display)
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "desktop outputs (X11):\n  screen (screen 0): 320x240 at +0+0, DELL P2415Q serial G3D7F68O0LLB\n" \
           "  screen (screen 1): 192x128 at +0+0, DELL E178WFP serial G340H86P4FLH" in out
    monkeypatch.delenv("DISPLAY")
    assert main(["devices"]) == 0
    assert "desktop outputs (X11):\n  no X display: set $DISPLAY" in capsys.readouterr().out


def test_a_display_profile_must_name_its_output(tmp_path: Path) -> None:
    path = tmp_path / "unnamed.toml"
    path.write_text(profile_text(":0"))
    with pytest.raises(Exception, match=r"slm.driver: the display driver needs the SLM's output: slm.edid_name"):
        load_profile(path)


@pytest.mark.parametrize("blob, fields", [
    ("dell-e178wfp-vga.bin", ("DEL", 53270, 877022280, "DELL E178WFP", "G340H86P4FLH", (1440, 900))),
    ("dell-p2415q-hdmi1.4.bin", ("DEL", 41152, 810306626, "DELL P2415Q", "G3D7F68O0LLB", (3840, 2160))),
    ("hp-lp2480zx-dp.bin", ("HWP", 9973, 16843009, "HP LP2480zx", "3CM820000N", (1920, 1200))),
    ("oculus-rift-dk1-hdmi.bin", ("OVR", 1, 0, "Rift DK", "Serial", (1280, 800))),
])
def test_edid_of_real_monitors(blob: str, fields: tuple[object, ...]) -> None:
    edid = parse_edid((EDIDS / blob).read_bytes())
    assert (edid.manufacturer, edid.product_code, edid.serial_number, edid.name, edid.serial_text,
            edid.preferred_mode) == fields


def test_edid_refusals() -> None:
    data = bytearray((EDIDS / "dell-e178wfp-vga.bin").read_bytes())
    data[60] ^= 1
    with pytest.raises(DeviceError, match="EDID checksum wrong: the base block sums to 1 modulo 256"):
        parse_edid(bytes(data))
    with pytest.raises(DeviceError, match="not an EDID: 12 bytes"):
        parse_edid(b"\0" * 12)
    assert os.path.getsize(EDIDS / "dell-e178wfp-vga.bin") == 128
