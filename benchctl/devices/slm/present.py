"""The X11 Present extension through python-xlib: a pixmap shown on a window at a vertical blank of one CRTC, and the
time of that vblank as the X server reports it.

python-xlib has no module for Present, so the three requests and the one event used here are declared from the
protocol (presentproto 1.2): QueryVersion (0), Pixmap (1), SelectInput (3) and CompleteNotify (a Generic Event,
evtype 1: kind, mode, event id, window, serial, ust, msc). The server copies (or flips) the pixmap into the window
at the vblank and then sends CompleteNotify with `ust`, the vblank's time in microseconds on the server's
CLOCK_MONOTONIC (the kernel's vblank timestamp under a DRM driver; Xvfb runs a fake 60 Hz vblank). The pixels are
the pixmap's, copied as they are: no scaling or filtering. The event's mode says "skipped" only when a later
request for the same window overtook this one, which waiting for each completion rules out.

python-xlib's own GEQueryVersion sends 32-bit version fields where the protocol has 16-bit ones (the server
answers BadLength); it is not needed: servers deliver generic events without it.
"""

from __future__ import annotations

import select
import time
from collections.abc import Callable
from typing import Any

from Xlib.protocol import rq

from benchctl.devices.errors import DeviceError

EXTENSION = "Present"
_COMPLETE_NOTIFY = 1  # evtype of CompleteNotify
_COMPLETE_MASK = 2  # PresentCompleteNotifyMask
_GENERIC_EVENT = 35


class _Card64(rq.ValueField):
    structcode = "Q"  # rq packs in native order, as X clients send (the byte-order byte says which)
    structvalues = 1


class _QueryVersion(rq.ReplyRequest):
    _request = rq.Struct(rq.Card8("opcode"), rq.Opcode(0), rq.RequestLength(), rq.Card32("major_version"),
                         rq.Card32("minor_version"))
    _reply = rq.Struct(rq.ReplyCode(), rq.Pad(1), rq.Card16("sequence_number"), rq.ReplyLength(),
                       rq.Card32("major_version"), rq.Card32("minor_version"), rq.Pad(16))


class _PresentPixmap(rq.Request):
    _request = rq.Struct(rq.Card8("opcode"), rq.Opcode(1), rq.RequestLength(), rq.Window("window"),
                         rq.Pixmap("pixmap"), rq.Card32("serial"), rq.Card32("valid"), rq.Card32("update"),
                         rq.Int16("x_off"), rq.Int16("y_off"), rq.Card32("target_crtc"), rq.Card32("wait_fence"),
                         rq.Card32("idle_fence"), rq.Card32("options"), rq.Pad(4), _Card64("target_msc"),
                         _Card64("divisor"), _Card64("remainder"))


class _SelectInput(rq.Request):
    _request = rq.Struct(rq.Card8("opcode"), rq.Opcode(3), rq.RequestLength(), rq.Card32("event_id"),
                         rq.Window("window"), rq.Card32("event_mask"))


_COMPLETE = rq.Struct(rq.Card8("kind"), rq.Card8("mode"), rq.Card32("event_id"), rq.Card32("window"),
                      rq.Card32("serial"), _Card64("ust"), _Card64("msc"))


class Presenter:
    """Presents pixmaps on `window` at the vblanks of `crtc` and waits for each to complete."""

    def __init__(self, display: Any, window: Any, crtc: int, opcode: int) -> None:
        self._display, self._window, self._crtc, self._opcode = display, window, crtc, opcode
        self._serial = 0
        display.ge_add_event_data(opcode, _COMPLETE_NOTIFY, _COMPLETE)
        _SelectInput(display=display.display, opcode=opcode, event_id=display.display.allocate_resource_id(),
                     window=window, event_mask=_COMPLETE_MASK)

    @classmethod
    def on(cls, display: Any, window: Any, crtc: int) -> Presenter | None:
        """A Presenter for `window`, or None when the X server has no Present extension. (A server with Present
        has the Generic Event extension its notifications travel in, which python-xlib then loads.)"""
        info = display.query_extension(EXTENSION)
        if info is None:
            return None
        _QueryVersion(display=display.display, opcode=info.major_opcode, major_version=1, minor_version=2)
        return cls(display, window, crtc, info.major_opcode)

    def present(self, pixmap: Any, timeout_s: float, check_errors: Callable[[], None]) -> int:
        """Show `pixmap` (the window's size and depth) at the next vblank; that vblank's `ust` (microseconds) once
        the server says. DeviceError when none comes within `timeout_s` (an output switched off has no vblanks);
        a late notification of that frame is then passed over. `check_errors` raises for an X error the server
        reported meanwhile (a refused request never completes)."""
        self._serial = self._serial % 0xFFFFFFFF + 1
        _PresentPixmap(display=self._display.display, opcode=self._opcode, window=self._window, pixmap=pixmap,
                       serial=self._serial, valid=0, update=0, x_off=0, y_off=0, target_crtc=self._crtc,
                       wait_fence=0, idle_fence=0, options=0, target_msc=0, divisor=0, remainder=0)
        self._display.flush()
        deadline = time.monotonic() + timeout_s
        while True:
            while self._display.pending_events():
                check_errors()
                event = self._display.next_event()
                if (event.type == _GENERIC_EVENT and event.extension == self._opcode
                        and event.evtype == _COMPLETE_NOTIFY and event.data.serial == self._serial):
                    ust: int = event.data.ust
                    return ust
            check_errors()
            left = deadline - time.monotonic()
            if left <= 0:
                raise DeviceError(f"the X server did not complete presenting frame {self._serial} within "
                                  f"{timeout_s:g} s: is the output switched off or in power saving?")
            select.select([self._display], [], [], left)
