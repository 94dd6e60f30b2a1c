"""PTP over USB for Canon EOS bodies, in layers (imports point down):

    eos.py        Canon EOS extension: remote mode, GetEvent records, remote release, chunked download
    session.py    sessions and transactions: command, data phase, response -> errors
    datasets.py   DeviceInfo / ObjectInfo datasets
    container.py  codes, and the container every message travels in
    transport.py  bytes over USB endpoints (bulk, interrupt, zero-length packets); `Transport` for simulators

The camera driver on top is benchctl.devices.camera.ptp_camera (`open_ptp_camera`).
"""

from benchctl.devices.camera.ptp.container import Container, ContainerType, MalformedContainer
from benchctl.devices.camera.ptp.eos import Eos
from benchctl.devices.camera.ptp.session import PtpSession, Response, ResponseBusy, ResponseError
from benchctl.devices.camera.ptp.transport import Transport, UsbTransport

__all__ = ["Container", "ContainerType", "Eos", "MalformedContainer", "PtpSession", "Response", "ResponseBusy",
           "ResponseError", "Transport", "UsbTransport"]
