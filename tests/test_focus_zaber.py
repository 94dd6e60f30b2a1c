"""The zaber focus driver: exact bytes of Zaber's ASCII protocol (expected-protocol script), then against the sim://
stage emulator with its hidden mechanics (backlash) and injected faults."""

from __future__ import annotations

from pathlib import Path

import pytest
from expected_protocol import ExpectedProtocol, Stalls

from benchctl.devices.errors import DeviceError, DeviceTimeout
from benchctl.devices.focus import open_focus
from benchctl.devices.focus.zaber import ZaberFocus, parse_reply
from benchctl.devices.lock import DeviceHeld
from benchctl.devices.serial_link import SerialLink
from benchctl.devices.sim.focus_mechanics import FOCUS_STATE, Mechanism, bind
from benchctl.devices.sim.state import load_state, save_state
from benchctl.devices.sim.zaber_stage import ZaberStage
from benchctl.errors import BenchctlError
from benchctl.profiles import FocusConfig, ProfileFile, SimFocusConfig, _checked, load_profile
from benchctl.schema import decode

OPEN = [(b"/1 1\r\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 0 get system.serial\r\n", b"@01 0 OK IDLE -- 4242\r\n"),
        (b"/1 0 get version\r\n", b"@01 0 OK IDLE -- 7.38\r\n"),
        (b"/1 1 get limit.max\r\n", b"@01 1 OK IDLE -- 84000\r\n")]


def scripted(pairs: list[tuple[bytes, bytes | None]], **config: object) -> tuple[ZaberFocus, ExpectedProtocol]:
    port = ExpectedProtocol(pairs)
    focus_config = FocusConfig(driver="zaber", port="script://stage", settle_ms=0, timeout_s=0.05, **config)
    return ZaberFocus(focus_config, SerialLink("script://stage", port=port, timeout_s=0.05, name="focus stage")), port


def test_reply_fields() -> None:
    reply = parse_reply("@01 1 OK BUSY WR 1234")
    assert reply is not None and (reply.device, reply.axis, reply.flag, reply.status, reply.warning, reply.data) == (
        1, 1, "OK", "BUSY", "WR", "1234")
    assert parse_reply("OK") is None and parse_reply("@x 1 OK IDLE -- 0") is None


def test_open_move_and_home_send_exactly_these_bytes() -> None:
    focus, port = scripted([
        *OPEN, (b"/1 1 get pos\r\n", b"@01 1 OK IDLE -- 5000\r\n"),
        (b"/1 1 move rel -250\r\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\r\n", b"@01 1 OK BUSY -- 0\r\n"), (b"/1 1\r\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\r\n", b"@01 1 OK IDLE -- 4750\r\n"),
        (b"/1 1 home\r\n", b"@01 1 OK BUSY -- 0\r\n"), (b"/1 1\r\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\r\n", b"@01 1 OK IDLE -- 0\r\n"),
    ])
    with port, focus:
        assert focus.position == 5000  # homed before: the controller's counter is the position
        move = focus.move(-250)
        assert (move.requested, move.position, move.reported, focus.direction) == (-250, 4750, 4750, -1)
        assert focus.home().position == 0
        assert focus.identity()["serial"] == "4242" and focus.identity()["travel"] == "4.0005 mm"
    assert not port.failures


def test_an_unreferenced_stage_is_not_moved_until_homed() -> None:
    pairs = [(b"/1 1\r\n", b"@01 1 OK IDLE WR 0\r\n"), *OPEN[1:]]
    focus, port = scripted(pairs)
    with port, focus:
        assert focus.position is None
        with pytest.raises(DeviceError, match="no reference position.*home it first"):
            focus.move(10)


@pytest.mark.parametrize("reply, message", [
    (b"@01 1 RJ IDLE -- BADDATA\r\n", "refused \\(BADDATA: beyond the stage's travel"),
    (b"@02 1 OK IDLE -- 0\r\n", "unexpected reply"),
    (b"@01 1 OK BUSY FS 0\r\n", None),
])
def test_refusals_and_stalls_are_one_line_errors(reply: bytes, message: str | None) -> None:
    pairs = [*OPEN, (b"/1 1 get pos\r\n", b"@01 1 OK IDLE -- 0\r\n"), (b"/1 1 move rel 100\r\n", reply)]
    if message is None:  # accepted, then the carriage stalls
        pairs.append((b"/1 1\r\n", b"@01 1 OK IDLE FS 0\r\n"))
        message = "warning FS: the carriage stalled.*free it, then `benchctl focus home`"
    focus, port = scripted(pairs)
    with port, focus, pytest.raises(DeviceError, match=message) as caught:
        focus.move(100)
    assert "\n" not in str(caught.value)


def test_a_silent_stage_is_a_timeout() -> None:
    focus, port = scripted([(b"/1 1\r\n", Stalls(b""))])
    with port, pytest.raises(DeviceTimeout, match="focus stage .* no reply to '/1 1'"):
        focus.open()
    assert not focus.is_open


# -- against the simulated stage -------------------------------------------------------------------------------------

def sim_config(options: str = "", **changes: object) -> FocusConfig:
    return FocusConfig(driver="zaber", port=f"sim://focus-stage?dialect=zaber{options}", settle_ms=0,
                       timeout_s=0.2, **changes)


def test_simulated_stage_moves_the_camera_with_its_backlash() -> None:
    hidden = SimFocusConfig(backlash_steps=300.0, start_steps=1000.0)
    bind(hidden)
    with ZaberFocus(sim_config()) as focus:
        assert focus.position is None  # power-on: no reference
        focus.home()
        assert Mechanism(hidden).true_steps == 0.0
        focus.move(2000)  # the first 300 take up the play
        assert Mechanism(hidden).true_steps == 1700.0 and focus.position == 2000
        focus.move(-100)  # all lost in the play
        assert Mechanism(hidden).true_steps == 1700.0
        focus.move_to(1000, approach=1, overshoot=600)  # coming back down: past it first, then up
        assert focus.position == 1000 and Mechanism(hidden).true_steps == 700.0
        focus.move_to(1500, approach=1, overshoot=600)  # already moving up: straight there
        assert Mechanism(hidden).true_steps == 1200.0
        with pytest.raises(DeviceError, match="BADDATA"):
            focus.move(10**6)
    with ZaberFocus(sim_config()) as focus:  # the controller keeps its counter between connections
        assert focus.position == 1500


def test_the_profile_binds_the_hidden_mechanics_and_the_stage_keeps_its_state() -> None:
    profile = load_profile("simulated")
    with open_focus(profile) as focus:
        focus.home()
        focus.move(4200)
    saved = load_state(FOCUS_STATE)
    assert saved["config"]["backlash_steps"] == profile.sim.focus.backlash_steps == 630
    assert saved["true_steps"] == 4200 - 630
    assert load_state("focus-stage")["position"] == 4200


def test_a_held_stage_names_its_holder() -> None:
    with ZaberFocus(sim_config()), pytest.raises(DeviceHeld, match="focus stage .* busy: held by"):
        ZaberFocus(sim_config()).open()


@pytest.mark.parametrize("fault, error", [("no_reply", DeviceTimeout), ("garbled", DeviceError)])
def test_faults_of_the_line(fault: str, error: type[Exception]) -> None:
    with pytest.raises(error, match="focus stage"):
        ZaberFocus(sim_config(f"&fault={fault}")).open()


def test_stall_fault_set_from_the_saved_state() -> None:
    with ZaberFocus(sim_config()) as focus:
        focus.home()
    save_state("focus-stage", {**load_state("focus-stage"), "faults": ["stall"]})
    with ZaberFocus(sim_config()) as focus, pytest.raises(DeviceError, match="warning FS"):
        focus.move(1000)


def test_cut_line_after_n_commands_is_a_timeout() -> None:
    with ZaberFocus(sim_config("&fault=drop_after=6")) as focus, pytest.raises(DeviceTimeout):
        focus.home()
        focus.move(10)


def test_slow_moves_are_waited_for() -> None:
    with ZaberFocus(sim_config("&speed=20000")) as focus:
        focus.home()
        assert focus.move(2000).reported == 2000  # 0.1 s of BUSY polled through


def test_profile_checks_for_focus() -> None:
    with pytest.raises(BenchctlError, match="focus.port.*needs a serial port"):
        _checked(Path("p.toml"), decode({"focus": {"driver": "zaber"}}, ProfileFile, Path("p.toml")))
    with pytest.raises(BenchctlError, match="focus.driver.*needs \\[camera\\] driver = \"ptp\""):
        _checked(Path("p.toml"), decode({"focus": {"driver": "eos"}}, ProfileFile, Path("p.toml")))
    with pytest.raises(BenchctlError, match="focus.driver"):
        decode({"focus": {"driver": "arduino"}}, ProfileFile, Path("p.toml"))


def test_the_emulator_answers_exact_bytes() -> None:
    bind(SimFocusConfig(backlash_steps=0.0, start_steps=100.0))
    stage = ZaberStage("focus-stage", {"speed": "1e9"})
    assert stage.receive(b"/1 1\r\n") == b"@01 1 OK IDLE WR 0\r\n"  # power-on: no reference
    assert stage.receive(b"/1 1 home\n") == b"@01 1 OK IDLE -- 0\r\n"  # LF alone ends a command too
    assert stage.receive(b"/1 1 move abs 2500\r\n/1 1 get pos\r\n") == (b"@01 1 OK IDLE -- 0\r\n"
                                                                          b"@01 1 OK IDLE -- 2500\r\n")
    assert stage.receive(b"/1 1 move rel 999999\r\n") == b"@01 1 RJ IDLE -- BADDATA\r\n"
    assert stage.receive(b"/1 1 jump\r\n") == b"@01 1 RJ IDLE -- BADCOMMAND\r\n"
    assert stage.receive(b"/1 0 get system.serial\r\n") == b"@01 0 OK IDLE -- 4242\r\n"
    assert stage.receive(b"/2 1 get pos\r\n") == b""  # another device's message: nobody else on the chain
    assert stage.receive(b"/1 1 get p") == b"" and stage.receive(b"os\r\n") == b"@01 1 OK IDLE -- 2500\r\n"
    assert Mechanism().true_steps == 2500.0


def test_an_approach_past_home_or_the_travels_end_stops_there() -> None:
    bind(SimFocusConfig(backlash_steps=10.0, range_steps=1000, start_steps=500.0))
    with ZaberFocus(sim_config()) as focus:
        focus.home()  # approached from above
        assert focus.move_to(0, approach=1, overshoot=50).position == 0  # cannot go below home to come up: stays
        focus.move_to(990, approach=1, overshoot=50)
        assert focus.move_to(990, approach=-1, overshoot=50).position == 990  # up to the end (1000), then down
        assert Mechanism().true_steps == 990.0 and focus.direction == -1
