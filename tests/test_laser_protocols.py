"""The exact bytes each laser dialect sends and expects (expected-protocol ports, no simulator in between)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import msgspec
import pytest
from expected_protocol import ExpectedProtocol, Stalls

from benchctl.devices.errors import DeviceError, SafetyError
from benchctl.devices.laser import CoboltLaser, Laser, ObisLaser, TemplateLaser, open_laser
from benchctl.devices.laser.deepstar import DeepstarLaser
from benchctl.devices.laser.sapphire import SapphireLaser
from benchctl.errors import BenchctlError
from benchctl.profiles import LaserChannel, LaserConfig, TemplateProtocol

Pairs = list[tuple[bytes, bytes | None]]

RGB_PROTOCOL = TemplateProtocol(
    set_power="CH{channel}:POW {mw:.2f}", get_power="CH{channel}:POW?", get_measured="CH{channel}:MEAS?",
    enable="CH{channel}:EMIT 1", disable="CH{channel}:EMIT 0", get_emission="CH{channel}:EMIT?",
    get_status="CH{channel}:STAT?", identify="*IDN?",
)


def channels(port_prefix: str | None = None) -> tuple[LaserChannel, ...]:
    """red (index 1) and green (index 2), 40 mW max; each on its own port when `port_prefix` is given."""
    return tuple(
        LaserChannel(name=name, index=index, wavelength_nm=nm, max_power_mw=40, setpoint_mw=1,
                     port=f"{port_prefix}-{name}" if port_prefix else None)
        for name, index, nm in (("red", 1, 680.0), ("green", 2, 520.0))
    )


def template_config(protocol: TemplateProtocol = RGB_PROTOCOL) -> LaserConfig:
    return LaserConfig(channels=channels(), driver="template", port="script://rgb", timeout_s=0.2, protocol=protocol)


def per_head_config(driver: str) -> LaserConfig:
    return LaserConfig(channels=channels(f"script://{driver}"), driver=driver, timeout_s=0.2)


@contextmanager
def scripted(cls: type[Laser], config: LaserConfig, scripts: dict[str, Pairs]) -> Iterator[Laser]:
    """`cls` on expected-protocol ports (one script per port URL), opened; every script must be used up."""
    ports = {url: ExpectedProtocol(pairs, name=url) for url, pairs in scripts.items()}
    laser = cls(config, port_factory=ports.__getitem__)
    with laser:
        yield laser
    for port in ports.values():
        port.check()
        assert port.closed


def heads(driver: str, red: Pairs, green: Pairs) -> dict[str, Pairs]:
    """Scripts for the red and green heads' ports of per_head_config(driver)."""
    return {f"script://{driver}-red": red, f"script://{driver}-green": green}


def ok(command: str, reply: str = "OK") -> tuple[bytes, bytes | None]:
    return f"{command}\r\n".encode(), f"{reply}\r\n".encode()


def obis(command: str, value: str | None = None) -> tuple[bytes, bytes | None]:
    """An OBIS exchange with handshaking: a setting answers OK, a query its value and then OK."""
    return ok(command, "OK" if value is None else f"{value}\r\nOK")


# -- template ----------------------------------------------------------------------------------------------------

TEMPLATE_OFF = [ok("CH1:EMIT 0"), ok("CH1:EMIT?", "0"), ok("CH2:EMIT 0"), ok("CH2:EMIT?", "0")]
# Connecting asks each channel whether it emits before switching it off (to report one that did).
TEMPLATE_CONNECT = [ok("CH1:EMIT?", "0"), *TEMPLATE_OFF[:2], ok("CH2:EMIT?", "0"), *TEMPLATE_OFF[2:]]


def test_template_session_bytes() -> None:
    script = TEMPLATE_CONNECT + [
        ok("*IDN?", "ACME RGB,SN 7"),
        ok("CH1:POW 20.00"), ok("CH1:POW?", "20.00"),
        ok("CH1:MEAS?", "19.90"),
        ok("CH1:STAT?"), ok("CH1:EMIT 1"), ok("CH1:EMIT?", "1"),
        ok("CH2:STAT?", "INTERLOCK OPEN"), ok("CH2:POW?", "0.00"), ok("CH2:MEAS?", "0.00"), ok("CH2:EMIT?", "0"),
        ok("CH1:EMIT 0"), ok("CH1:EMIT?", "0"),
    ] + TEMPLATE_OFF
    with scripted(TemplateLaser, template_config(), {"script://rgb": script}) as laser:
        assert laser.channel_names == ("red", "green")
        assert laser.identity() == "ACME RGB,SN 7"
        assert laser.set_power("red", "20mW") == pytest.approx(0.02)
        assert laser.measured_w("red") == pytest.approx(0.0199)
        laser.set_emission("red", True)
        status = laser.status("green")
        assert (status.name, status.wavelength_nm, status.setpoint_w, status.measured_w) == ("green", 520.0, 0.0, 0.0)
        assert (status.emission, status.interlock_ok, status.faults) == (False, False, ())
        laser.set_emission("red", False)


def test_template_in_watts_with_echo_and_on_off_replies() -> None:
    protocol = TemplateProtocol(set_power="PW{channel} {w:.4f}", get_power="PW{channel}?", enable="ON{channel}",
                                disable="OFF{channel}", get_emission="EM{channel}?", ok_reply="DONE",
                                error_prefix="?", echo=True, power_unit="W", line_ending="\n")

    def echoed(command: str, reply: str = "DONE") -> tuple[bytes, bytes | None]:
        return f"{command}\n".encode(), f"{command}\n{reply}\n".encode()

    off = [echoed("OFF1"), echoed("EM1?", "OFF"), echoed("OFF2"), echoed("EM2?", "OFF")]
    connect = [echoed("EM1?", "OFF"), *off[:2], echoed("EM2?", "OFF"), *off[2:]]
    script = connect + [echoed("PW2 0.0050"), echoed("PW2?", "0.0050"), echoed("ON2"), echoed("EM2?", "ON"),
                    echoed("PW2?", "0.0050"), echoed("EM2?", "ON")] + off
    with scripted(TemplateLaser, template_config(protocol), {"script://rgb": script}) as laser:
        assert laser.set_power("green", 0.005) == pytest.approx(0.005)
        laser.set_emission("green", True)  # no status command: nothing to check first
        assert laser.measured_w("green") is None
        status = laser.status("green")  # only PW2? and EM2?: no status or measured command configured
        assert (status.setpoint_w, status.measured_w, status.emission, status.interlock_ok) == (0.005, None, True, None)


def test_template_fault_text_blocks_emission() -> None:
    script = TEMPLATE_CONNECT + [ok("CH1:STAT?", "FAULT 1 TEMPERATURE")] + TEMPLATE_OFF
    with scripted(TemplateLaser, template_config(), {"script://rgb": script}) as laser:
        with pytest.raises(SafetyError, match="FAULT 1 TEMPERATURE"):
            laser.set_emission("red", True)


def test_template_error_reply_raises_with_the_devices_text() -> None:
    script = TEMPLATE_CONNECT + [ok("CH2:POW 30.00", "ERR 2 OUT OF RANGE")] + TEMPLATE_OFF
    with scripted(TemplateLaser, template_config(), {"script://rgb": script}) as laser:
        with pytest.raises(DeviceError, match="'CH2:POW 30.00' refused: ERR 2 OUT OF RANGE"):
            laser.set_power("green", "30mW")


def test_template_with_a_bad_placeholder_fails_at_construction() -> None:
    protocol = TemplateProtocol(set_power="CH{chanel}:POW {mw}", get_power="x", enable="x", disable="x")
    with pytest.raises(BenchctlError, match="laser.protocol.set_power"):
        TemplateLaser(template_config(protocol))


# -- cobolt ------------------------------------------------------------------------------------------------------

def cobolt_open() -> Pairs:
    return [ok("@cobas 0"), ok("l?", "0"), ok("l0"), ok("l?", "0"), ok("gmlp?", "40.0")]


COBOLT_CLOSE = [ok("l0"), ok("l?", "0")]


def test_cobolt_session_bytes() -> None:
    red = cobolt_open() + [
        ok("sn?", "21853"),
        ok("p 0.020000"), ok("p?", "0.0200"),
        ok("pa?", "0.0199"),
        ok("ilk?", "0"), ok("f?", "0"), ok("l1"), ok("l?", "1"),
        ok("ilk?", "0"), ok("f?", "4"), ok("p?", "0.0200"), ok("pa?", "0.0199"), ok("l?", "1"),
    ] + COBOLT_CLOSE
    # a firmware that refuses sn? is asked gsn?
    green = cobolt_open() + [ok("sn?", "Syntax error: illegal command"), ok("gsn?", "30001")] + COBOLT_CLOSE
    with scripted(CoboltLaser, per_head_config("cobolt"), heads("cobolt", red, green)) as laser:
        assert laser.identity() == "red: Cobolt laser, serial number 21853; green: Cobolt laser, serial number 30001"
        assert laser.set_power("red", "50%") == pytest.approx(0.02)
        assert laser.measured_w("red") == pytest.approx(0.0199)
        laser.set_emission("red", True)
        status = laser.status("red")
        assert status.emission and status.interlock_ok is True
        assert status.faults == ("constant-power fault (f? = 4)",)


def test_cobolt_interlock_open_refuses_before_l1() -> None:
    red = cobolt_open() + [ok("ilk?", "1"), ok("f?", "3")] + COBOLT_CLOSE
    green = cobolt_open() + COBOLT_CLOSE
    with scripted(CoboltLaser, per_head_config("cobolt"), heads("cobolt", red, green)) as laser:
        with pytest.raises(SafetyError, match="interlock open"):
            laser.set_emission("red", True)


def test_cobolt_clamped_readback_raises() -> None:
    red = cobolt_open() + [ok("p 0.030000"), ok("p?", "0.020000")] + COBOLT_CLOSE
    green = cobolt_open() + COBOLT_CLOSE
    with scripted(CoboltLaser, per_head_config("cobolt"), heads("cobolt", red, green)) as laser:
        with pytest.raises(DeviceError, match="asked for 30 mW, the device holds 20 mW"):
            laser.set_power("red", "30mW")


def test_cobolt_syntax_error_raises_with_the_devices_text() -> None:
    red = [ok("@cobas 0", "Syntax error: illegal command"), ok("l0"), ok("l?", "0")]
    green = cobolt_open()
    ports = {"script://cobolt-red": ExpectedProtocol(red), "script://cobolt-green": ExpectedProtocol(green)}
    with pytest.raises(DeviceError, match="'@cobas 0' refused: Syntax error: illegal command"):
        CoboltLaser(per_head_config("cobolt"), port_factory=ports.__getitem__).open()
    for port in ports.values():  # the failing head was still switched off, the other made safe too
        port.check()
        assert port.closed


def test_cobolt_head_limit_refuses_before_sending() -> None:
    red = [ok("@cobas 0"), ok("l?", "0"), ok("l0"), ok("l?", "0"), ok("gmlp?", "25.0")] + COBOLT_CLOSE
    green = cobolt_open() + COBOLT_CLOSE
    with scripted(CoboltLaser, per_head_config("cobolt"), heads("cobolt", red, green)) as laser:
        with pytest.raises(DeviceError, match="above the head's own limit 25 mW; nothing was sent"):
            laser.set_power("red", "30mW")


def test_cobolt_refuses_channels_sharing_a_port() -> None:
    config = LaserConfig(channels=channels(), driver="cobolt", port="script://one")
    with pytest.raises(BenchctlError, match="share port script://one"):
        CoboltLaser(config)


# -- sapphire ----------------------------------------------------------------------------------------------------

PROMPT = "Sapphire:0-> "


def sapphire(command: str, *answer: str) -> tuple[bytes, bytes | None]:
    """A Sapphire exchange with echo off and the prompt on: the returned line ending, the answer, the prompt."""
    return f"{command}\r\n".encode(), "".join(f"{line}\r\n" for line in ("", *answer)).encode() + PROMPT.encode()


def sapphire_open(echo: bool = False) -> Pairs:
    """Connecting: the prompt on and echo off (a head that echoes echoes these two), then made safe as every laser."""
    line = [
        (b">=1\r\n", (b">=1" if echo else b"") + f"\r\n{PROMPT}".encode()),
        (b"E=0\r\n", (b"E=0" if echo else b"") + f"\r\n{PROMPT}".encode()),
    ]
    return line + [sapphire("?L", "0"), sapphire("L=0"), sapphire("?L", "0"), sapphire("?MAXLP", "220.000")]


SAPPHIRE_CLOSE = [sapphire("L=0"), sapphire("?L", "0")]


def test_sapphire_session_bytes() -> None:
    red = sapphire_open(echo=True) + [
        sapphire("?HID", "505925.000"),
        sapphire("P=20.000", "Note: Laser_Output is OFF (L=0)"), sapphire("?SP", "20.000"),
        sapphire("?K", "1"), sapphire("?FF", "0"), sapphire("L=1"), sapphire("?L", "1"),
        sapphire("?P", "19.990"),
        sapphire("?K", "1"), sapphire("?FF", str(1 << 13 | 1 << 4)), sapphire("?SP", "20.000"),
        sapphire("?P", "19.990"), sapphire("?L", "1"),
    ] + SAPPHIRE_CLOSE
    green = sapphire_open() + [sapphire("?HID", "600001.000"), sapphire("P=5.000", "value must be between 20.000 "
                                                                                   "and 220.000")] + SAPPHIRE_CLOSE
    with scripted(SapphireLaser, per_head_config("sapphire"), heads("sapphire", red, green)) as laser:
        assert laser.identity() == "red: Coherent Sapphire, head 505925.000; green: Coherent Sapphire, head 600001.000"
        assert laser.set_power("red", "20mW") == pytest.approx(0.02)
        laser.set_emission("red", True)
        assert laser.measured_w("red") == pytest.approx(0.01999)
        status = laser.status("red")
        assert (status.emission, status.interlock_ok, status.faults) == (True, True, ("diode current fault",))
        with pytest.raises(DeviceError, match=r"'P=5\.000' refused: value must be between 20\.000 and 220\.000"):
            laser.set_power("green", "5mW")


def test_sapphire_interlock_and_key_refuse_before_l1() -> None:
    red = sapphire_open() + [sapphire("?K", "1"), sapphire("?FF", "1")] + SAPPHIRE_CLOSE
    green = sapphire_open() + [sapphire("?K", "0"), sapphire("?FF", "0")] + SAPPHIRE_CLOSE
    with scripted(SapphireLaser, per_head_config("sapphire"), heads("sapphire", red, green)) as laser:
        with pytest.raises(SafetyError, match="interlock open"):
            laser.set_emission("red", True)
        with pytest.raises(SafetyError, match=r"fault active \(key switch at standby\)"):
            laser.set_emission("green", True)


# -- deepstar ----------------------------------------------------------------------------------------------------

def deepstar(command: str, reply: str) -> tuple[bytes, bytes | None]:
    """A Deepstar exchange: the command padded to 14 characters, CR LF."""
    return f"{command:<14}\r\n".encode(), f"{reply}\r\n".encode()


def deepstar_open(emitting_at: str | None = None) -> Pairs:
    """Connecting: the state, LF (UK: it was not on), the state again, the model code (the head's maximum); a head
    found in S2 is asked its setpoint to report it."""
    if emitting_at is None:
        return [deepstar("S?", "S1"), deepstar("LF", "UK"), deepstar("S?", "S1"), deepstar("STAT0", "MC 488  200 TA")]
    return [deepstar("S?", "S2"), deepstar("LF", "LOFFOK"), deepstar("S?", "S1"), deepstar("PP?", emitting_at),
            deepstar("STAT0", "MC 488  200 TA")]


DEEPSTAR_CLOSE = [deepstar("LF", "UK"), deepstar("S?", "S1")]


def test_deepstar_session_bytes() -> None:
    red = deepstar_open(emitting_at="PP800") + [
        deepstar("STAT2", "R111 N02 SNP131056 SNC131056 WH 04667 SLS B9C 500"),
        deepstar("PP400", "PP400"), deepstar("PP?", "PP400"),  # 50 mW of 200: 1023.75 steps of 0xFFF
        deepstar("S?", "S1"), deepstar("LON", "LONOK"), deepstar("L2", ">"), deepstar("IPO", "IPO"),
        deepstar("S?", "S2"),
        deepstar("P?", "P0147"),
        deepstar("LF", "LOFFOK"), deepstar("S?", "S1"),
    ] + DEEPSTAR_CLOSE
    green = deepstar_open() + [deepstar("STAT2", "R111 N02"), deepstar("S?", "S0")] + DEEPSTAR_CLOSE
    config = LaserConfig(channels=tuple(msgspec.structs.replace(ch, max_power_mw=150) for ch in channels(
        "script://deepstar")), driver="deepstar", timeout_s=0.2)
    with scripted(DeepstarLaser, config, heads("deepstar", red, green)) as laser:
        assert laser.connect_report() == ["red was emitting at 100.024 mW; switched off"]  # 0x800 of 0xFFF
        assert laser.identity() == ("red: Omicron Deepstar 488 nm 200 mW, head serial 131056; green: Omicron Deepstar "
                                    "488 nm 200 mW, head serial ?")
        assert laser.set_power("red", "50mW") == pytest.approx(1024 / 4095 * 0.2)
        laser.set_emission("red", True)
        assert laser.measured_w("red") == pytest.approx(327 / 0xCCC * 0.2)
        laser.set_emission("red", False)
        with pytest.raises(SafetyError, match=r"fault active \(error or interlock open \(state S0\)\)"):
            laser.set_emission("green", True)


def test_deepstar_interlocked_at_lon_is_switched_off_again() -> None:
    """The state said S1, then LON answers INT (the interlock opened meanwhile): a SafetyError, and LF is sent."""
    red = deepstar_open() + [deepstar("S?", "S1"), deepstar("LON", "INT"), deepstar("LF", "UK"),
                             deepstar("S?", "S0")] + [deepstar("LF", "UK"), deepstar("S?", "S0")]
    green = deepstar_open() + DEEPSTAR_CLOSE
    config = LaserConfig(channels=channels("script://deepstar"), driver="deepstar", timeout_s=0.2)
    with scripted(DeepstarLaser, config, heads("deepstar", red, green)) as laser:
        with pytest.raises(SafetyError, match=r"interlock open \(LON answered INT\): emission not enabled"):
            laser.set_emission("red", True)


def test_deepstar_head_limit_refuses_before_sending() -> None:
    red = deepstar_open() + DEEPSTAR_CLOSE
    green = deepstar_open() + DEEPSTAR_CLOSE
    config = LaserConfig(channels=tuple(msgspec.structs.replace(ch, max_power_mw=500) for ch in channels(
        "script://deepstar")), driver="deepstar", timeout_s=0.2)
    with scripted(DeepstarLaser, config, heads("deepstar", red, green)) as laser:
        with pytest.raises(DeviceError, match="above the head's own limit 200 mW; nothing was sent"):
            laser.set_power("red", "300mW")


# -- obis --------------------------------------------------------------------------------------------------------

def obis_open(prefix: str = "SOURce", system: str = "SYSTem") -> Pairs:
    return [
        obis(f"{system}:AUTostart OFF"), obis(f"{system}:CDRH OFF"), obis(f"{prefix}:AM:STATe?", "OFF"),
        obis(f"{prefix}:AM:STATe OFF"), obis(f"{prefix}:AM:STATe?", "OFF"),
        obis(f"{prefix}:POWer:LIMit:HIGH?", "0.0400"),
    ]


def obis_close(prefix: str = "SOURce") -> Pairs:
    return [obis(f"{prefix}:AM:STATe OFF"), obis(f"{prefix}:AM:STATe?", "OFF")]


def test_obis_session_bytes() -> None:
    red = obis_open() + [
        obis("*IDN?", "Coherent, Inc - OBIS 637nm LX 140mW - V1.0 - 12345"),
        obis("SOURce:POWer:LEVel:IMMediate:AMPLitude 0.020000"),
        obis("SOURce:POWer:LEVel:IMMediate:AMPLitude?", "2.0000e-02"),
        obis("SOURce:POWer:LEVel?", "0.01990"),
        obis("SYSTem:LOCK?", "ON"), obis("SYSTem:FAULt?", "0x00000000"),
        obis("SOURce:AM:STATe ON"), obis("SOURce:AM:STATe?", "ON"),
        obis("SYSTem:LOCK?", "ON"), obis("SYSTem:FAULt?", "0x00000003"),
        obis("SOURce:POWer:LEVel:IMMediate:AMPLitude?", "0.020000"), obis("SOURce:POWer:LEVel?", "0.0199"),
        obis("SOURce:AM:STATe?", "ON"),
    ] + obis_close()
    green = obis_open() + [obis("*IDN?", "Coherent, Inc - OBIS 520nm LX 50mW - V1.0 - 23456")] + obis_close()
    with scripted(ObisLaser, per_head_config("obis"), heads("obis", red, green)) as laser:
        assert laser.identity().startswith("red: Coherent, Inc - OBIS 637nm")
        assert laser.set_power("red", "20mW") == pytest.approx(0.02)
        assert laser.measured_w("red") == pytest.approx(0.0199)
        laser.set_emission("red", True)
        status = laser.status("red")
        assert status.emission and status.interlock_ok is True
        assert status.faults == ("base plate temperature out of range", "diode temperature out of range")


def test_obis_box_addresses_heads_after_the_first_keyword() -> None:
    config = LaserConfig(channels=channels(), driver="obis", port="script://box", timeout_s=0.2)
    script = obis_open("SOURce1", "SYSTem1") + obis_open("SOURce2", "SYSTem2") + [
        obis("*IDN?", "Coherent, Inc - OBIS LX/LS box"),
        obis("SOURce2:POWer:LEVel:IMMediate:AMPLitude 0.005000"),
        obis("SOURce2:POWer:LEVel:IMMediate:AMPLitude?", "0.005"),
        obis("SYSTem2:LOCK?", "OFF"), obis("SYSTem2:FAULt?", "0"),
    ] + obis_close("SOURce1") + obis_close("SOURce2")
    with scripted(ObisLaser, config, {"script://box": script}) as laser:
        assert laser.identity() == "Coherent, Inc - OBIS LX/LS box"
        laser.set_power("green", "5mW")
        with pytest.raises(SafetyError, match="interlock open"):
            laser.set_emission("green", True)


def test_obis_error_reply_and_missing_handshake() -> None:
    red = obis_open() + [
        ok("SOURce:POWer:LEVel:IMMediate:AMPLitude 0.010000", "ERR-220"),
        (b"SOURce:POWer:LEVel?\r\n", Stalls(b"0.0100\r\n0.0100\r\n")),  # two values, then no OK: framing lost
    ] + obis_close()
    green = obis_open() + obis_close()
    with scripted(ObisLaser, per_head_config("obis"), heads("obis", red, green)) as laser:
        with pytest.raises(DeviceError, match="refused: ERR-220"):
            laser.set_power("red", "10mW")
        with pytest.raises(DeviceError, match="garbled|no reply"):
            laser.measured_w("red")


def test_open_laser_chooses_the_driver_by_name() -> None:
    ports = {"script://rgb": ExpectedProtocol(TEMPLATE_CONNECT + TEMPLATE_OFF)}
    with open_laser(template_config(), port_factory=ports.__getitem__) as laser:
        assert type(laser) is TemplateLaser and laser.is_open
    assert not laser.is_open
    ports["script://rgb"].check()
