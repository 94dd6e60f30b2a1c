"""SerialLink: exact framing, echo, error replies, resynchronisation and every failure as a one-line DeviceError."""

from __future__ import annotations

import threading
import time

import pytest
import serial
from expected_protocol import ExpectedProtocol, Stalls
from hypothesis import given, settings
from hypothesis import strategies as st

from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.devices.serial_link import ErrorReply, SerialLink, open_port

URL = "script://unit"


def scripted(pairs: list[tuple[bytes, bytes | None]], **options: object) -> tuple[SerialLink, ExpectedProtocol]:
    port = ExpectedProtocol(pairs)
    return SerialLink(URL, name="laser", port=port, timeout_s=0.2, **options), port  # type: ignore[arg-type]


def one_line(exc: pytest.ExceptionInfo[BaseException]) -> str:
    message = str(exc.value)
    assert "\n" not in message
    return message


def test_query_command_and_multi_line_replies_use_exact_bytes() -> None:
    link, port = scripted([
        (b"*IDN?\r\n", b"unit 1\r\n"),
        (b"CH1:EMIT 0\r\n", b"OK\r\n"),
        (b"SYST:INFO?\r\n", b"model X\r\nSN 7\r\nOK\r\n"),
    ])
    with port, link:
        assert link.query("*IDN?") == "unit 1"
        link.command("CH1:EMIT 0", "OK")
        assert link.query_lines("SYST:INFO?", until="OK") == ["model X", "SN 7"]
    assert port.closed


def test_line_ending_is_the_dialects_own() -> None:
    link, port = scripted([(b"p?\r", b"0.5\r")], line_ending="\r")
    with port:
        assert link.query("p?") == "0.5"


def test_echo_is_consumed_when_configured() -> None:
    link, port = scripted([(b"l?\r\n", b"l?\r\n1\r\n"), (b"l1\r\n", b"l1\r\nOK\r\n")], echo=True)
    with port:
        assert link.query("l?") == "1"
        link.command("l1")


def test_unexpected_echo_is_reported() -> None:
    link, _ = scripted([(b"l?\r\n", b"l?\r\n1\r\n")])
    with pytest.raises(DeviceError) as info:
        link.query("l?")
    assert "echo" in one_line(info) and "'l?'" in str(info.value)


def test_missing_echo_is_reported() -> None:
    link, _ = scripted([(b"l?\r\n", b"1\r\n")], echo=True)
    with pytest.raises(DeviceError, match="expected the echo of 'l\\?'"):
        link.query("l?")


def test_error_reply_carries_the_devices_text_and_keeps_the_line_in_step() -> None:
    link, port = scripted([(b"CH1:POW 99\r\n", b"ERR 2 OUT OF RANGE\r\n"), (b"CH1:POW?\r\n", b"1.00\r\n")],
                          error_prefix="ERR")
    with port:
        with pytest.raises(ErrorReply) as info:
            link.command("CH1:POW 99")
        message = one_line(info)
        assert "ERR 2 OUT OF RANGE" in message and "CH1:POW 99" in message and URL in message
        assert link.query("CH1:POW?") == "1.00"  # no drain (the script would fail a read with nothing pending)


def test_unexpected_reply_to_a_command() -> None:
    link, port = scripted([(b"l0\r\n", b"BUSY\r\n")])
    with port, pytest.raises(DeviceError, match="unexpected reply to 'l0': 'BUSY'"):
        link.command("l0")


def test_no_reply_is_a_timeout_naming_command_and_port() -> None:
    link, port = scripted([(b"p?\r\n", None)])
    with port, pytest.raises(DeviceTimeout) as info:
        link.query("p?")
    message = one_line(info)
    assert "no reply to 'p?'" in message and URL in message and "laser" in message


@pytest.mark.parametrize("reply", [b"\xff\xfe\r\n", b"OK\x00\r\n", Stalls(b"OK")])
def test_garbled_reply_is_a_device_error_not_a_timeout(reply: bytes) -> None:
    link, port = scripted([(b"p?\r\n", reply)])
    with port, pytest.raises(DeviceError, match="garbled reply to 'p\\?'") as info:
        link.query("p?")
    assert not isinstance(info.value, DeviceTimeout)


def test_closed_link_refuses_commands() -> None:
    link, _ = scripted([])
    link.close()
    link.close()
    with pytest.raises(DeviceError, match="closed"):
        link.query("p?")


def test_non_ascii_command_is_refused_before_sending() -> None:
    link, port = scripted([])
    with port, pytest.raises(DeviceError, match="ASCII"):
        link.query("p\u00b5?")


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=40))
def test_any_reply_bytes_give_a_line_or_a_device_error(reply: bytes) -> None:
    link, _ = scripted([(b"p?\r\n", Stalls(reply))])
    try:
        line = link.query("p?")
    except DeviceError as exc:
        assert "\n" not in str(exc)
    else:
        assert line.isprintable() and reply.startswith(line.encode() + b"\r\n")


# -- against real pyserial ports: sim://, loop://, missing and busy ports ----------------------------------------


def test_sim_scheme_is_registered_and_speaks_the_template_protocol() -> None:
    with SerialLink("sim://rgb-laser", timeout_s=0.5, error_prefix="ERR") as link:
        assert link.query("*IDN?").startswith("benchctl,simulated RGB laser")
        link.command("CH2:POW 1.50")
        assert link.query("CH2:POW?") == "1.500"
        with pytest.raises(ErrorReply, match="ERR 1 UNKNOWN COMMAND"):
            link.query("HELLO?")
    assert "benchctl.devices.sim" in serial.protocol_handler_packages


def test_busy_port() -> None:
    with SerialLink("sim://rgb-laser", timeout_s=0.2):
        with pytest.raises(DeviceBusy) as info:
            SerialLink("sim://rgb-laser", timeout_s=0.2, name="laser")
        assert "sim://rgb-laser" in one_line(info)
    SerialLink("sim://rgb-laser", timeout_s=0.2).close()  # free again once closed


@pytest.mark.parametrize(("url", "says"), [
    ("/dev/benchctl-no-such-port", "not found"),
    ("nosuchscheme://x", "cannot open port"),
    ("sim://rgb-laser?dialect=klingon", "unknown dialect"),
    ("sim://rgb-laser?fault=on_fire", "unknown fault"),
])
def test_port_that_cannot_be_opened(url: str, says: str) -> None:
    with pytest.raises(DeviceError) as info:
        SerialLink(url, timeout_s=0.2, name="laser")
    message = one_line(info)
    assert says in message and url in message


def test_sim_no_reply_times_out_within_about_the_timeout() -> None:
    with SerialLink("sim://rgb-laser?fault=no_reply", timeout_s=0.2) as link:
        started = time.monotonic()
        with pytest.raises(DeviceTimeout, match="no reply to '\\*IDN\\?' within 0.2 s"):
            link.query("*IDN?")
        assert 0.15 < time.monotonic() - started < 1.0


def test_stale_input_is_flushed_before_a_command() -> None:
    port = open_port("sim://rgb-laser", baudrate=115200, timeout_s=0.5, name="laser")
    port.write(b"*IDN?\r\n")  # its reply is left unread in the input buffer
    time.sleep(0.01)
    with SerialLink("sim://rgb-laser", timeout_s=0.5, port=port) as link:
        assert link.query("CH1:POW?") == "0.000"


def test_a_late_reply_is_drained_not_taken_for_the_next_answer() -> None:
    port = open_port("sim://rgb-laser?reply_delay_s=0.3", baudrate=115200, timeout_s=0.2, name="laser")
    with SerialLink("sim://rgb-laser", timeout_s=0.2, port=port) as link:
        with pytest.raises(DeviceTimeout):
            link.query("*IDN?")  # its reply arrives 0.1 s after the timeout
        port.timeout = link.timeout_s = 0.5
        assert link.query("CH1:POW?") == "0.000"


def test_channels_share_one_link_across_threads() -> None:
    with SerialLink("sim://rgb-laser", timeout_s=1.0) as link:
        for index in (1, 2, 3):
            link.command(f"CH{index}:POW {index}.00")
        results: dict[int, list[str]] = {}

        def poll(index: int) -> None:
            results[index] = [link.query(f"CH{index}:POW?") for _ in range(15)]

        threads = [threading.Thread(target=poll, args=(index,)) for index in (1, 2, 3)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert results == {index: [f"{index}.000"] * 15 for index in (1, 2, 3)}


def test_write_delay_pauses_after_each_write() -> None:
    link, port = scripted([(b"l0\r\n", b"OK\r\n")], write_delay_s=0.05)
    started = time.monotonic()
    with port:
        link.command("l0")
    assert time.monotonic() - started >= 0.05


def test_loop_url_works_through_the_same_code() -> None:
    with SerialLink("loop://", timeout_s=0.2, echo=True) as link:  # a loopback echoes: the echo is consumed ...
        with pytest.raises(DeviceTimeout):
            link.query("ping")  # ... and then nothing answers
