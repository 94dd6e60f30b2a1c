"""The outputs (monitors) of an X11 desktop, read through RandR with python-xlib: name, mode, position, EDID.

Every X screen of the display is read (a desktop usually has one screen with one output per connector; Xvfb's
test servers have one output per screen). The EDID comes from the output's `EDID` property; one that cannot be
parsed (bad checksum, truncated) leaves its output listed with the reason, never hides the others. python-xlib is an
optional dependency (`pip install 'benchctl[display]'`): without it, or without a display to connect to, the
functions here raise a one-line DeviceError saying so.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from benchctl.devices.errors import DeviceError
from benchctl.devices.slm.edid import Edid, parse_edid

INSTALL_HINT = "pip install 'benchctl[display]'"


@dataclass(frozen=True)
class DesktopOutput:
    """One connected output with a mode: where it sits on its X screen and what its EDID says."""

    display: str  # the X display, e.g. ":0"
    screen: int
    name: str  # the RandR output (connector) name, e.g. HDMI-A-1
    x: int
    y: int
    width: int
    height: int
    refresh_hz: float | None  # None where the mode has no timing (virtual outputs)
    crtc: int
    edid: Edid | None
    edid_error: str | None = None  # why the output's EDID could not be read (then `edid` is None)

    def describe(self) -> str:
        rate = f" @ {self.refresh_hz:.2f} Hz" if self.refresh_hz else ""
        monitor = f"{self.edid.name or '?'} serial {self.edid.serial or '?'}" if self.edid else (
            f"EDID unreadable ({self.edid_error})" if self.edid_error else "no EDID")
        return f"{self.name} (screen {self.screen}): {self.width}x{self.height}{rate} at +{self.x}+{self.y}, {monitor}"


def xlib() -> Any:
    """python-xlib's `Xlib` package; DeviceError saying what to install when it is missing."""
    try:
        import Xlib.display
        import Xlib.error
        import Xlib.ext.randr  # noqa: F401 - registers the RandR requests on Display
    except ImportError:
        raise DeviceError(f"desktop displays need python-xlib: {INSTALL_HINT}") from None
    return Xlib


def connect(name: str | None) -> Any:
    """An Xlib Display for `name` (None: $DISPLAY); DeviceError when there is none to connect to."""
    module = xlib()
    display_name = name or os.environ.get("DISPLAY")
    if not display_name:
        raise DeviceError("no X display: set $DISPLAY or slm.x_display (desktop displays need an X11 session; on "
                          "Wayland, XWayland outputs carry no EDID)")
    try:
        display = module.display.Display(display_name)
    except Exception as exc:  # python-xlib raises several unrelated classes for an unreachable display
        raise DeviceError(f"cannot connect to X display {display_name!r}: {exc}") from None
    # python-xlib's RandR module registers its errors at codes 0-2 instead of above its error base, over the core
    # BadRequest and BadValue, with classes it then fails to parse (AttributeError): this connection gets the core
    # table back (RandR's own errors are then plain XErrors).
    display.display.error_classes = dict(module.error.xerror_class)
    return display


def desktop_outputs(display: Any) -> list[DesktopOutput]:
    """The connected outputs with an active mode on every screen of `display` (an open Xlib Display)."""
    from Xlib import X

    if not display.has_extension("RANDR"):
        raise DeviceError(f"X display {display.get_display_name()} has no RandR extension: outputs cannot be read")
    edid_atom = display.intern_atom("EDID")
    found = []
    for screen in range(display.screen_count()):
        resources = display.screen(screen).root.xrandr_get_screen_resources()
        modes = {mode.id: mode for mode in resources.modes}
        for output in resources.outputs:
            info = display.xrandr_get_output_info(output, resources.config_timestamp)
            if info.connection != 0 or not info.crtc:  # 0: RR_Connected
                continue
            crtc = display.xrandr_get_crtc_info(info.crtc, resources.config_timestamp)
            mode = modes.get(crtc.mode)
            rate = mode.dot_clock / (mode.h_total * mode.v_total) if mode and mode.h_total and mode.v_total else None
            value = display.xrandr_get_output_property(output, edid_atom, X.AnyPropertyType, 0, 256)._data["value"]
            edid, edid_error = _edid(bytes(value)) if value else (None, None)
            found.append(DesktopOutput(display.get_display_name(), screen, info.name, crtc.x, crtc.y, crtc.width,
                                       crtc.height, rate, info.crtc, edid, edid_error))
    return found


def _edid(data: bytes) -> tuple[Edid | None, str | None]:
    """(the parsed EDID, None), or (None, why it cannot be parsed)."""
    try:
        return parse_edid(data), None
    except DeviceError as exc:
        return None, str(exc)
