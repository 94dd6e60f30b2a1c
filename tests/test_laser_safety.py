"""Laser safety rules: off at connect, limits refused before any byte, off on every way out; parsers never lie."""

from __future__ import annotations

import math
import signal
import threading
import time
from collections.abc import Iterator

import pytest
from expected_protocol import ExpectedProtocol
from hypothesis import given, settings
from hypothesis import strategies as st
from test_laser_protocols import TEMPLATE_CONNECT, TEMPLATE_OFF, ok, per_head_config, template_config
from test_laser_sim import DIALECTS, RGB, saved_channel, sim_config

from benchctl.devices.errors import DeviceError, DeviceTimeout, EmissionNotOff, SafetyError
from benchctl.devices.laser import CoboltLaser, Laser, ObisLaser, TemplateLaser, open_laser
from benchctl.devices.safety import TERMINATION_SIGNALS, TerminatedBySignal, signals_interrupt, wait
from benchctl.devices.sim.state import save_state
from benchctl.errors import BadValueError, BenchctlError

Pairs = list[tuple[bytes, bytes | None]]


def template_on(script: Pairs, **options: object) -> tuple[TemplateLaser, ExpectedProtocol]:
    port = ExpectedProtocol(script)
    return TemplateLaser(template_config(), port_factory=lambda url: port, **options), port  # type: ignore[arg-type]


def leave_emitting(dialect: str) -> None:
    """Saved state as if an earlier program had left every channel emitting at 10 mW (a Deepstar at the step of its
    40 mW / 0xFFF nearest to it, 10.0024 mW)."""
    on = {"setpoint_w": round(0.01 / 0.04 * 0xFFF) / 0xFFF * 0.04 if dialect == "deepstar" else 0.01, "emission": True}
    if dialect == "template":
        save_state("rgb-laser", {"channels": {str(index): on for _, index, _ in RGB}})
    for name, _, _ in RGB if dialect != "template" else ():
        save_state(f"{dialect}-{name}", {"channels": {"1": on}})


@pytest.mark.parametrize("dialect", DIALECTS)
def test_connecting_turns_emission_off_on_every_channel(dialect: str) -> None:
    leave_emitting(dialect)
    assert all(saved_channel(dialect, name)["emission"] for name, _, _ in RGB)
    with open_laser(sim_config(dialect)) as laser:
        assert not any(saved_channel(dialect, name)["emission"] for name, _, _ in RGB)
        assert not any(laser.emission(name) for name in laser.channel_names)
        assert laser.setpoint_w("red") == pytest.approx(0.01, rel=1e-3)  # setpoints are kept


@pytest.mark.parametrize("power", ["41mW", "0.05W", "101%", 0.0401, 1, "1e9 W"])
def test_power_above_the_limit_is_refused_before_any_byte(power: str | float) -> None:
    laser, port = template_on(TEMPLATE_CONNECT + TEMPLATE_OFF)
    with laser:
        with pytest.raises(SafetyError, match="above the profile's limit 40 mW.*nothing was sent"):
            laser.set_power("red", power)
    port.check()  # the script held no exchange for the refused setting


def test_power_above_the_limit_is_refused_even_before_connecting() -> None:
    laser = TemplateLaser(template_config(), port_factory=lambda url: pytest.fail("no port may be opened"))
    with pytest.raises(SafetyError):
        laser.set_power("green", "50mW")


@settings(max_examples=100, deadline=None)
@given(st.floats(min_value=1.0001, max_value=1e6), st.sampled_from(["mW", "%", "W", "float"]))
def test_any_power_above_the_limit_is_refused(factor: float, unit: str) -> None:
    forms: dict[str, str | float] = {"mW": f"{40 * factor!r}mW", "%": f"{100 * factor!r}%",
                                     "W": f"{0.04 * factor!r}W", "float": 0.04 * factor}
    power = forms[unit]
    laser = TemplateLaser(template_config(), observe=True, port_factory=lambda url: ExpectedProtocol([]))
    with laser, pytest.raises(SafetyError):
        laser.set_power("red", power)


@pytest.mark.parametrize("power", [-0.001, math.nan, math.inf, "-1mW", "20"])
def test_nonsense_power_is_a_bad_value(power: str | float) -> None:
    laser = TemplateLaser(template_config())
    with pytest.raises(BadValueError):
        laser.set_power("red", power)


def test_unknown_channel_lists_the_channels() -> None:
    with pytest.raises(BenchctlError, match="no laser channel 'purple'; known channels: red, green"):
        TemplateLaser(template_config()).set_power("purple", "1mW")


@pytest.mark.parametrize("dialect", DIALECTS)
@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_emission_off_after_an_exception_inside_with(dialect: str, error: type[BaseException]) -> None:
    with pytest.raises(error):
        with open_laser(sim_config(dialect)) as laser:
            laser.set_emission("red", True)
            laser.set_emission("blue", True)
            laser.leave_on = True  # even then: an exception turns emission off
            raise error("boom")
    assert not any(saved_channel(dialect, name)["emission"] for name, _, _ in RGB)


def test_leave_on_keeps_emission_after_a_plain_close_and_observe_sees_it() -> None:
    with open_laser(sim_config("template"), leave_on=True) as laser:
        laser.set_emission("green", True)
    assert saved_channel("template", "green")["emission"]
    with open_laser(sim_config("template"), observe=True) as laser:
        assert laser.status("green").emission
        with pytest.raises(DeviceError, match="observe"):
            laser.set_power("green", "1mW")
        with pytest.raises(DeviceError, match="observe"):
            laser.set_emission("red", True)
    assert saved_channel("template", "green")["emission"]
    with open_laser(sim_config("template")):
        pass
    assert not saved_channel("template", "green")["emission"]


def test_close_tries_every_channel_then_raises_the_first_error() -> None:
    script = TEMPLATE_CONNECT + [ok("CH1:EMIT 0", "ERR 7 BUSY"), ok("CH2:EMIT 0"), ok("CH2:EMIT?", "0")]
    laser, port = template_on(script)
    laser.open()
    with pytest.raises(DeviceError, match="ERR 7 BUSY"):
        laser.close()
    port.check()
    assert port.closed and not laser.is_open


def test_lost_reply_after_enabling_switches_the_channel_off_again() -> None:
    script = TEMPLATE_CONNECT + [
        ok("CH1:STAT?"), ok("CH1:EMIT 1"), (b"CH1:EMIT?\r\n", None),  # the read-back is lost
        ok("CH1:EMIT 0"), ok("CH1:EMIT?", "0"),  # switched off before the error is raised
    ] + TEMPLATE_OFF
    laser, port = template_on(script)
    with pytest.raises(DeviceTimeout, match="CH1:EMIT\\?"):
        with laser:
            laser.set_emission("red", True)
    port.check()


def test_emission_still_on_after_off_is_an_error() -> None:
    laser, port = template_on([ok("CH1:EMIT?", "0"), ok("CH1:EMIT 0"), ok("CH1:EMIT?", "1"), ok("CH2:EMIT?", "0"),
                               ok("CH2:EMIT 0"), ok("CH2:EMIT?", "0")])
    with pytest.raises(EmissionNotOff, match="'red'.*emission still ON after the off command: use the key switch / "
                                             "interlock"):
        laser.open()
    port.check()
    assert port.closed


def test_observe_mode_sends_nothing_at_connect_or_close() -> None:
    laser, port = template_on([], observe=True)
    with laser:
        assert laser.is_open
    port.check()


# -- reply parsers (hypothesis): a value the driver returns is what the device said, anything else a DeviceError

_REPLY = st.one_of(
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=12),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["1", "0", "ON", "OFF", "on", " 1", "0x10", "1e3", "OK", "ERR 1 X"]),
)


def observed(cls: type[Laser], script: Pairs, config_of: str = "template") -> Laser:
    """`cls` connected in observe mode (nothing sent at connect) to a port replaying `script`."""
    config = template_config() if config_of == "template" else per_head_config(config_of)
    port = ExpectedProtocol(script)
    return cls(config, observe=True, port_factory=lambda url: port).open()


@settings(max_examples=150, deadline=None)
@given(_REPLY)
def test_power_replies_parse_or_raise(reply: str) -> None:
    laser = observed(TemplateLaser, [ok("CH1:POW?", reply)])
    try:
        watts = laser.setpoint_w("red")
    except DeviceError as exc:
        assert "\n" not in str(exc)
        if not reply.startswith("ERR"):
            assert "expected a number" in str(exc)
    else:
        assert watts == float(reply) / 1e3 and math.isfinite(watts)


@settings(max_examples=150, deadline=None)
@given(_REPLY)
def test_emission_replies_parse_or_raise(reply: str) -> None:
    laser = observed(TemplateLaser, [ok("CH1:EMIT?", reply)])
    try:
        on = laser.emission("red")
    except DeviceError:
        assert reply.strip().upper() not in ("1", "0", "ON", "OFF")
    else:
        assert on == (reply.strip().upper() in ("1", "ON"))


@settings(max_examples=150, deadline=None)
@given(st.integers(min_value=0, max_value=2**32 - 1), st.booleans(), st.booleans())
def test_obis_fault_codes_list_one_fault_per_bit(code: int, as_hex: bool, lock_on: bool) -> None:
    script = [ok("SYSTem:LOCK?", f"{'ON' if lock_on else 'OFF'}\r\nOK"),
              ok("SYSTem:FAULt?", f"{f'0x{code:08X}' if as_hex else code}\r\nOK"),
              ok("SOURce:POWer:LEVel:IMMediate:AMPLitude?", "0.001\r\nOK"), ok("SOURce:POWer:LEVel?", "0\r\nOK"),
              ok("SOURce:AM:STATe?", "OFF\r\nOK")]
    status = observed(ObisLaser, script, "obis").status("red")
    assert status.interlock_ok is lock_on and len(status.faults) == bin(code).count("1")


@settings(max_examples=60, deadline=None)
@given(st.integers(min_value=0, max_value=9), st.sampled_from(["0", "1"]))
def test_cobolt_fault_codes(code: int, ilk: str) -> None:
    script = [ok("ilk?", ilk), ok("f?", str(code)), ok("p?", "0.001"), ok("pa?", "0"), ok("l?", "0")]
    status = observed(CoboltLaser, script, "cobolt").status("red")
    assert status.interlock_ok is (ilk == "0" and code != 3)
    assert len(status.faults) == (0 if code in (0, 3) else 1)
    assert all(fault.endswith(f"(f? = {code})") for fault in status.faults)


@pytest.mark.parametrize("dialect", DIALECTS)
def test_a_channel_found_emitting_at_connect_is_reported(dialect: str) -> None:
    leave_emitting(dialect)
    with open_laser(sim_config(dialect)) as laser:
        power = "10.0024 mW" if dialect == "deepstar" else "10 mW"
        assert laser.connect_report() == [f"{name} was emitting at {power}; switched off" for name, _, _ in RGB]
    with open_laser(sim_config(dialect)) as laser:
        assert laser.connect_report() == []


def test_every_laser_command_and_a_run_say_what_was_found_emitting(tmp_path, small_profile_path, bench_profile_path,
                                                                   capsys) -> None:
    import json

    from benchctl.cli import main

    def green_left_on() -> None:
        save_state("rgb-laser", {"channels": {str(index): {"setpoint_w": 0.002, "emission": name == "green"}
                                              for name, index, _ in RGB}})

    for argv in (["laser", "off"], ["laser", "set", "red", "1mW"], ["laser", "on", "red", "--for", "0s"]):
        green_left_on()
        assert main([*argv, "-p", str(small_profile_path)]) == 0
        assert "green was emitting at 2 mW; switched off" in capsys.readouterr().out.splitlines()
    green_left_on()
    procedure = tmp_path / "p.toml"
    procedure.write_text('procedure = "power-sweep"\n[parameters]\ncolours = ["green"]\nlevels = ["1mW", "2mW"]\n')
    assert main(["run", str(procedure), "-p", str(bench_profile_path), "-o", str(tmp_path / "runs")]) == 0
    assert "laser: green was emitting at 2 mW; switched off" in capsys.readouterr().out.splitlines()
    (folder,) = (tmp_path / "runs").iterdir()
    devices = json.loads((folder / "devices.json").read_text())
    assert devices["laser_found_emitting"] == ["green was emitting at 2 mW; switched off"]


def signal_from_another_thread(signum: int, after_s: float) -> threading.Thread:
    """A thread that, after `after_s`, receives `signum` itself: the C-level handler runs there, as when the
    kernel hands a process-wide SIGTERM to one of torch's worker threads instead of the main thread."""
    def deliver() -> None:
        time.sleep(after_s)
        signal.pthread_kill(threading.get_ident(), signum)

    thread = threading.Thread(target=deliver, daemon=True)
    thread.start()
    return thread


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_termination_signal_on_another_thread_ends_a_device_wait(signum: int) -> None:
    # time.sleep(60) would run its full minute here: the main thread is never woken by the signal itself
    start = time.monotonic()
    with pytest.raises(TerminatedBySignal) as raised, signals_interrupt():
        signal_from_another_thread(signum, after_s=0.2).join(timeout=0)
        wait(60)
    assert raised.value.signum == signum and time.monotonic() - start < 30


@pytest.fixture
def ctrl_c_raises() -> Iterator[None]:
    """Python's own SIGINT handler, which a shell's background job (SIGINT ignored) would not have installed."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("signum, raised", [(signal.SIGTERM, TerminatedBySignal), (signal.SIGHUP, TerminatedBySignal),
                                             (signal.SIGINT, KeyboardInterrupt)])
def test_a_signal_whose_exception_was_swallowed_still_ends_the_next_wait(signum: int, raised: type[BaseException],
                                                                        ctrl_c_raises: None) -> None:
    """C code that calls Python code may discard the handler's exception (a SIGTERM in an import's ABC
    registration did, in a capture's render); the next device wait must not then sleep its 30 s out."""
    with pytest.raises(raised) as caught, signals_interrupt():
        try:
            signal.raise_signal(signum)
        except KeyboardInterrupt:
            pass  # what the C code did
        wait(60)
    assert getattr(caught.value, "signum", signal.SIGINT) == signum


def test_a_wait_outlasts_signals_whose_handler_returns() -> None:
    seen: list[int] = []
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: seen.append(signum))
    try:
        with signals_interrupt():
            signal_from_another_thread(signal.SIGUSR1, after_s=0.05)
            start = time.monotonic()
            wait(0.5)
            waited = time.monotonic() - start
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert seen == [signal.SIGUSR1] and waited >= 0.5


def test_signal_handlers_and_the_wakeup_descriptor_are_restored() -> None:
    before = {sig: signal.getsignal(sig) for sig in TERMINATION_SIGNALS}
    with signals_interrupt():
        assert all(signal.getsignal(sig) is not before[sig] for sig in TERMINATION_SIGNALS)
    assert {sig: signal.getsignal(sig) for sig in TERMINATION_SIGNALS} == before
    assert signal.set_wakeup_fd(-1) == -1  # nothing left installed
