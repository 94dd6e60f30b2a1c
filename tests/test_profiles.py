"""Hardware profiles: the simulated bench loads exactly; every kind of mistake is a one-line BenchctlError."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

import benchctl
from benchctl.errors import BenchctlError
from benchctl.profiles import LaserChannel, load_profile

REPO_PROFILES = Path(benchctl.__file__).resolve().parents[1] / "hardware_profiles"


def edited(path: Path, old: str, new: str) -> Path:
    """The profile at `path` with one piece of text replaced (which must be there)."""
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))
    return path


def error_of(path: Path) -> str:
    with pytest.raises(BenchctlError) as info:
        load_profile(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    return message


def test_simulated_profile_has_the_papers_bench(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("BENCHCTL_PROFILE", raising=False)
    monkeypatch.chdir(tmp_path)  # no ./hardware_profiles here: falls back to the repository's folder
    profile = load_profile()
    assert profile.path == REPO_PROFILES / "simulated.toml"
    assert profile.name == "simulated"
    assert profile.optics.distance_mm == 70.0 and profile.optics.distance_m == pytest.approx(0.07)
    assert profile.optics.roi == (880, 1600)
    assert (profile.slm.width, profile.slm.height, profile.slm.bit_depth) == (1920, 1088, 8)
    assert profile.slm.pitch_um == 3.74 and profile.slm.pitch_m == pytest.approx(3.74e-6)
    assert profile.slm.shape == (1088, 1920)
    assert profile.channels == (
        LaserChannel(name="red", index=1, wavelength_nm=680.0, max_power_mw=40.0, setpoint_mw=40.0),
        LaserChannel(name="green", index=2, wavelength_nm=520.0, max_power_mw=40.0, setpoint_mw=2.0),
        LaserChannel(name="blue", index=3, wavelength_nm=450.0, max_power_mw=40.0, setpoint_mw=2.0),
    )
    assert profile.channel("green").wavelength_m == pytest.approx(520e-9)
    assert load_profile("simulated") == profile


def test_lookup_order(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, small_profile_path: Path) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("BENCHCTL_PROFILE", str(small_profile_path))
    assert load_profile().name == "small"
    monkeypatch.delenv("BENCHCTL_PROFILE")
    local = tmp_path / "hardware_profiles"
    local.mkdir()
    shutil.copy(small_profile_path, local / "simulated.toml")
    assert load_profile().path == Path("hardware_profiles/simulated.toml")  # ./hardware_profiles first
    shutil.copy(small_profile_path, local / "mybench.toml")
    assert load_profile("mybench").name == "small"
    monkeypatch.setenv("BENCHCTL_PROFILE", "mybench")
    assert load_profile().path == Path("hardware_profiles/mybench.toml")


def test_unknown_name_and_missing_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(BenchctlError, match="hardware profile 'nobench' not found \\(looked for hardware_profiles"):
        load_profile("nobench")
    monkeypatch.setenv("BENCHCTL_PROFILE", "nobench")
    with pytest.raises(BenchctlError, match="from \\$BENCHCTL_PROFILE"):
        load_profile()
    assert "hardware profile not found" in error_of(tmp_path / "missing.toml")


def test_describe_summarises_grid_and_channels() -> None:
    text = load_profile(REPO_PROFILES / "simulated.toml").describe()
    for fragment in ("1088 x 1920", "3.74 um", "70 mm", "880 x 1600", "green", "520 nm", "2 mW (5 %)",
                     "40 mW (100 %)"):
        assert fragment in text, fragment


def test_unknown_channel_lists_the_known_ones(small_profile_path: Path) -> None:
    with pytest.raises(BenchctlError, match="no laser channel 'violet'; known channels: red, green, blue"):
        load_profile(small_profile_path).channel("violet")


def test_defaults_for_optional_keys(small_profile_path: Path) -> None:
    text = small_profile_path.read_text()
    for line in ('name = "small"', 'description = "scaled-down simulated bench for tests"', "index = 1", "index = 2",
                 "index = 3"):
        text = text.replace(line + "\n", "")
    small_profile_path.write_text(text)
    profile = load_profile(small_profile_path)
    assert (profile.name, profile.description) == ("small", "")
    assert [ch.index for ch in profile.channels] == [1, 2, 3]


def test_toml_syntax_error_names_the_line(small_profile_path: Path) -> None:
    message = error_of(edited(small_profile_path, "pitch_um = 8.0", "pitch_um = = 8.0"))
    assert "TOML syntax error" in message and "line 11" in message


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("pitch_um = 8.0", "pitch = 8.0",
         "slm.pitch: unknown key (did you mean 'pitch_um'? known: driver, device, width, height, pitch_um"),
        ("[slm]", "[cameras]\nmodel = 'x'\n\n[slm]",
         "cameras: unknown section (did you mean 'camera'? known: name, description, optics, slm, laser, camera"),
        ("[slm]", "[camera]\ndriver = 'webcam'\n\n[slm]",
         "camera.driver: unknown value 'webcam' (choose from sim, ptp, gphoto2, genicam)"),
        ("wavelength_nm = 520", "wavelenght_nm = 520",
         "laser.channels[1].wavelenght_nm: unknown key (did you mean 'wavelength_nm'?"),
        ("pitch_um = 8.0\n", "", "slm.pitch_um: missing required key"),
        ('driver = "template"', 'driver = "coherent"',
         "laser.driver: unknown value 'coherent' (choose from template, cobolt, obis, sapphire, deepstar)"),
        ("[slm]", "[slm]\nflip_x = 1", "slm.flip_x: expected true or false, got 1 (int)"),
        ("[slm]", "[slm]\ngrating_period_px = [8]", "slm.grating_period_px: expected two numbers [rows, cols]"),
        ("[slm]", '[slm]\ndriver = "framebuffer"', "slm.device: the framebuffer driver needs a device"),
        ('port = "sim://rgb-laser"\n', "", "laser.channels[0].port: no serial port: set laser.port"),
        ("[laser.protocol]", "[laser.protocols]", "laser.protocols: unknown section (did you mean 'protocol'?"),
        ('set_power = "CH{channel}:POW {mw:.2f}"\n', "", "laser.protocol.set_power: missing required key"),
        ("[laser]", "[slm.lut]\nviolet = 'v.csv'\n\n[laser]", "slm.lut.violet: no laser channel 'violet'"),
        ("width = 96", 'width = "96"', "slm.width: expected an integer, got '96' (str)"),
        ("width = 96", "width = 96.0", "slm.width: expected an integer, got 96.0 (float)"),
        ("distance_mm = 20.0", "distance_mm = true",
         "optics.distance_mm: expected a finite number, got True (bool)"),
        ("distance_mm = 20.0", "distance_mm = nan", "optics.distance_mm: expected a finite number, got nan (float)"),
        ("roi = [48, 80]", "roi = [48]", "optics.roi: expected two integers [rows, cols], got [48] (list)"),
        ("roi = [48, 80]", "roi = [48, 0]", "optics.roi[1]: must be > 0, got 0"),
        ("pitch_um = 8.0", "pitch_um = 0", "slm.pitch_um: must be >= 0.1, got 0.0"),
        ("distance_mm = 20.0", "distance_mm = -20.0", "optics.distance_mm: must be > 0, got -20.0"),
        ("bit_depth = 8", "bit_depth = 24", "slm.bit_depth: must be <= 16, got 24"),
        ("wavelength_nm = 450", "wavelength_nm = -450",
         "laser.channels[2].wavelength_nm: must be >= 100, got -450.0"),
        ("setpoint_mw = 2\n", "setpoint_mw = -1\n", "laser.channels[1].setpoint_mw: must be >= 0, got -1.0"),
        ("roi = [48, 80]", "roi = [65, 80]",
         "optics.roi: [65, 80] is larger than the SLM grid 64 x 96 (slm.height x slm.width)"),
        ("roi = [48, 80]", "roi = [48, 80]\ndepth_range_mm = [25, 15]",
         "optics.depth_range_mm: [25.0, 15.0] must be [near, far] with near < far"),
        ("roi = [48, 80]", "roi = [48, 80]\ndepth_range_mm = [0, 15]", "optics.depth_range_mm[0]: must be > 0, got 0"),
        ("setpoint_mw = 40", "setpoint_mw = 41",
         "laser.channels[0].setpoint_mw: 41 mW is above max_power_mw 40 mW"),
        ('name = "blue"', 'name = "red"',
         "laser.channels[2].name: duplicate channel name 'red' (also laser.channels[0].name)"),
        ("index = 3", "index = 1",
         "laser.channels[2].index: duplicate channel index 1 (also laser.channels[0].index)"),
        ('name = "green"', 'name = " "',
         "laser.channels[1].name: channel name must not be empty, got ' '"),
        ("[[laser.channels]]", "[[lasers.channels]]", "lasers: unknown section (did you mean 'laser'?"),
        ("[slm]", "[sim.sensor]\nshape = [30000, 30000]\n\n[slm]",  # was a traceback when the camera rendered it
         "sim.sensor.shape: 30000 x 30000 = 900,000,000 pixels is above the limit of 67,108,864 (set "
         "$BENCHCTL_MAX_PIXELS to raise it)"),
        ("[slm]", '[camera]\ndriver = "genicam"\nregion = [0, 0, 20000, 20000]\n\n[slm]',  # an 800 MB DNG a frame
         "camera.region height x width: 20000 x 20000 = 400,000,000 pixels is above the limit of 67,108,864"),
    ],
)
def test_errors_name_file_key_and_value(small_profile_path: Path, old: str, new: str, expected: str) -> None:
    assert expected in error_of(edited(small_profile_path, old, new))


def test_no_channels(small_profile_path: Path) -> None:
    text = small_profile_path.read_text()
    head = text[: text.index("[[laser.channels]]")]
    small_profile_path.write_text(head.replace("[laser]\n", "[laser]\nchannels = []\n"))
    assert "laser.channels: at least 1 entry required, got 0" in error_of(small_profile_path)


def test_template_driver_needs_its_protocol(small_profile_path: Path) -> None:
    text = small_profile_path.read_text()
    start, end = text.index("[laser.protocol]"), text.index("[[laser.channels]]")
    small_profile_path.write_text(text[:start] + text[end:])
    assert "laser.protocol: the template driver needs a [laser.protocol] section" in error_of(small_profile_path)


def test_a_profile_may_describe_only_some_devices(small_profile_path: Path) -> None:
    text = small_profile_path.read_text()
    small_profile_path.write_text(text[text.index("[laser]"):])  # laser only
    profile = load_profile(small_profile_path)
    assert profile.slm is None and profile.optics is None
    assert [ch.name for ch in profile.channels] == ["red", "green", "blue"]
    with pytest.raises(BenchctlError, match=r"needs a \[slm\] section, which the profile lacks"):
        profile.require("laser", "slm")
    assert profile.section("laser") is profile.laser  # the section itself, typed without its None
    with pytest.raises(BenchctlError, match=rf"^{re.escape(str(small_profile_path))}: this needs a \[optics\] section"):
        profile.section("optics")
    small_profile_path.write_text('name = "empty"\n')
    assert "no device section: give at least one of optics, slm, laser" in error_of(small_profile_path)


def test_device_keys_take_documented_defaults_and_luts_resolve_beside_the_profile(small_profile_path: Path) -> None:
    profile = load_profile(edited(small_profile_path, "[laser]", "[slm.lut]\ngreen = 'luts/g.csv'\n\n[laser]"))
    slm, laser = profile.slm, profile.laser
    assert (slm.driver, slm.device, slm.settle_ms, slm.flip_x, slm.flip_y) == ("sim", None, 100.0, False, False)
    assert (slm.phase_offset_rad, slm.two_pi_gray, slm.grating_period_px) == (0.0, None, (0.0, 0.0))
    assert slm.lut == {"green": (small_profile_path.parent / "luts" / "g.csv").resolve()}
    assert (laser.driver, laser.baudrate, laser.timeout_s, laser.write_delay_s) == ("template", 115200, 1.0, 0.0)
    assert laser.protocol.line_ending == "\r\n" and laser.protocol.ok_reply == "OK"
    assert laser.protocol.power_unit == "mW" and laser.protocol.echo is False
    assert laser.port_of(profile.channel("red")) == "sim://rgb-laser"


def test_camera_section_defaults(small_profile_path: Path) -> None:
    assert load_profile(small_profile_path).camera is None
    with pytest.raises(BenchctlError, match=r"needs a \[camera\] section"):
        load_profile(small_profile_path).require("camera")
    profile = load_profile(edited(small_profile_path, "[slm]", "[camera]\ndriver = 'ptp'\n\n[slm]"))
    cam = profile.camera
    assert (cam.driver, cam.usb_id, cam.transport, cam.frames) == ("ptp", "04a9:32a0", "usb", 1)
    assert (cam.exposure_s, cam.iso, cam.write_properties, cam.image_timeout_s) == (None, None, False, 90.0)


def test_a_scaled_bench_scales_depth_offsets_with_the_grid_side_and_the_distance_with_its_area():
    from benchctl.calibration.geometry import grid_profile

    profile = load_profile("simulated")
    assert profile.section("optics").depth_range_mm == (65.0, 75.0)
    optics = grid_profile(profile, (272, 480), scale_distance=True).section("optics")
    assert optics.distance_mm == pytest.approx(70 / 16)
    assert optics.depth_range_mm == pytest.approx((70 / 16 - 5 / 4, 70 / 16 + 5 / 4))
    tiny = grid_profile(profile, (34, 60), scale_distance=True).section("optics")  # offsets would reach the SLM
    assert tiny.depth_range_mm[0] == pytest.approx(0.5 * tiny.distance_mm)
    assert grid_profile(profile, (272, 480)).section("optics").depth_range_mm == (65.0, 75.0)
