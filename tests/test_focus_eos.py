"""The eos focus driver: DriveLens (0x9155) in the PTP EOS layer, exact container bytes, and the simulated body's lens
with its hidden backlash, step-size spread and end stops (answered OK even when a drive was ignored)."""

from __future__ import annotations

import struct
from collections.abc import Callable

import msgspec
import pytest

from benchctl.devices.camera.ptp.container import Container, ContainerType, OperationCode, ResponseCode
from benchctl.devices.camera.ptp.eos import EosProperty, drive_lens_code, parse_drive_lens
from benchctl.devices.camera.ptp_camera import EosTiming, PtpCamera
from benchctl.devices.errors import DeviceError
from benchctl.devices.focus import focus_for
from benchctl.devices.focus.eos import EosFocus
from benchctl.devices.lock import DeviceHeld
from benchctl.devices.sim.eos_usb import DRIVE_STEPS, SimEosTransport
from benchctl.devices.sim.focus_mechanics import Mechanism
from benchctl.errors import BadValueError
from benchctl.profiles import CameraConfig, FocusConfig, Profile, SimFocusConfig, load_profile
from benchctl.runner.instruments import Instruments

FAST = EosTiming(settle_s=0.0, release_events_s=0.05, poll_interval_s=0.001, busy_retry_s=0.05)
LENS = SimFocusConfig(plane_mm=70.0, mm_per_step=0.01, range_steps=400, start_steps=200, backlash_steps=6.0)


def no_image() -> tuple[bytes, str]:
    raise AssertionError("no capture in these tests")


def lens_focus(lens: Mechanism, **changes: object) -> tuple[EosFocus, SimEosTransport]:
    sim = SimEosTransport(no_image, lens=lens)
    camera = PtpCamera(CameraConfig(driver="ptp"), sim, FAST)
    config = msgspec.structs.replace(FocusConfig(driver="eos", settle_ms=0), **changes)  # type: ignore[arg-type]
    return EosFocus(config, camera, owns_camera=True), sim


@pytest.mark.parametrize("far, size, code", [(False, 1, 0x0001), (False, 3, 0x0003), (True, 1, 0x8001),
                                             (True, 2, 0x8002)])
def test_drive_lens_codes_and_container_bytes(far: bool, size: int, code: int) -> None:
    assert drive_lens_code(far, size) == code and parse_drive_lens(code) == (far, size)
    command = Container(ContainerType.COMMAND, OperationCode.EosDriveLens, 7, (code,)).pack()
    assert command == struct.pack("<IHHII", 16, 1, 0x9155, 7, code)


def test_invalid_drive_sizes() -> None:
    with pytest.raises(BadValueError, match="1, 2 or 3"):
        drive_lens_code(True, 4)
    assert parse_drive_lens(0x0004) is None and parse_drive_lens(0x18001) is None


def test_drives_start_the_live_view_and_move_the_lens_by_counted_steps() -> None:
    lens = Mechanism(LENS)
    focus, sim = lens_focus(lens, drive_size=2, home_drives=10)
    with focus:
        focus.home()  # 10 x Near 3 (48 steps each): into the near end stop from 200
        assert lens.true_steps == 0.0 and focus.position == 0
        drives = [c.params for c in sim.commands if c.code == OperationCode.EosDriveLens]
        assert drives == [(0x0003,)] * 10
        assert (EosProperty.EVFOutputDevice, (2,)) in sim.property_writes  # live view before the first drive
        focus.move(5)  # 5 x Far 2: 40 steps, the first 6 take up the play
        assert lens.true_steps == 5 * DRIVE_STEPS[2] - 6 and focus.position == 5
        focus.move(-1)  # 8 steps back: 6 into the play, 2 of motion
        assert lens.true_steps == 5 * DRIVE_STEPS[2] - 6 - 2 and focus.direction == -1


def test_drives_outside_live_view_and_into_an_end_stop_are_answered_ok_and_ignored() -> None:
    lens = Mechanism(LENS)
    sim = SimEosTransport(no_image, lens=lens)
    camera = PtpCamera(CameraConfig(driver="ptp"), sim, FAST).open()
    try:
        assert camera._session is not None
        eos_response = camera._session.transact(OperationCode.EosDriveLens, 0x8003)  # EVF output 8: not live
        assert eos_response.code == ResponseCode.OK and lens.true_steps == 200.0
        for _ in range(20):  # 20 x 48 steps Far from 200: the far end stop at 400 stops it
            camera.drive_lens(True, 3)
        assert lens.true_steps == 400.0 and sim.lens_drives == 5
        bad = camera._session.transact(OperationCode.EosDriveLens, 0x0007)
        assert bad.code == ResponseCode.InvalidParameter
    finally:
        camera.close()


def test_step_size_spread_makes_counted_positions_drift() -> None:
    lens = Mechanism(msgspec.structs.replace(LENS, step_spread=0.2, backlash_steps=0.0, range_steps=10**6,
                                             start_steps=1000))
    focus, _ = lens_focus(lens, home_drives=30)
    with focus:
        focus.home()
        for _ in range(10):
            focus.move(30)
        assert focus.position == 300 and lens.true_steps != 300.0  # counted is not true
        assert abs(lens.true_steps - 300) < 5 * 0.2 * 300**0.5 + 1


def test_a_body_without_drive_lens_is_refused_in_one_line() -> None:
    sim = SimEosTransport(no_image)  # no lens: the operation is not offered
    focus = EosFocus(FocusConfig(driver="eos", settle_ms=0), PtpCamera(CameraConfig(driver="ptp"), sim, FAST), True)
    with focus, pytest.raises(DeviceError, match="does not offer DriveLens"):
        focus.move(1)


def test_the_simulated_eos_profile_drives_the_benchs_lens_and_holds_the_camera() -> None:
    profile = load_profile("simulated-eos")
    focus = focus_for(profile)
    assert isinstance(focus, EosFocus)
    with focus:
        focus.home()
        focus.move(20)
        with pytest.raises(DeviceHeld, match="camera"):  # the lens is driven through the camera it holds
            PtpCamera.for_profile(profile).open()
    assert Mechanism(profile.sim.focus).true_steps > 0


def test_a_run_drives_the_lens_through_its_own_camera(make_bench_profile: Callable[..., Profile]) -> None:
    profile = make_bench_profile(camera={"driver": "ptp", "transport": "sim"},
                                 focus={"driver": "eos", "settle_ms": 0, "home_drives": 10},
                                 sim={"focus": {"mm_per_step": 0.005, "range_steps": 400, "start_steps": 200,
                                                "backlash_steps": 0.0}})
    with Instruments(profile, say=lambda line: None) as instruments:
        focus = instruments.focus
        assert isinstance(focus, EosFocus) and focus.camera is instruments.camera
        focus.home()
        focus.move(7)
        assert Mechanism().true_steps == 7.0 and focus.ground_truth() == {"true_steps": 7.0, "backlash_steps": 0.0}
        assert instruments.identities["focus"]["driver"] == "eos"
    assert not focus.is_open and not focus.camera.is_open
