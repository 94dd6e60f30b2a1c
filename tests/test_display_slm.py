"""The `display` SLM driver on a real X server (Xvfb with two screens, each with its RandR output, the EDIDs of two
real monitors set on them), and the EDID parser on real monitors' EDIDs (tests/data/edid/README.md)."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_mono_camera import finished_run, store_registration

from benchctl.capture.raw import decode_raw
from benchctl.cli import main
from benchctl.devices.errors import DeviceError
from benchctl.devices.slm import display as display_module
from benchctl.devices.slm import save_lut, slm_for
from benchctl.devices.slm.display import DisplaySLM, presented_time
from benchctl.devices.slm.edid import parse_edid
from benchctl.optics.phase_encoding import PhaseLUT
from benchctl.profiles import load_profile

EDIDS = Path(__file__).with_name("data") / "edid"
SLM_SCREEN = (192, 128)  # screen 1: the SLM; screen 0 is the desktop monitor
pytestmark = [pytest.mark.third_party,
              pytest.mark.skipif(shutil.which("Xvfb") is None, reason="needs Debian's xvfb (.ci/run installs it)")]


Screen = tuple[int, int, int, str]  # width, height, depth, EDID file


def serve(number: int, screens: tuple[Screen, ...]) -> subprocess.Popen[bytes]:
    """Xvfb as display :`number` with one screen per (width, height, depth, EDID file), started: each screen's RandR
    output carries the EDID, each CRTC's gamma ramp the identity, as on a desktop (Xvfb leaves it uninitialised:
    zeros or garbage); -noreset: all that stays when the client that set it leaves."""
    from Xlib import display

    layout = [argument for screen, (width, height, depth, _) in enumerate(screens)
              for argument in ("-screen", str(screen), f"{width}x{height}x{depth}")]
    server = subprocess.Popen(["Xvfb", f":{number}", *layout, "-nolisten", "tcp", "-noreset"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(100):
            if Path(f"/tmp/.X11-unix/X{number}").exists():
                break
            time.sleep(0.05)
        time.sleep(0.2)
        connection = display.Display(f":{number}")
        for screen, (_, _, _, blob) in enumerate(screens):
            resources = connection.screen(screen).root.xrandr_get_screen_resources()
            set_edid(connection, resources.outputs[0], (EDIDS / blob).read_bytes())
            set_gamma(connection, resources.crtcs[0], 1.0)
        connection.sync()
        connection.close()
    except BaseException:
        stop(server)  # never left running when its set-up fails
        raise
    return server


def stop(server: subprocess.Popen[bytes]) -> None:
    server.terminate()
    server.wait()


@contextmanager
def xvfb(*screens: Screen) -> Iterator[str]:
    """`serve` on a free display number; its name (":N")."""
    number = next(n for n in range(90, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists()
                  and not Path(f"/tmp/.X{n}-lock").exists())
    server = serve(number, screens)
    try:
        yield f":{number}"
    finally:
        stop(server)


@pytest.fixture(scope="module")
def x_display() -> Iterator[str]:
    """Xvfb with screen 0 320x240 showing a Dell P2415Q and screen 1 192x128 (the SLM) a Dell E178WFP, at depth 24."""
    with xvfb((320, 240, 24, "dell-p2415q-hdmi1.4.bin"), (*SLM_SCREEN, 24, "dell-e178wfp-vga.bin")) as name:
        yield name


def set_edid(connection: Any, output: int, blob: bytes) -> None:
    from Xlib import X

    connection.xrandr_change_output_property(output, connection.intern_atom("EDID"), connection.intern_atom("INTEGER"),
                                             X.PropModeReplace, (8, blob))


def set_gamma(connection: object, crtc: int, gamma: float) -> None:
    """A 256-entry ramp out = in ** (1 / gamma) on every colour of `crtc` (1.0: the identity)."""
    ramp = [round(65535 * (i / 255) ** (1 / gamma)) for i in range(256)]
    connection.xrandr_set_crtc_gamma(crtc, 256, ramp, ramp, ramp)  # type: ignore[attr-defined]


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


def test_frames_are_presented_at_a_vblank_after_their_request(tmp_path: Path, x_display: str) -> None:
    """Through X11 Present (Xvfb's fake 60 Hz vblank): each frame's presentation time is the vblank's, after the
    request and before show_gray returned, later than the previous one; the pixels are still exact; the settle
    wait counts from the vblank (so it is shorter than settle_ms by the time since then)."""
    rng = np.random.default_rng(8)
    with slm(tmp_path, x_display, edid_name="DELL E178WFP", settle_ms=50) as display_slm:
        assert display_slm.info()["presentation"].startswith("X11 Present: vsync'd")
        assert display_slm.info()["output"].startswith("screen (screen 1): 192x128")
        waits: list[float] = []
        display_slm.sleep = waits.append
        spans = []
        for _ in range(4):
            pattern = rng.integers(0, 256, (SLM_SCREEN[1], SLM_SCREEN[0]), dtype=np.uint8)
            before = datetime.now(timezone.utc)
            display_slm.show_gray(pattern)
            spans.append((before, datetime.fromisoformat(display_slm.presented_at), datetime.now(timezone.utc)))
            assert np.array_equal(read_back(x_display, display_slm)[:, :, 1], pattern)
    for before, presented, after in spans:
        assert before <= presented <= after
    presented = [span[1] for span in spans]
    assert presented == sorted(presented) and len(set(presented)) == len(presented)
    assert all(0 < wait < 0.05 for wait in waits)


def test_a_frame_the_server_does_not_present_in_time_is_an_error_and_the_next_one_shows(
        tmp_path: Path, x_display: str, monkeypatch: pytest.MonkeyPatch) -> None:
    pattern = np.full((SLM_SCREEN[1], SLM_SCREEN[0]), 99, np.uint8)
    with slm(tmp_path, x_display, edid_name="DELL E178WFP") as display_slm:
        timeout_s = display_module.PRESENT_TIMEOUT_S
        monkeypatch.setattr(display_module, "PRESENT_TIMEOUT_S", 0.0)  # no vblank comes that fast
        with pytest.raises(DeviceError) as caught:
            display_slm.show_gray(pattern)
        assert str(caught.value) == ("SLM (display slm.edid_name = 'DELL E178WFP'): the X server did not complete "
                                     "presenting frame 1 within 0 s: is the output switched off or in power saving?")
        monkeypatch.setattr(display_module, "PRESENT_TIMEOUT_S", timeout_s)
        display_slm.show_gray(pattern + 1)  # frame 1's late notification is passed over
        assert np.array_equal(read_back(x_display, display_slm)[:, :, 0], pattern + 1)


def test_without_present_frames_go_straight_into_the_window(tmp_path: Path, x_display: str,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """An X server without the Present extension (Xvfb always has it, so the client is told it has not): the frame
    is written into the window, exact; presented_at is when XSync returned, the settle wait is settle_ms, and the
    record says so."""
    from Xlib import display

    asked = display.Display.query_extension
    monkeypatch.setattr(display.Display, "query_extension",
                        lambda self, name: None if name == "Present" else asked(self, name))
    pattern = (np.indices((SLM_SCREEN[1], SLM_SCREEN[0])).sum(axis=0) % 251).astype(np.uint8)
    with slm(tmp_path, x_display, edid_name="DELL E178WFP", settle_ms=20) as display_slm:
        assert display_slm.info()["presentation"].startswith("XPutImage into the window: no Present extension")
        waits: list[float] = []
        display_slm.sleep = waits.append
        before = datetime.now(timezone.utc)
        display_slm.show_gray(pattern)
        assert before <= datetime.fromisoformat(display_slm.presented_at) <= datetime.now(timezone.utc)
        assert np.array_equal(read_back(x_display, display_slm)[:, :, 2], pattern) and waits == [0.02]


def test_a_present_time_off_this_machines_clock_is_not_taken() -> None:
    assert presented_time(2_500_000, 2.4, 2.6) == 2.5
    assert presented_time(2_500_000, 2.6, 2.7) is None  # before the request: another machine's clock
    assert presented_time(9_000_000, 2.6, 2.7) is None


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


def test_an_output_whose_gamma_ramp_is_not_the_identity_is_refused(tmp_path: Path, x_display: str) -> None:
    from Xlib import display

    connection = display.Display(x_display)
    crtc = connection.screen(1).root.xrandr_get_screen_resources().crtcs[0]
    try:
        set_gamma(connection, crtc, 2.2)
        connection.sync()
        with pytest.raises(DeviceError, match=r"^screen: its red gamma ramp is not the identity, so the panel would "
                                              r"not get the gray levels sent: `xrandr --output screen --gamma 1:1:1`"):
            slm(tmp_path, x_display, edid_name="DELL E178WFP").open()
    finally:
        set_gamma(connection, crtc, 1.0)
        connection.sync()  # close() alone may leave the request unsent
        connection.close()


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


def read_words(x_display: str, slm: DisplaySLM) -> np.ndarray:
    """The SLM output's pixels as the X server holds them, as (H, W) 32-bit words (depths 24 and 30)."""
    return read_back(x_display, slm).view("<u4")[:, :, 0]


@pytest.mark.parametrize("depth, bit_depth", [(24, 8), (30, 8), (30, 10)])
def test_every_gray_level_reaches_each_channel_at_the_screens_depth(tmp_path: Path, depth: int,
                                                                     bit_depth: int) -> None:
    """On a 10-bit desktop (depth 30: R, G, B of 10 bits at bits 20, 10 and 0) an 8-bit gray level g goes into every
    channel's top 8 bits (g << 2; the low bits zero, so a link that drops, rounds or dithers them gives g), and a
    10-bit SLM's levels go in whole; at depth 24, as they are."""
    channel_bits = depth // 3
    levels = 1 << bit_depth
    pattern = (np.arange(SLM_SCREEN[0] * SLM_SCREEN[1]) * 7 % levels).reshape(SLM_SCREEN[1], SLM_SCREEN[0])
    pattern = pattern.astype(np.uint8 if bit_depth == 8 else np.uint16)
    assert set(np.unique(pattern)) == set(range(levels))
    with xvfb((*SLM_SCREEN, depth, "dell-e178wfp-vga.bin")) as name:
        with slm(tmp_path, name, edid_name="DELL E178WFP", bit_depth=bit_depth) as display_slm:
            assert display_slm.info()["pixels"] == f"depth {depth} ({channel_bits}/{channel_bits}/{channel_bits} " \
                                                   "bits per R/G/B)"
            display_slm.show_gray(pattern)
            words = read_words(name, display_slm)
    mask = (1 << channel_bits) - 1
    for shift in (0, channel_bits, 2 * channel_bits):
        assert np.array_equal(words >> shift & mask, pattern.astype(np.uint32) << (channel_bits - bit_depth)), shift
    assert not (words >> 3 * channel_bits).any()


def test_a_screen_whose_channels_cannot_hold_the_gray_levels_is_refused(tmp_path: Path) -> None:
    """Depth 16 (5/6/5 bits) cannot carry 8-bit gray, nor depth 24 a 10-bit SLM's: one line at open, nothing shown."""
    with xvfb((*SLM_SCREEN, 16, "dell-e178wfp-vga.bin"), (*SLM_SCREEN, 24, "hp-lp2480zx-dp.bin")) as name:
        with pytest.raises(DeviceError) as caught:
            slm(tmp_path, name, edid_name="DELL E178WFP").open()
        assert str(caught.value) == (f"screen (screen 0 of X display {name}) is at depth 16 (5/6/5 bits per R/G/B): "
                                     "the SLM's 8-bit gray levels need 8 bits in every channel; run that output's X "
                                     "screen at depth 24 or 30 (or set slm.bit_depth to what the panel takes)")
        with pytest.raises(DeviceError, match=r"^screen \(screen 1 of X display :\d+\) is at depth 24 \(8/8/8 bits per "
                                              r"R/G/B\): the SLM's 10-bit gray levels need 10 bits"):
            slm(tmp_path, name, edid_name="HP LP2480zx", bit_depth=10).open()


@pytest.mark.parametrize("depth, spoil, refused", [
    (30, "depth", r"the frame's pixels: BadMatch \(request opcode 72\.0\)"),  # depth-24 pixels, a 10-bit desktop
    (24, "crtc", r"presenting it: XError \(request opcode \d+\.1\)"),  # PresentPixmap on a CRTC that is not there
])
def test_an_x_error_ends_the_frame_in_one_line_and_it_is_not_counted_as_presented(tmp_path: Path, depth: int,
                                                                                  spoil: str, refused: str) -> None:
    """The X server refuses a request after the fact (as a depth-24 frame on a 10-bit desktop was, BadMatch, while the
    frame was recorded as presented): the frame fails with one line naming the error, at once (not after the wait
    for its vblank), before it is counted, and the next good frame shows."""
    blank = np.zeros((SLM_SCREEN[1], SLM_SCREEN[0]), np.uint8)
    with xvfb((*SLM_SCREEN, depth, "dell-e178wfp-vga.bin")) as name:
        with slm(tmp_path, name, edid_name="DELL E178WFP") as display_slm:
            display_slm.show_gray(blank + 7)
            shown, presented = display_slm.displayed_frame(), display_slm.presented_at
            layout, presenter = display_slm._layout, display_slm._presenter
            assert layout is not None and presenter is not None
            if spoil == "depth":
                display_slm._layout = dataclasses.replace(layout, depth=24)
            else:
                presenter._crtc = 0xBAD
            started = time.monotonic()
            with pytest.raises(DeviceError) as caught:
                display_slm.show_gray(blank + 9)
            assert time.monotonic() - started < display_module.PRESENT_TIMEOUT_S
            assert re.fullmatch(rf"SLM \(display slm.edid_name = 'DELL E178WFP'\): the X server refused {refused}",
                                str(caught.value)), str(caught.value)
            assert (display_slm.displayed_frame(), display_slm.presented_at) == (shown, presented)
            display_slm._layout, presenter._crtc = layout, display_slm.output.crtc  # type: ignore[union-attr]
            display_slm.show_gray(blank + 11)
            assert (read_words(name, display_slm) & 0xFF == (11 << (depth // 3 - 8)) & 0xFF).all()


def test_an_x_server_that_goes_away_is_one_line_and_the_next_frame_connects_again(tmp_path: Path) -> None:
    screens = ((*SLM_SCREEN, 24, "dell-e178wfp-vga.bin"),)
    number = next(n for n in range(90, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists()
                  and not Path(f"/tmp/.X{n}-lock").exists())
    server = serve(number, screens)
    pattern = (np.indices((SLM_SCREEN[1], SLM_SCREEN[0])).sum(axis=0) % 256).astype(np.uint8)
    try:
        with slm(tmp_path, f":{number}", edid_name="DELL E178WFP") as display_slm:
            display_slm.show_gray(pattern)
            shown = display_slm.displayed_frame()
            stop(server)
            for _ in range(2):  # the frame that finds it gone, and the next one, which cannot connect
                with pytest.raises(DeviceError) as caught:
                    display_slm.show_gray(pattern)
                assert str(caught.value).startswith(
                    f"SLM (display slm.edid_name = 'DELL E178WFP'): lost its X display :{number} (X server stopped or "
                    f"restarted?) and could not show the frame on it again: cannot connect to X display ':{number}'")
                assert "\n" not in str(caught.value) and display_slm.displayed_frame() == shown
            server = serve(number, screens)
            display_slm.show_gray(255 - pattern)
            assert display_slm.displayed_frame() == shown + 1
            assert np.array_equal(read_back(f":{number}", display_slm)[:, :, 1], 255 - pattern)
    finally:
        stop(server)


def test_an_unreadable_edid_is_named_and_passed_over(tmp_path: Path, x_display: str,
                                                     capsys: pytest.CaptureFixture[str],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The desktop monitor's EDID with a bad checksum, then cut to 100 bytes: `benchctl devices` still lists both
    outputs and says why one EDID cannot be read; the SLM, named by its own EDID, opens; a profile naming the
    unreadable monitor's EDID is refused naming that output (it may be the one meant)."""
    from Xlib import display

    good = (EDIDS / "dell-p2415q-hdmi1.4.bin").read_bytes()
    bad = bytearray(good)
    bad[60] ^= 1
    connection = display.Display(x_display)
    output = connection.screen(0).root.xrandr_get_screen_resources().outputs[0]
    monkeypatch.setenv("DISPLAY", x_display)
    try:
        for blob, why in ((bytes(bad), "EDID checksum wrong: the base block sums to 255 modulo 256, not 0"),
                          (good[:100], "not an EDID: 100 bytes, header 00ffffffffffff00 (expected 00ffffffffffff00)")):
            set_edid(connection, output, blob)
            connection.sync()
            assert main(["devices"]) == 0
            assert f"desktop outputs (X11):\n  screen (screen 0): 320x240 at +0+0, EDID unreadable ({why})\n" \
                   "  screen (screen 1): 192x128 at +0+0, DELL E178WFP serial G340H86P4FLH" in capsys.readouterr().out
            with slm(tmp_path, x_display, edid_name="DELL E178WFP") as display_slm:
                assert display_slm.output is not None and display_slm.output.screen == 1
            with pytest.raises(DeviceError) as caught:
                slm(tmp_path, x_display, edid_name="DELL P2415Q", width=320, height=240).open()
            assert str(caught.value).startswith(f"no output of X display {x_display} matches slm.edid_name = 'DELL "
                                                f"P2415Q', and the EDID of screen (screen 0) cannot be read: if that "
                                                f"is the SLM, name it by connector (slm.output) (outputs: screen "
                                                f"(screen 0): 320x240 at +0+0, EDID unreadable ({why}); ")
    finally:
        set_edid(connection, output, good)
        connection.sync()
        connection.close()


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


LAB_EDITS = [  # (line of hardware_profiles/genicam_hdmi.toml, what this lab writes there): CHECK lines only
    ("roi = [880, 1600] ", "roi = [96, 160] "),
    ('edid_name = "GAEA-2" ', 'edid_name = "DELL E178WFP" '),
    ('# x_display = ":0" ', 'x_display = "{x_display}" '),
    ("width = 1920 ", "width = 192 "),
    ("height = 1080 ", "height = 128 "),
    ('port = "/dev/ttyUSB0" ', 'port = "sim://rgb-laser" '),
    ('serial = "12345678" ', 'serial = "1" '),
    ('pixel_format = "BayerRG12" ', 'pixel_format = "Mono16" '),
    ("# region = [0, 0, 2048, 2048] ", "region = [0, 0, 384, 256] "),
]


def test_a_lab_runs_the_colour_capture_after_editing_only_the_example_profile(tmp_path: Path,
                                                                              x_display: str) -> None:
    """The issue's "done when": hardware_profiles/genicam_hdmi.toml with only lines marked CHECK changed, for a
    bench whose SLM is the Dell E178WFP output of this X server, whose camera is Aravis's fake camera in Mono16 and
    whose laser is the simulated unit speaking the profile's protocol; the shipped colour capture runs on it. The
    procedure is told to use a stored registration and to skip lookup-table calibration (the fake camera draws its
    own pattern, so neither can be measured on it), and to take one frame without dark (its pattern moves from
    frame to frame)."""
    text = (Path(__file__).parents[1] / "hardware_profiles" / "genicam_hdmi.toml").read_text()
    lines = text.splitlines()
    for line, edited in LAB_EDITS:
        (number,) = [n for n, text_line in enumerate(lines) if text_line.startswith(line)]
        assert "CHECK" in lines[number] or "CHECK" in lines[number - 1], line  # (height's is on width's line)
        lines[number] = edited.format(x_display=x_display) + lines[number][len(line):]
    profile = tmp_path / "lab.toml"
    profile.write_text("\n".join(lines) + "\n")
    store_registration(profile, 2.0, (0.5, 0.5))
    procedure_text = (Path(__file__).parents[1] / "procedures" / "colour_capture.toml").read_text()
    procedure = tmp_path / "capture.toml"
    procedure.write_text(procedure_text.replace('registration = "auto"', 'registration = "stored"').replace(
        "frames = 2 ", "frames = 1 ").replace("dark_frames = 1 ", "dark_frames = 0 ").replace(
        "[parameters]", '[parameters]\nlut_calibration = "skip"'))
    assert main(["run", str(procedure), "--profile", str(profile), "--out", str(tmp_path / "runs")]) == 0
    folder, metrics, done = finished_run(tmp_path / "runs")
    devices = json.loads((folder / "devices.json").read_text())
    assert devices["slm"]["presentation"].startswith("X11 Present: vsync'd")
    assert "DELL E178WFP serial G340H86P4FLH" in devices["slm"]["output"]
    assert devices["camera"]["pixel_format"] == "Mono16 (16 bit, mono)"
    exposures = [step["result"] for step in done if step["step"].startswith(("probe/", "capture/"))]
    presented = [datetime.fromisoformat(result["slm_presented_at"]) for result in exposures]
    assert len(presented) == 6 and presented == sorted(presented)
    for result in exposures:
        assert decode_raw(folder / result["folder"] / result["frames"][0]).layout == "mono"
    assert set(metrics["targets"][0]["colours"]) == {"red", "green", "blue"}


def test_showing_is_the_windows_own_frame_black_at_first(tmp_path: Path, x_display: str) -> None:
    with slm(tmp_path, x_display, edid_name="DELL E178WFP") as display_slm:
        opened = display_slm.showing()  # the new window's black background, as the X server holds it
        assert opened.frame is not None and not opened.frame.any() and opened.frame_id == 0
        assert opened.by is not None and opened.by.endswith(f"(pid {os.getpid()})")
        assert not read_back(x_display, display_slm)[:, :, :3].any()
        gray = (np.arange(SLM_SCREEN[0] * SLM_SCREEN[1]) % 256).astype(np.uint8).reshape(SLM_SCREEN[1], -1)
        display_slm.show_gray(gray)
        shown = display_slm.showing()
        assert np.array_equal(shown.frame, gray) and shown.frame_id == 1 and shown.at == display_slm.presented_at
        assert np.array_equal(read_back(x_display, display_slm)[:, :, 2], shown.frame)


def start_xvfb(number: int) -> subprocess.Popen:
    """Xvfb :number with one 192 x 128 screen (its output is named "screen"), once its socket is there."""
    server = subprocess.Popen(["Xvfb", f":{number}", "-screen", "0", f"{SLM_SCREEN[0]}x{SLM_SCREEN[1]}x24",
                               "-nolisten", "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(100):
        if Path(f"/tmp/.X11-unix/X{number}").exists():
            break
        time.sleep(0.05)
    time.sleep(0.2)
    return server


def test_the_console_says_a_lost_x_server_in_one_line_and_connects_again(tmp_path: Path) -> None:
    """The X server of a display SLM dies under the console: the page gets one line (never a 500 and a traceback),
    the SLM panel says it is lost, and once an X server is back the SLM connects again without a restart."""
    from starlette.testclient import TestClient

    from benchctl.console.app import create_app
    from console_bench import ORIGIN, TOKEN, access, make_console

    number = next(n for n in range(200, 300) if not Path(f"/tmp/.X11-unix/X{n}").exists()
                  and not Path(f"/tmp/.X{n}-lock").exists())
    profile = tmp_path / "display.toml"
    profile.write_text(profile_text(f":{number}", output="screen") + "\n[optics]\ndistance_mm = 20\nroi = [96, 160]\n")
    server = start_xvfb(number)
    console = make_console(load_profile(profile), tmp_path)
    try:
        with TestClient(create_app(console, access()), base_url=ORIGIN) as client:  # a 500 would raise here
            client.headers.update({"x-benchctl-token": TOKEN, "origin": ORIGIN})
            assert client.post("/api/slm", json={"kind": "flat"}).status_code == 200
            server.kill()
            server.wait()
            lost = client.post("/api/slm", json={"kind": "flat", "phase_rad": 1.0})
            assert lost.status_code == 400 and "\n" not in lost.json()["error"], lost.text
            assert "SLM (display slm.output = 'screen')" in lost.json()["error"]
            slm = client.get("/api/state").json()["slm"]
            assert slm["connected"] is False and slm["error"].endswith("(connect again when it is back)")
            again = client.post("/api/slm", json={"kind": "flat"}).json()["error"]
            assert again.startswith("SLM not connected: ") and "connect again" in again
            server = start_xvfb(number)
            connected = client.post("/api/connect", json={"device": "slm"}).json()
            assert connected["connected"] is True and connected["error"] is None
            shown = client.post("/api/slm", json={"kind": "blank"})
            assert shown.status_code == 200 and console.slm.held.device is not None
            assert not read_back(f":{number}", console.slm.held.device)[:, :, :3].any()  # the new server shows it
    finally:
        console.close()
        server.kill()
        server.wait()
