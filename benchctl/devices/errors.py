"""Errors devices raise: all are BenchctlErrors, shown to the user as one line naming device and port."""

from benchctl.errors import BenchctlError


class DeviceError(BenchctlError):
    """A device is missing, refused a command, answered something unexpected or reports a fault."""


class DeviceTimeout(DeviceError):
    """A device did not answer within its timeout (lost reply, cable pulled, wrong port or baud rate)."""


class DeviceBusy(DeviceError):
    """The port or device is held by another program."""


class SafetyError(DeviceError):
    """Refused before anything was sent: the request would break a safety rule (power above the limit,
    emission with the interlock open or a fault active)."""


class EmissionNotOff(SafetyError):
    """Switching a laser's emission off was not confirmed: its state is unknown (possibly on) or it is still on."""
