"""The laser drivers against the sim:// emulators: same driver code, real byte protocols, injected faults."""

from __future__ import annotations

import time

import msgspec
import pytest

from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout, EmissionNotOff, SafetyError
from benchctl.devices.laser import open_laser
from benchctl.devices.sim.state import load_state, save_state
from benchctl.profiles import LaserChannel, LaserConfig, TemplateProtocol, load_profile

DIALECTS = ("template", "cobolt", "obis", "sapphire", "deepstar")
TELL_INTERLOCK = ("template", "cobolt", "obis", "sapphire")  # a Deepstar has one state (S0) for both: see below
RGB = (("red", 1, 680.0), ("green", 2, 520.0), ("blue", 3, 450.0))
RGB_PROTOCOL = TemplateProtocol(
    set_power="CH{channel}:POW {mw:.2f}", get_power="CH{channel}:POW?", get_measured="CH{channel}:MEAS?",
    enable="CH{channel}:EMIT 1", disable="CH{channel}:EMIT 0", get_emission="CH{channel}:EMIT?",
    get_status="CH{channel}:STAT?", identify="*IDN?",
)


def _channel(name: str, index: int, nm: float, port: str | None = None) -> LaserChannel:
    return LaserChannel(name=name, index=index, wavelength_nm=nm, max_power_mw=40.0, setpoint_mw=1.0, port=port)


def sim_config(dialect: str, options: str = "", *, channels: int = 3, timeout_s: float = 0.2,
               echo: bool = False) -> LaserConfig:
    """The RGB bench on sim://: one template unit on one port, or one cobolt / obis head per channel and port."""
    query = f"&{options}" if options else ""
    chosen = RGB[:channels]
    if dialect == "template":
        return LaserConfig(
            channels=tuple(_channel(name, index, nm) for name, index, nm in chosen),
            driver="template", port=f"sim://rgb-laser?dialect=template{query}", timeout_s=timeout_s,
            protocol=msgspec.structs.replace(RGB_PROTOCOL, echo=echo),
        )
    return LaserConfig(
        channels=tuple(_channel(name, index, nm, port=f"sim://{dialect}-{name}?dialect={dialect}{query}")
                       for name, index, nm in chosen),
        driver=dialect, timeout_s=timeout_s,
    )


def saved_channel(dialect: str, name: str) -> dict:
    """What the simulated unit holds for channel `name` (its saved state; one never changed holds its factory state,
    emission off: a Deepstar answers LF in standby without changing anything)."""
    index = {n: i for n, i, _ in RGB}[name]
    if dialect == "template":
        return load_state("rgb-laser")["channels"][str(index)]
    return load_state(f"{dialect}-{name}").get("channels", {}).get("1", {"setpoint_w": 0.0, "emission": False})


@pytest.mark.parametrize("dialect", DIALECTS)
def test_session(dialect: str) -> None:
    with open_laser(sim_config(dialect)) as laser:
        assert laser.identity()
        assert laser.set_power("red", "20mW") == pytest.approx(0.02, rel=1e-3)  # a Deepstar sets 40 mW / 4095 steps
        laser.set_emission("red", True)
        status = laser.status("red")
        assert status.emission and status.faults == ()
        assert status.interlock_ok is (None if dialect == "deepstar" else True)
        assert status.measured_w == pytest.approx(0.02, rel=1e-2)
        assert laser.measured_w("green") == 0.0 and not laser.emission("green")
        assert saved_channel(dialect, "red")["emission"]
        laser.set_emission("red", False)
        assert laser.measured_w("red") == 0.0
    assert not saved_channel(dialect, "red")["emission"]


def test_the_default_profile_speaks_the_simulators_protocol() -> None:
    laser_config = load_profile("simulated").require("laser").laser
    assert laser_config is not None
    config = msgspec.structs.replace(laser_config, timeout_s=0.5)
    with open_laser(config) as laser:
        assert "simulated RGB laser" in laser.identity()
        assert laser.set_power("green", "5%") == pytest.approx(0.002)
        laser.set_emission("green", True)
        assert laser.status("green").emission


def test_obis_box_of_heads_on_one_port() -> None:
    config = LaserConfig(channels=tuple(_channel(name, index, nm) for name, index, nm in RGB),
                         driver="obis", port="sim://obis-box?dialect=obis&channels=3", timeout_s=0.2)
    with open_laser(config) as laser:
        laser.set_power("blue", "3mW")
        laser.set_emission("blue", True)
        assert [laser.emission(name) for name in laser.channel_names] == [False, False, True]
    assert load_state("obis-box")["channels"]["3"] == {"setpoint_w": pytest.approx(0.003), "emission": False}


@pytest.mark.parametrize("dialect", DIALECTS)
def test_state_persists_between_connections(dialect: str) -> None:
    config = sim_config(dialect)
    with open_laser(config) as laser:
        laser.set_power("green", "5mW")
        laser.set_emission("green", True)
    with open_laser(config) as laser:
        assert laser.setpoint_w("green") == pytest.approx(0.005, rel=1e-3)
        assert not laser.emission("green")


def test_busy_port() -> None:
    config = sim_config("template")
    with open_laser(config):
        with pytest.raises(DeviceBusy, match="sim://rgb-laser"):
            open_laser(config)
    open_laser(config).close()


def test_no_reply_is_a_timeout() -> None:
    started = time.monotonic()
    with pytest.raises(EmissionNotOff, match="no reply to 'CH1:EMIT 0' within 0.2 s; .*: emission state UNKNOWN, "
                                             "possibly ON: use the key switch / interlock") as info:
        open_laser(sim_config("template", "fault=no_reply", channels=1))
    assert isinstance(info.value.__cause__, DeviceTimeout)
    assert time.monotonic() - started < 2.0  # one timeout, not a hang


@pytest.mark.parametrize("dialect", DIALECTS)
def test_garbled_replies_are_device_errors(dialect: str) -> None:
    with pytest.raises(DeviceError, match="garbled") as info:
        open_laser(sim_config(dialect, "fault=garbled", channels=1))
    assert not isinstance(info.value, DeviceTimeout)


def test_echo_handled_when_configured_and_reported_when_not() -> None:
    with open_laser(sim_config("template", "fault=echo", echo=True)) as laser:
        assert laser.set_power("red", "1mW") == pytest.approx(0.001)
    with pytest.raises(DeviceError, match="echo"):
        open_laser(sim_config("template", "fault=echo", channels=1))
    with pytest.raises(DeviceError, match="echo"):
        open_laser(sim_config("cobolt", "fault=echo", channels=1))


def test_slow_replies_within_the_timeout_work_and_beyond_it_time_out() -> None:
    with open_laser(sim_config("template", "fault=slow&reply_delay_s=0.02", channels=1, timeout_s=0.5)) as laser:
        assert laser.set_power("red", "1mW") == pytest.approx(0.001)
    with pytest.raises(EmissionNotOff, match="no reply .*emission state UNKNOWN"):
        open_laser(sim_config("template", "fault=slow&reply_delay_s=0.3", channels=1, timeout_s=0.2))


@pytest.mark.parametrize("dialect", TELL_INTERLOCK)
def test_interlock_open_refuses_emission(dialect: str) -> None:
    with open_laser(sim_config(dialect, "fault=interlock_open")) as laser:
        assert laser.status("red").interlock_ok is False
        with pytest.raises(SafetyError, match="interlock open"):
            laser.set_emission("red", True)
        assert not laser.emission("red")
    assert not saved_channel(dialect, "red")["emission"]


def test_fault_set_in_the_saved_state_applies_on_next_connection() -> None:
    save_state("rgb-laser", {"faults": ["interlock_open"]})  # what `benchctl sim fault` does
    with open_laser(sim_config("template")) as laser:
        with pytest.raises(SafetyError, match="interlock"):
            laser.set_emission("green", True)


@pytest.mark.parametrize("fault", ["interlock_open", "device_fault"])
def test_a_deepstar_in_state_s0_refuses_emission(fault: str) -> None:
    """The head's S0 is "error or interlock" alike: reported as a fault, emission refused before LON is sent."""
    with open_laser(sim_config("deepstar", f"fault={fault}")) as laser:
        status = laser.status("red")
        assert (status.interlock_ok, status.faults) == (None, ("error or interlock open (state S0)",))
        with pytest.raises(SafetyError, match=r"fault active \(error or interlock open \(state S0\)\)"):
            laser.set_emission("red", True)
        assert not laser.emission("red")


@pytest.mark.parametrize("dialect", TELL_INTERLOCK)
def test_device_fault_is_reported_and_blocks_emission(dialect: str) -> None:
    with open_laser(sim_config(dialect, "fault=device_fault")) as laser:
        faults = laser.status("red").faults
        assert len(faults) == 1 and "temperature" in faults[0].lower()
        with pytest.raises(SafetyError, match="fault active"):
            laser.set_emission("red", True)
        assert not laser.emission("red")


@pytest.mark.parametrize("dialect", DIALECTS)
def test_clamped_setpoint_is_detected_by_readback(dialect: str) -> None:
    with open_laser(sim_config(dialect, "fault=clamp&max_mw=40")) as laser:
        assert laser.set_power("red", "10mW") == pytest.approx(0.01, rel=1e-3)
        with pytest.raises(DeviceError, match=r"asked for 30 mW, the device holds 20(\.00\d+)? mW"):
            laser.set_power("red", "30mW")


def test_cable_pulled_mid_session_says_emission_is_unknown() -> None:
    # open: 3 x (EMIT 0, EMIT?) = 6 commands; set_power: 2; set_emission: STAT?, EMIT 1, EMIT? -> 11
    with pytest.raises(EmissionNotOff, match="emission state UNKNOWN, possibly ON: use the key switch / interlock"):
        with open_laser(sim_config("template", "fault=drop_after=11")) as laser:
            laser.set_power("red", "20mW")
            laser.set_emission("red", True)
            assert saved_channel("template", "red")["emission"]
            laser.status("red")  # the 12th command: its reply is lost
    assert not any(saved_channel("template", name)["emission"] for name, _, _ in RGB)
