"""benchctl's laser drivers against python-microscope's byte-level mocks of real lasers (microscope.testsuite.
mock_devices, a test-only dependency: GPL-3.0+): a Cobolt Jive, a Coherent Sapphire and an Omicron Deepstar, as
python-microscope's authors modelled them from the manuals and their own hardware. A thin adapter gives a mock the
few port methods SerialLink uses; the mock answers each command as it is written."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
from microscope.testsuite import mock_devices

from benchctl.devices.errors import DeviceError, SafetyError
from benchctl.devices.laser import open_laser
from benchctl.devices.laser.base import Laser
from benchctl.profiles import LaserChannel, LaserConfig

pytestmark = pytest.mark.third_party


class MockPort:
    """A python-microscope SerialMock as the port SerialLink reads and writes; closing it leaves the mock (the laser
    it stands for) as it is, to be looked at."""

    def __init__(self, mock: Any) -> None:
        self.mock = mock
        self.closed = False

    @property
    def in_waiting(self) -> int:
        return int(self.mock.in_buffer.getbuffer().nbytes - self.mock.in_read_bytes)

    def read(self, size: int = 1) -> bytes:
        data: bytes = self.mock.read(size)
        return data

    def write(self, data: bytes) -> int:
        self.mock.write(bytes(data))
        return len(data)

    def flush(self) -> None:
        """The mock answers as it is written to."""

    def reset_input_buffer(self) -> None:
        self.mock.reset_input_buffer()

    def close(self) -> None:
        self.closed = True


@contextmanager
def laser_on(driver: str, mock: Any, max_power_mw: float = 100.0, **options: Any) -> Iterator[Laser]:
    """benchctl's `driver` for one channel, green, whose port is `mock`: connected (made safe) and closed after."""
    config = LaserConfig(channels=(LaserChannel(name="green", index=1, wavelength_nm=561.0, max_power_mw=max_power_mw,
                                                setpoint_mw=20.0, port="mock://green"),),
                         driver=driver, timeout_s=0.2)
    port = MockPort(mock)
    with open_laser(config, port_factory=lambda url: port, **options) as laser:
        yield laser
    assert port.closed


def test_cobolt_against_python_microscopes_jive() -> None:
    mock = mock_devices.CoboltLaserMock()
    mock.auto_start, mock.light = True, True  # left emitting in autostart: connecting clears both
    with laser_on("cobolt", mock) as laser:
        assert laser.connect_report() == ["green was emitting at 50 mW; switched off"]
        assert (mock.auto_start, mock.light) == (False, False)
        assert laser.identity() == "Cobolt laser, serial number 7863"  # asked as sn?: the Jive refuses gsn?
        assert laser.set_power("green", "20mW") == pytest.approx(0.02) and mock.power == pytest.approx(20.0)
        laser.set_emission("green", True)
        assert mock.light and laser.measured_w("green") == pytest.approx(0.02)
        status = laser.status("green")
        assert (status.emission, status.interlock_ok, status.faults) == (True, True, ())
        laser.set_emission("green", False)
        assert not mock.light
        mock.interlock_open = True
        with pytest.raises(SafetyError, match="interlock open: emission not enabled"):
            laser.set_emission("green", True)
        assert not mock.light
        laser.set_emission("green", False)
        mock.interlock_open = False
        laser.set_emission("green", True)
    assert not mock.light  # off on the way out


def test_sapphire_against_python_microscopes_mock() -> None:
    """The mock starts as a head whose key was just turned on: ready and emitting at 50 mW, echo and prompt on."""
    mock = mock_devices.CoherentSapphireLaserMock()
    assert mock.light and mock.echo and mock.prompt
    with laser_on("sapphire", mock, max_power_mw=100.0) as laser:
        assert laser.connect_report() == ["green was emitting at 50 mW; switched off"]
        assert (mock.light, mock.echo, mock.prompt) == (False, False, True)
        assert laser.identity() == "Coherent Sapphire, head 505925.000"
        assert laser.set_power("green", "30mW") == pytest.approx(0.03) and mock.power == pytest.approx(30.0)
        with pytest.raises(DeviceError, match=r"'P=10\.000' refused: value must be between 20\.000 and 220\.000"):
            laser.set_power("green", "10mW")  # below this head's minimum
        laser.set_emission("green", True)
        assert mock.light and laser.measured_w("green") == pytest.approx(0.03)
        status = laser.status("green")  # ?FF has bit 13, "laser ready": not a fault
        assert (status.emission, status.interlock_ok, status.faults) == (True, True, ())
        laser.set_emission("green", False)
        mock.key = "standby"
        with pytest.raises(SafetyError, match=r"fault active \(key switch at standby\)"):
            laser.set_emission("green", True)
        mock.key = "on"
        laser.set_emission("green", True)
    assert not mock.light


def test_sapphire_head_limit_refuses_before_sending() -> None:
    mock = mock_devices.CoherentSapphireLaserMock()
    with laser_on("sapphire", mock, max_power_mw=500.0) as laser:
        with pytest.raises(DeviceError, match="above the head's own limit 220 mW; nothing was sent"):
            laser.set_power("green", "300mW")
        assert mock.power == pytest.approx(50.0)


def test_deepstar_against_python_microscopes_mock() -> None:
    """Fixed 16-byte commands (the mock refuses any other length in standby); on is LON, Deepstar mode, internal
    peak power, after which the mock's light is on; off is LF."""
    mock = mock_devices.OmicronDeepstarLaserMock()
    with laser_on("deepstar", mock, max_power_mw=150.0) as laser:
        assert laser.connect_report() == [] and mock.state == mock.State.S1
        assert laser.identity() == "Omicron Deepstar 488 nm 200 mW, head serial 131056"
        assert laser.set_power("green", "100mW") == pytest.approx(0.1, abs=0.2 / 4095)
        assert mock.power == pytest.approx(100.0, abs=200 / 4095)
        laser.set_emission("green", True)
        assert mock.light and mock.mode == mock.Mode.deepstar and mock.internal_peak_power
        assert laser.measured_w("green") == pytest.approx(0.1, abs=0.2 / 0xCCC)
        laser.set_emission("green", False)
        assert mock.state == mock.State.S1 and not mock.light
        mock.state = mock.State.S0  # interlocked
        with pytest.raises(SafetyError, match=r"fault active \(error or interlock open \(state S0\)\)"):
            laser.set_emission("green", True)
        mock.state = mock.State.S1
        laser.set_emission("green", True)
    assert not mock.light and mock.state == mock.State.S1


def test_an_observing_connection_changes_nothing_on_the_sapphire() -> None:
    """`laser status` connects to observe: it may still set the line up (echo off, prompt on), never the light."""
    mock = mock_devices.CoherentSapphireLaserMock()
    with laser_on("sapphire", mock, observe=True) as laser:
        assert laser.status("green").emission
    assert mock.light
