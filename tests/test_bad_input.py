"""Bad input gets one line naming the file, key or value: never a traceback, never unbounded memory or time."""

from __future__ import annotations

import contextlib
import itertools
import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import one_error_line

from benchctl.cli import main
from benchctl.errors import BenchctlError

REPO = Path(__file__).resolve().parents[1]


def png_header(height: int, width: int) -> bytes:
    """A PNG file whose header says height x width (8-bit gray) and whose data is a few compressed zero rows."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 1000))
            + chunk(b"IEND", b""))


# -- image files ----------------------------------------------------------------------------------------------------


def test_a_zero_byte_image_is_one_line_everywhere(tmp_path: Path, small_profile_path: Path, bench_profile_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "data" / "empty.png"
    empty.parent.mkdir()
    empty.write_bytes(b"")
    procedure = tmp_path / "p.toml"
    procedure.write_text(f'procedure = "colour-capture"\n[parameters]\ntargets = ["{empty}"]\n')
    p, bench = str(small_profile_path), str(bench_profile_path)
    for argv in (["generate", str(empty), "-o", str(tmp_path / "g"), "-p", p],
                 ["slm", "show", str(empty), "-p", p],
                 ["run", str(procedure), "-p", bench, "--dry-run"],
                 ["bench", "speed-vs-error", "--targets", str(empty), "--methods", "dpac", "--iterations", "1",
                  "--size", "64x96", "-o", str(tmp_path / "b"), "-p", p],
                 ["train", "--method", "holonet", "--data", str(empty.parent), "--max-steps", "1", "-p", p,
                  "-o", str(tmp_path / "t")]):
        assert one_error_line(capsys, argv).endswith(f"{empty}: empty file (0 bytes), not an image"), argv


def test_pixel_counts_are_bounded_before_decoding_and_the_limit_can_be_raised(
        tmp_path: Path, small_profile_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    from benchctl.images import read_image

    huge = tmp_path / "huge.png"
    huge.write_bytes(png_header(20000, 20000))
    assert huge.stat().st_size < 2000
    line = one_error_line(capsys, ["generate", str(huge), "-o", str(tmp_path / "g"), "-p", str(small_profile_path)])
    assert line == (f"benchctl: error: {huge}: 20000 x 20000 = 400,000,000 pixels is above the limit of 67,108,864 "
                    "(set $BENCHCTL_MAX_PIXELS to raise it)")
    jpeg = tmp_path / "huge.jpg"
    ok, encoded = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))
    data = bytearray(encoded.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", 30000, 30000)
    jpeg.write_bytes(bytes(data))
    with pytest.raises(BenchctlError, match=r"30000 x 30000 = 900,000,000 pixels is above the limit"):
        read_image(jpeg)

    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((64, 96), np.uint8))
    monkeypatch.setenv("BENCHCTL_MAX_PIXELS", "6000")
    with pytest.raises(BenchctlError, match=r"64 x 96 = 6,144 pixels is above the limit of 6,000"):
        read_image(small)
    monkeypatch.setenv("BENCHCTL_MAX_PIXELS", "6144")
    assert read_image(small).shape == (64, 96)


def test_a_non_finite_float_target_is_refused_and_metrics_are_strict_json(tmp_path: Path, small_profile_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    from benchctl.files import write_json

    image = np.full((48, 80, 3), 0.5, np.float32)
    image[3, 4, 1] = np.nan
    path = tmp_path / "nan.tiff"
    assert cv2.imwrite(str(path), image)
    line = one_error_line(capsys, ["generate", str(path), "-o", str(tmp_path / "g"), "-p", str(small_profile_path)])
    assert line.endswith(f"{path}: 1 NaN or infinite value(s); a target image must be finite")
    assert not (tmp_path / "g" / "metrics.json").exists()
    with pytest.raises(BenchctlError, match="metrics.json: Out of range float values are not JSON compliant"):
        write_json(tmp_path / "metrics.json", {"psnr": float("nan")})
    assert not (tmp_path / "metrics.json").exists()


def test_training_images_one_pixel_high_or_wide_load_flipped(tmp_path: Path) -> None:
    from benchctl.training.data import ImageSource
    from benchctl.training.training import load_targets

    cv2.imwrite(str(tmp_path / "row.png"), np.full((1, 50, 3), 128, np.uint8))
    cv2.imwrite(str(tmp_path / "column.png"), np.full((40, 1, 3), 200, np.uint8))
    sources = [ImageSource(name, path=tmp_path / name) for name in ("row.png", "column.png")]
    for flips in ([(False, True), (True, False)], [(True, True), (True, True)]):
        targets = load_targets(sources, (64, 96), (48, 80), flips)
        assert targets.shape == (2, 3, 64, 96) and bool(targets[:, :, 8:56, 8:88].gt(0).all())


# -- profiles ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("old, new, message", [
    ("pitch_um = 8.0", "pitch_um = 8000.0", "slm.pitch_um: must be <= 1000, got 8000.0"),
    ("wavelength_nm = 520", "wavelength_nm = 0.00000052",
     "laser.channels[1].wavelength_nm: must be >= 100, got 5.2e-07"),
    ("width = 96", "width = 10000000", "slm.height x slm.width: 64 x 10000000 = 640,000,000 pixels is above the limit "
                                       "of 67,108,864 (set $BENCHCTL_MAX_PIXELS to raise it)"),
    ('name = "small"', 'name = "../../x"', "name: '../../x' must be letters, digits, '_', '-' or '.' and start with a "
                                           "letter or digit (it names the profile's calibration folder)"),
])
def test_profile_values_outside_their_range_are_named(tmp_path: Path, small_profile_path: Path, old: str, new: str,
                                                      message: str, capsys: pytest.CaptureFixture[str]) -> None:
    text = small_profile_path.read_text()
    assert old in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(old, new))
    assert one_error_line(capsys, ["profile", "check", str(path)]) == f"benchctl: error: {path}: {message}"


def test_partial_profiles(tmp_path: Path, small_profile_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = small_profile_path.read_text()
    laser_only = tmp_path / "laser_only.toml"
    laser_only.write_text(text[text.index("[laser]"):])
    no_laser = tmp_path / "no_laser.toml"
    no_laser.write_text(text[:text.index("[laser]")])
    assert main(["profile", "check", str(laser_only)]) == 0
    assert "Propagation SLM -> target: not described (needs [slm], [optics] and [laser])" in capsys.readouterr().out
    no_optics = tmp_path / "no_optics.toml"
    no_optics.write_text(text[:text.index("[optics]")] + text[text.index("[slm]"):])
    for profile, section in ((laser_only, "slm"), (no_laser, "laser"), (no_optics, "optics")):
        line = one_error_line(capsys, ["generate", "chart:bars", "-o", str(tmp_path / "g"), "-p", str(profile)])
        assert line == f"benchctl: error: {profile}: this needs a [{section}] section, which the profile lacks"
    assert not (tmp_path / "g").exists()
    line = one_error_line(capsys, ["bench", "speed-vs-error", "-p", str(laser_only), "-o", str(tmp_path / "b")])
    assert line == f"benchctl: error: {laser_only}: this needs a [slm] section, which the profile lacks"


def test_an_endless_file_named_as_profile_procedure_calibration_or_image_is_refused_without_reading_it_all(
        tmp_path: Path, small_profile_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """/dev/zero behind every name a user gives was read until memory ran out: a device is now refused unread, a
    file larger than the cap unread too (calibration files named by a profile are found through their real path: a
    sparse file stands in), and an endless pipe once the cap is read."""
    import threading

    zero = {suffix: tmp_path / f"zero{suffix}" for suffix in (".toml", ".png")}
    for link in zero.values():
        link.symlink_to("/dev/zero")
    for suffix in (".json", ".csv", ".npy"):
        zero[suffix] = tmp_path / f"large{suffix}"
        with open(zero[suffix], "wb") as sparse:
            sparse.truncate(17 * 2**20)
    cap = "read no further ({} files are smaller: is it the file you meant?)"
    text = small_profile_path.read_text()
    with_model = tmp_path / "with_model.toml"
    with_model.write_text(text.replace("[optics]\n", f'[optics]\nmodel = "{zero[".json"]}"\n'))
    for suffix in (".csv", ".npy"):
        with_lut = tmp_path / f"with_lut{suffix}.toml"
        with_lut.write_text(text + f'\n[slm.lut]\ngreen = "{zero[suffix]}"\n')
        line = one_error_line(capsys, ["profile", "check", str(with_lut)])
        assert line == f"benchctl: error: {zero[suffix]}: over 16 MiB, {cap.format('lookup table')}"
    assert one_error_line(capsys, ["profile", "check", str(with_model)]) == (
        f"benchctl: error: {zero['.json']}: over 16 MiB, {cap.format('calibration')}")
    for argv, path, what in (
            (["profile", "check", str(zero[".toml"])], zero[".toml"], "hardware profile"),
            (["run", str(zero[".toml"]), "-p", str(small_profile_path), "--dry-run"], zero[".toml"], "procedure"),
            (["generate", str(zero[".png"]), "-o", str(tmp_path / "g"), "-p", str(small_profile_path)], zero[".png"],
             "image")):
        assert one_error_line(capsys, argv) == f"benchctl: error: {path}: is a device, not a file ({what} expected)"
    pipe = tmp_path / "endless.toml"
    os.mkfifo(pipe)

    def endless() -> None:
        with contextlib.suppress(BrokenPipeError), open(pipe, "wb") as writer:
            while True:
                writer.write(b"# " * 2**15)

    writer = threading.Thread(target=endless, daemon=True)
    writer.start()
    assert one_error_line(capsys, ["profile", "check", str(pipe)]) == (
        f"benchctl: error: {pipe}: over 16 MiB, {cap.format('hardware profile')}")
    writer.join(timeout=10)
    assert not writer.is_alive()


def test_a_run_name_too_long_for_a_folder_and_a_settle_time_of_days_are_named(
        tmp_path: Path, bench_profile_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 300-character procedure name was an OSError traceback (file name too long) once the run started, and
    settle_ms = 1e9 (a unit slip) was accepted: a run would have waited 11 days after every SLM frame."""
    procedure = tmp_path / "p.toml"
    procedure.write_text(f'name = "{"x" * 300}"\nprocedure = "power-sweep"\n')
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert line == f"benchctl: error: {procedure}: name: at most 100 characters, got 300"
    procedure.write_text('procedure = "power-sweep"\n[parameters]\nsettle_ms = 1e9\n')
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert line == f"benchctl: error: {procedure}: parameters.settle_ms: must be <= 60000, got 1000000000.0"
    profile = tmp_path / "slow.toml"
    profile.write_text(bench_profile_path.read_text().replace("settle_ms = 0", "settle_ms = 1e12"))
    line = one_error_line(capsys, ["profile", "check", str(profile)])
    assert line == f"benchctl: error: {profile}: slm.settle_ms: must be <= 60000, got 1000000000000.0"


def test_out_that_cannot_hold_run_folders_is_named_by_the_dry_run(tmp_path: Path, bench_profile_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """`--out` naming a file was accepted by the dry run, and `--out /proc/x` was refused as out of disk space."""
    procedure = tmp_path / "p.toml"
    procedure.write_text('procedure = "power-sweep"\n[parameters]\ncolours = ["green"]\n')
    run = ["run", str(procedure), "-p", str(bench_profile_path)]
    for out, problem in ((procedure, f"{procedure} is a file, not a folder"),
                         (procedure / "runs", f"{procedure} is a file, not a folder"),
                         (Path("/proc/x"), "/proc is on a file system without a disk (such as /proc or /sys)")):
        for dry in (["--dry-run"], []):
            line = one_error_line(capsys, [*run, "--out", str(out), *dry])
            assert line == f"benchctl: error: --out {out}: {problem}: a run folder cannot be created there", line


def test_misspelt_names_get_a_did_you_mean_and_an_empty_sgd_says_so(
        tmp_path: Path, small_profile_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    procedure = tmp_path / "colour.toml"
    procedure.write_text('procedure = "colour-captur"\n')
    assert one_error_line(capsys, ["profile", "check", "simulatd"]).startswith(
        "benchctl: error: hardware profile 'simulatd' not found (did you mean 'simulated'?) (looked for ")
    assert one_error_line(capsys, ["profile", "check", str(tmp_path / "smal.toml")]) == (
        f"benchctl: error: {tmp_path / 'smal.toml'}: hardware profile not found (did you mean "
        f"'{small_profile_path}'?)")
    line = one_error_line(capsys, ["run", str(tmp_path / "colur.toml"), "--dry-run"])
    assert line == f"benchctl: error: {tmp_path / 'colur.toml'}: procedure file not found (did you mean '{procedure}'?)"
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(small_profile_path), "--dry-run"])
    assert line.startswith(f"benchctl: error: {procedure}: procedure: unknown procedure 'colour-captur' (did you mean "
                           "'colour-capture'?) (built-ins: ")
    assert main(["generate", "chart:bars", "--method", "sgd", "--iterations", "0", "--colours", "green", "-o", "g",
                 "-p", str(small_profile_path)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == ("sgd: --iterations 0 runs no iteration: the holograms are "
                                                       "sgd's starting phase alone")


# -- procedures -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("parameters, message", [
    ("repeats = 1000000", "parameters.repeats: must be <= 1000, got 1000000"),
    ('method = "nosuch"', "parameters.method / checkpoint: unknown hologram method 'nosuch'"),
    ('method = "holonet"', "parameters.method / checkpoint: no trained checkpoint for 'holonet' and profile 'bench'"),
    ('method = "holonet-dcm4"\ncheckpoint = "CKPT"', "parameters.method / checkpoint: "),
])
def test_dry_run_refuses_what_the_run_would_fail_on(tmp_path: Path, bench_profile_path: Path, parameters: str,
                                                   message: str, capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "p.toml"
    parameters = parameters.replace("CKPT", str(REPO / "checkpoints" / "simulated" / "holonet-dcm4.pt"))
    procedure.write_text(f'procedure = "colour-capture"\n[parameters]\n{parameters}\n')
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert message in line
    if "holonet-dcm4.pt" in parameters:  # trained for the simulated profile's geometry, not this bench's
        assert "holonet-dcm4.pt" in line and "profile 'bench'" in line, line


def test_a_plan_is_bounded(tmp_path: Path, bench_profile_path: Path) -> None:
    from benchctl.runner.engine import run_procedure

    procedure = tmp_path / "many.py"
    procedure.write_text("from benchctl.runner.api import Parameters, Step\nPARAMETERS = Parameters\n\n\n"
                         "def plan(context):\n"
                         "    return [Step(f's{i}', 'nothing', lambda c: {}) for i in range(100001)]\n")
    with pytest.raises(BenchctlError, match="plans 100,001 steps, above the limit of 100,000"):
        run_procedure(procedure, profile=str(bench_profile_path), dry_run=True, say=lambda _: None)


# -- the simulated bench ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("argv, message", [
    (["sim", "fault", "rgb-laser", "frobnicate"],
     "rgb-laser: unknown fault 'frobnicate' (known: no_reply, garbled, echo, slow, "
                                                  "interlock_open, device_fault, clamp, drop_after=N)"),
    (["sim", "fault", "sim-camera", "unplug"], "simulated camera: unknown fault 'unplug' (known: unplug_at=N)"),
    (["sim", "fault", "no-such-laser", "no_reply"],
     "no simulated device 'no-such-laser' (known: rgb-laser, sim-camera)"),
])
def test_sim_fault_refuses_unknown_faults_and_devices(argv: list[str], message: str, small_profile_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from benchctl.devices.sim.state import list_states

    assert one_error_line(capsys, [*argv, "-p", str(small_profile_path)]) == f"benchctl: error: {message}"
    assert list_states() == {}


# -- device input -----------------------------------------------------------------------------------------------------


class FloodPort:
    """A serial port that answers every command with an endless line (no line ending ever)."""

    in_waiting = 256

    def read(self, size: int = 1) -> bytes:
        return b"A" * size

    def write(self, data: bytes) -> int:
        return len(data)

    def flush(self) -> None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


def test_a_serial_reply_line_is_bounded() -> None:
    from benchctl.devices.errors import DeviceError
    from benchctl.devices.serial_link import MAX_LINE_BYTES, SerialLink

    link = SerialLink("socket://flood:1", timeout_s=3600, port=FloodPort())
    with pytest.raises(DeviceError, match=f"reply to '\\*IDN\\?' is over {MAX_LINE_BYTES} bytes without a"):
        link.query("*IDN?")
    assert len(link._rx) <= MAX_LINE_BYTES + 256


def test_ptp_container_length_is_capped_before_reading() -> None:
    from test_ptp_container import FakeEndpoint

    from benchctl.devices.camera.ptp.transport import MAX_CONTAINER_BYTES, UsbTransport
    from benchctl.devices.errors import DeviceError

    header = struct.pack("<IHHI", 0xFFFFFFF0, 2, 0x1009, 1)
    bulk_in = FakeEndpoint(transfers=[header + b"\0" * 500] + [b"\0" * 512] * 10)
    with pytest.raises(DeviceError, match=f"PTP container of 4,294,967,280 bytes, above the limit of "
                                          f"{MAX_CONTAINER_BYTES:,}"):
        UsbTransport(FakeEndpoint(), bulk_in, usb_vendor=0x04A9).receive()
    assert len(bulk_in.reads) == 1  # nothing read beyond the header's transfer


class EndlessData:
    """A transport whose camera answers a command with data containers and never a response."""

    def __init__(self) -> None:
        self.sent = 0

    def send(self, container: bytes) -> None:
        self.sent += 1

    def receive(self) -> bytes:
        from benchctl.devices.camera.ptp.container import Container, ContainerType

        return Container(ContainerType.DATA, 0x1001, 0, payload=b"x" * 1000).pack()

    def receive_event(self, timeout_s: float) -> bytes | None:
        return None

    def close(self) -> None: ...


def test_ptp_data_containers_per_transaction_are_capped() -> None:
    from benchctl.devices.camera.ptp import session
    from benchctl.devices.errors import DeviceError

    with pytest.raises(DeviceError, match=f"GetDeviceInfo .* sent over {session.MAX_DATA_CONTAINERS} data containers"):
        session.PtpSession(EndlessData()).transact(0x1001)


def test_a_ptp_transaction_has_a_deadline(monkeypatch: pytest.MonkeyPatch) -> None:
    from benchctl.devices.camera.ptp import session
    from benchctl.devices.errors import DeviceError

    clock = itertools.count(0.0, 100.0)  # every look at the clock: 100 s later
    monkeypatch.setattr(session.time, "monotonic", lambda: next(clock))
    with pytest.raises(DeviceError, match=r"GetDeviceInfo \(0x1001\) did not end within 600 s"):
        session.PtpSession(EndlessData()).transact(0x1001)
