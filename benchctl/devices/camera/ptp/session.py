"""PTP sessions and transactions over a Transport: command, optional data phase either way, response.

Each operation is one transaction with its own id; ids count up from OpenSession, which uses 0. A response
other than OK becomes a ResponseError naming the operation and the response (DeviceBusy also a DeviceBusy);
pyusb errors from the transport become one-line DeviceErrors saying which operation they interrupted.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass

import usb.core

from benchctl.devices.camera.ptp.container import (
    Container,
    ContainerType,
    MalformedContainer,
    OperationCode,
    ResponseCode,
    code_name,
)
from benchctl.devices.camera.ptp.datasets import DeviceInfo, ObjectInfo
from benchctl.devices.camera.ptp.transport import Transport, usb_failure
from benchctl.devices.errors import DeviceBusy, DeviceError

SESSION_ID = 1
_LAST_TRANSACTION_ID = 0xFFFFFFFE  # 0xFFFFFFFF is reserved; ids wrap to 1
MAX_DATA_CONTAINERS = 4096  # data containers in one transaction (a camera sends one per object or property)
MAX_DATA_BYTES = 512 << 20  # bytes of data in one transaction (the largest RAW files are ~100 MB)
TRANSACTION_DEADLINE_S = 600.0  # one transaction, however its camera keeps answering
_HINTS: dict[int, str] = {
    ResponseCode.SessionNotOpen: "the camera closed the session (asleep or reset?): reconnect",
    ResponseCode.OperationNotSupported: "this camera does not offer that operation",
}


class ResponseError(DeviceError):
    """The camera answered an operation with a response code other than OK."""

    def __init__(self, operation: int, response: int, params: tuple[int, ...] = ()) -> None:
        self.operation = operation
        self.response = response
        self.params = params
        hint = _HINTS.get(response)
        super().__init__(f"camera refused {code_name(operation)}: {code_name(response)}"
                         + (f"; {hint}" if hint else ""))


class ResponseBusy(ResponseError, DeviceBusy):
    """The camera answered DeviceBusy (0x2019)."""


def response_error(operation: int, response: int, params: tuple[int, ...] = ()) -> ResponseError:
    cls = ResponseBusy if response == ResponseCode.DeviceBusy else ResponseError
    return cls(operation, response, params)


@dataclass(frozen=True)
class Response:
    """The outcome of a transaction: response code and parameters, and the data phase the camera sent."""

    code: int
    params: tuple[int, ...] = ()
    data: bytes = b""


class PtpSession:
    """One PTP session on a transport; `request` runs a transaction and raises unless the response is OK."""

    def __init__(self, transport: Transport, timeout_s: float | None = None) -> None:
        self.transport = transport
        self.timeout_s = timeout_s  # only for messages: the transport enforces its own timeout
        self.is_open = False
        self._next_id = 0

    @contextlib.contextmanager
    def _usb(self, doing: str) -> Iterator[None]:
        try:
            yield
        except usb.core.USBError as exc:
            raise usb_failure(exc, doing, self.timeout_s) from exc

    def open(self, session_id: int = SESSION_ID) -> None:
        """OpenSession(session_id) with transaction id 0; later operations count on from 1. A session left open
        (by a program that died) is closed and opened afresh."""
        self._next_id = 0
        response = self.transact(OperationCode.OpenSession, session_id)
        if response.code == ResponseCode.SessionAlreadyOpen:
            self.request(OperationCode.CloseSession)
            self._next_id = 0
            response = self.transact(OperationCode.OpenSession, session_id)
        if response.code != ResponseCode.OK:
            raise response_error(OperationCode.OpenSession, response.code, response.params)
        self.is_open = True

    def close(self) -> None:
        """CloseSession, if one is open."""
        if self.is_open:
            self.is_open = False
            self.request(OperationCode.CloseSession)

    def _take_id(self) -> int:
        transaction_id = self._next_id
        self._next_id = 1 if transaction_id >= _LAST_TRANSACTION_ID else transaction_id + 1
        return transaction_id

    def transact(self, operation: int, *params: int, data: bytes | None = None) -> Response:
        """Run one transaction (sending `data` as its data phase, if given) and return the response as is."""
        transaction_id = self._take_id()
        name = code_name(operation)
        with self._usb(name):
            self.transport.send(Container(ContainerType.COMMAND, operation, transaction_id, params).pack())
            if data is not None:
                self.transport.send(Container(ContainerType.DATA, operation, transaction_id, payload=data).pack())
            received = bytearray()  # appending to bytes would copy everything received so far, every time
            containers = 0
            deadline = time.monotonic() + TRANSACTION_DEADLINE_S
            while True:
                if time.monotonic() > deadline:
                    raise DeviceError(f"camera: {name} did not end within {TRANSACTION_DEADLINE_S:g} s; reconnect "
                                      "the camera")
                container = Container.unpack(self.transport.receive())
                if container.transaction_id != transaction_id:
                    raise DeviceError(f"camera answered transaction {container.transaction_id} while {name} was "
                                      f"transaction {transaction_id}: out of step; reconnect the camera")
                if container.type == ContainerType.DATA:
                    containers += 1
                    if containers > MAX_DATA_CONTAINERS or len(received) + len(container.payload) > MAX_DATA_BYTES:
                        raise DeviceError(f"camera: {name} sent over {MAX_DATA_CONTAINERS} data containers or "
                                          f"{MAX_DATA_BYTES:,} bytes without ending; reconnect the camera")
                    received += container.payload
                elif container.type == ContainerType.RESPONSE:
                    return Response(container.code, container.params, bytes(received))
                else:
                    raise MalformedContainer(f"unexpected {container.type.name.lower()} container "
                                             f"{code_name(container.code)} on the bulk pipe during {name}")

    def request(self, operation: int, *params: int, data: bytes | None = None) -> Response:
        """`transact`, raising ResponseError (ResponseBusy for DeviceBusy) unless the camera answered OK."""
        response = self.transact(operation, *params, data=data)
        if response.code != ResponseCode.OK:
            raise response_error(operation, response.code, response.params)
        return response

    def get_device_info(self) -> DeviceInfo:
        return DeviceInfo.unpack(self.request(OperationCode.GetDeviceInfo).data)

    def get_object_info(self, handle: int) -> ObjectInfo:
        return ObjectInfo.unpack(self.request(OperationCode.GetObjectInfo, handle).data)

    def poll_event(self, timeout_s: float) -> Container | None:
        """The next standard PTP event from the interrupt endpoint, or None within `timeout_s`."""
        with self._usb("an event wait"):
            raw = self.transport.receive_event(timeout_s)
        return None if raw is None else Container.unpack(raw)
