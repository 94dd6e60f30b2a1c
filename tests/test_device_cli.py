"""`benchctl laser`, `benchctl slm` and `benchctl sim` on the simulated bench, each call a separate command."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from benchctl.cli import main


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _line(stdout: str, channel: str) -> str:
    return next(line for line in stdout.splitlines() if line.startswith(channel))


def test_setpoint_persists_between_commands(capsys, small_profile_path):
    p = str(small_profile_path)
    code, out, _ = _run(capsys, "laser", "set", "red", "20mW", "-p", p)
    assert code == 0 and "20 mW" in out
    code, out, _ = _run(capsys, "laser", "set", "green", "5%", "-p", p)
    assert code == 0 and "2 mW" in out  # 5 % of 40 mW
    code, out, _ = _run(capsys, "laser", "status", "-p", p)
    assert code == 0
    assert "20 mW" in _line(out, "red") and "emission off" in _line(out, "red")
    assert "2 mW" in _line(out, "green")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["laser", "set", "red", "50mW"], "above"),
        (["laser", "set", "red", "20"], "20"),
        (["laser", "set", "purple", "1mW"], "purple"),
        (["laser", "on", "purple"], "purple"),
        (["laser", "on", "red", "--for", "soon"], "soon"),
    ],
)
def test_laser_user_errors_are_one_line(capsys, small_profile_path, argv, message):
    code, _, err = _run(capsys, *argv, "-p", str(small_profile_path))
    assert code == 2
    assert err.startswith("benchctl: error:") and err.count("\n") == 1 and message in err


def test_on_for_a_time_then_off(capsys, small_profile_path):
    p = str(small_profile_path)
    code, out, _ = _run(capsys, "laser", "on", "blue", "--for", "50ms", "-p", p)
    assert code == 0
    assert "blue: emission ON at 0 mW (read back; measured 0 mW; not the profile's setpoint of 2 mW) for 0.05 s" in out
    assert "blue: emission off" in out
    assert "emission off" in _line(_run(capsys, "laser", "status", "-p", p)[1], "blue")


def test_on_at_a_zero_setpoint_says_no_light_comes_out(capsys, small_profile_path):
    p = str(small_profile_path)
    assert _run(capsys, "laser", "set", "green", "0mW", "-p", p)[0] == 0
    code, out, _ = _run(capsys, "laser", "on", "green", "--for", "10ms", "-p", p)
    assert code == 0 and "green: the setpoint is 0 mW, so no light comes out" in out
    assert _run(capsys, "laser", "set", "blue", "1mW", "-p", p)[0] == 0
    assert "setpoint is 0 mW" not in _run(capsys, "laser", "on", "blue", "--for", "10ms", "-p", p)[1]


def test_leave_on_says_so_and_off_turns_it_off(capsys, small_profile_path):
    p = str(small_profile_path)
    code, out, _ = _run(capsys, "laser", "on", "red", "--leave-on", "-p", p)
    assert code == 0 and "LEFT ON" in out
    assert "emission ON" in _line(_run(capsys, "laser", "status", "-p", p)[1], "red")
    code, out, _ = _run(capsys, "laser", "off", "-p", p)
    assert code == 0 and "red: emission off" in out
    assert "emission off" in _line(_run(capsys, "laser", "status", "-p", p)[1], "red")


def test_interlock_open_refuses_emission(capsys, small_profile_path):
    p = str(small_profile_path)
    assert _run(capsys, "sim", "fault", "rgb-laser", "interlock_open")[0] == 0
    code, _, err = _run(capsys, "laser", "on", "red", "--for", "10ms", "-p", p)
    assert code == 2 and "interlock" in err.lower()
    assert "emission off" in _line(_run(capsys, "laser", "status", "-p", p)[1], "red")
    assert _run(capsys, "sim", "fault", "rgb-laser", "--clear")[0] == 0
    assert _run(capsys, "laser", "on", "red", "--for", "10ms", "-p", p)[0] == 0


def test_sim_reset_forgets_setpoints(capsys, small_profile_path, sim_state_dir):
    p = str(small_profile_path)
    _run(capsys, "laser", "set", "red", "10mW", "-p", p)
    code, out, _ = _run(capsys, "sim", "status")
    assert code == 0 and str(sim_state_dir) in out and "rgb-laser" in out
    assert _run(capsys, "sim", "reset")[0] == 0
    assert "10 mW" not in _line(_run(capsys, "laser", "status", "-p", p)[1], "red")


def test_command_needing_a_missing_section_names_it(capsys, tmp_path, small_profile_path):
    text = small_profile_path.read_text()
    laser_only = tmp_path / "laser_only.toml"
    laser_only.write_text(text[text.index("[laser]"):])
    code, _, err = _run(capsys, "slm", "info", "-p", str(laser_only))
    assert code == 2 and "[slm]" in err


@pytest.mark.slow  # takes seconds to a minute on two cores
def test_sigterm_during_laser_on_turns_emission_off(tmp_path, small_profile_path, sim_state_dir):
    env = {**os.environ, "BENCHCTL_SIM_DIR": str(sim_state_dir)}
    cmd = [sys.executable, "-m", "benchctl"]
    proc = subprocess.Popen([*cmd, "laser", "on", "green", "--for", "60s", "-p", str(small_profile_path)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    line = ""
    while "emission ON" not in line and time.monotonic() < deadline:
        line = proc.stdout.readline()
    assert "emission ON" in line, proc.stderr.read()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signal.SIGTERM, err
    status = subprocess.run([*cmd, "laser", "status", "-p", str(small_profile_path)], env=env,
                            capture_output=True, text=True, timeout=60)
    assert "emission off" in _line(status.stdout, "green")


def test_slm_show_gray_image_then_blank(capsys, tmp_path, small_profile_path):
    from benchctl.devices.sim.slm import read_displayed

    gray = (np.arange(64 * 96).reshape(64, 96) % 256).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "frame.png"), gray)
    p = str(small_profile_path)
    code, out, _ = _run(capsys, "slm", "show", str(tmp_path / "frame.png"), "-p", p)
    assert code == 0
    shown, _ = read_displayed()
    assert np.array_equal(shown, gray)
    assert _run(capsys, "slm", "blank", "-p", p)[0] == 0
    assert not read_displayed()[0].any()


def test_slm_show_phase_encodes_for_the_channel(capsys, tmp_path, small_profile_path):
    from benchctl.devices.sim.slm import read_displayed

    np.save(tmp_path / "phase.npy", np.full((64, 96), np.pi / 2))
    code, _, _ = _run(capsys, "slm", "show", str(tmp_path / "phase.npy"), "--channel", "red",
                      "-p", str(small_profile_path))
    assert code == 0
    assert (read_displayed()[0] == 64).all()  # pi / 2 on the linear 8-bit table


@pytest.mark.parametrize(
    "name, content, extra, message",
    [
        ("small.png", np.zeros((10, 10), np.uint8), [], "10"),
        ("colour.png", np.zeros((64, 96, 3), np.uint8), [], "channels"),
        ("phase.npy", np.zeros((64, 96)), [], "--channel"),
        ("phase.npy", np.zeros((64, 96)), ["--channel", "violet"], "violet"),
        ("missing.png", None, [], "missing.png"),
    ],
)
def test_slm_show_errors(capsys, tmp_path, small_profile_path, name, content, extra, message):
    path = tmp_path / name
    if content is not None:
        np.save(path, content) if name.endswith(".npy") else cv2.imwrite(str(path), content)
    code, _, err = _run(capsys, "slm", "show", str(path), *extra, "-p", str(small_profile_path))
    assert code == 2 and err.count("\n") == 1 and message in err


def test_slm_info(capsys, small_profile_path):
    code, out, _ = _run(capsys, "slm", "info", "-p", str(small_profile_path))
    assert code == 0 and "96" in out and "64" in out and "sim" in out


CAMERA = """
[camera]
driver = "{driver}"
transport = "sim"

[sim.imaging]
magnification = 1.0

[sim.sensor]
shape = [160, 240]
margin = [4, 6]
"""


@pytest.mark.parametrize("driver", ["sim", "ptp"])
def test_camera_capture_writes_a_dng_rawpy_reads(capsys, tmp_path, small_profile_path, driver):
    from benchctl.capture.raw import decode_raw

    small_profile_path.write_text(small_profile_path.read_text() + CAMERA.format(driver=driver))
    p = str(small_profile_path)
    code, out, _ = _run(capsys, "camera", "info", "-p", p)
    assert code == 0 and ("Canon EOS M10" in out if driver == "ptp" else "sim" in out)
    code, out, _ = _run(capsys, "camera", "capture", "-o", str(tmp_path / "frame.dng"), "-p", p)
    assert code == 0 and "frame.dng" in out
    image = decode_raw(tmp_path / "frame.dng")
    assert image.mosaic.shape == (156, 234)  # the active area: margins cropped
    assert abs(float(image.mosaic.mean())) < 0.01  # lasers off: black level and read noise only
    code, out, _ = _run(capsys, "camera", "capture", "-o", str(tmp_path / "series.dng"), "--frames", "2", "-p", p)
    assert code == 0
    assert sorted(f.name for f in tmp_path.glob("series*")) == ["series-000.dng", "series-001.dng"]
    assert (tmp_path / "series-000.dng").read_bytes() != (tmp_path / "series-001.dng").read_bytes()


def test_camera_capture_checks_the_disk_before_the_first_shutter(capsys, tmp_path, small_profile_path, monkeypatch):
    """Frames of 160 x 240 (76.8 kB as 16-bit DNG pixels), 200 kB free: --frames 5 is refused in one line naming the
    largest count that fits, before anything is captured; 2 are taken."""
    from collections import namedtuple

    from benchctl.devices.sim.state import load_state
    from benchctl.runner import estimates

    small_profile_path.write_text(small_profile_path.read_text() + CAMERA.format(driver="sim"))
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(estimates.shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 200_000, 200_000))
    capture = ["camera", "capture", "-o", str(tmp_path / "series.dng"), "-p", str(small_profile_path), "--frames"]
    code, _, err = _run(capsys, *capture, "5")
    assert code == 2 and err == (f"benchctl: error: {tmp_path}: 200 kB free, and 5 frame(s) of about 76.8 kB need "
                                 "384 kB: at most --frames 2 fits here; free some space or capture elsewhere (-o)\n")
    assert not list(tmp_path.glob("series*")) and "frame" not in load_state("sim-camera")
    code, out, _ = _run(capsys, *capture, "2")
    assert code == 0 and out.count("captured ") == 2


def test_camera_capture_holds_one_frame_in_memory_however_many_it_takes(tmp_path, small_profile_path):
    """Each frame is saved and let go before the next: six frames peak no higher than two (they kept every frame's
    bytes until the end: 5.8 GB for a 2048^2 Mono16 camera's series)."""
    import tracemalloc

    from benchctl.profiles import load_profile
    from benchctl.runner import device_commands

    small_profile_path.write_text(small_profile_path.read_text() + CAMERA.format(driver="sim").replace(
        "shape = [160, 240]", "shape = [400, 600]"))
    profile = load_profile(small_profile_path)
    frame_bytes = 2 * 400 * 600
    peaks = {}
    for count in (2, 6):
        list(device_commands.camera_capture(profile, tmp_path / f"warm-{count}.dng", 1))  # imports, caches
        tracemalloc.start()
        lines = list(device_commands.camera_capture(profile, tmp_path / f"series-{count}.dng", count))
        peaks[count] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert len(lines) == count and len(list(tmp_path.glob(f"series-{count}-*.dng"))) == count
    assert peaks[6] - peaks[2] < frame_bytes, (peaks, frame_bytes)


def test_camera_without_a_camera_section_says_so(capsys, small_profile_path, tmp_path):
    code, _, err = _run(capsys, "camera", "capture", "-o", str(tmp_path / "x.dng"), "-p", str(small_profile_path))
    assert code == 2 and "[camera]" in err


def test_devices_lists_what_this_machine_has(capsys):
    code, out, _ = _run(capsys, "devices")
    assert code == 0
    assert "serial ports:" in out and "PTP cameras:" in out and "framebuffers:" in out
