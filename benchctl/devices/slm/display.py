"""The `display` SLM driver: an HDMI / DisplayPort SLM that is a monitor of the X11 desktop.

The output is chosen by what the profile names: the EDID's monitor name (`slm.edid_name`) and serial
(`slm.edid_serial`), which survive re-plugging, or the connector (`slm.output`, e.g. HDMI-A-1). Its mode must be
the profile's width x height (else the error names every output and mode there is). A borderless window
(override-redirect: no window manager moves, decorates or scales it) covers exactly that output. Each gray frame
is written with XPutImage, in the pixel format of the screen's visual (every channel carries the gray level in its
top bits: depth 24 and 30 both show 8-bit gray exactly, depth 30 also 10-bit; a depth that cannot, such as 16, is
refused at open: benchctl.devices.slm.x_pixels), into an off-screen pixmap, which the X11 Present extension puts on
the window at the output's next vertical blank (vsync: no frame is seen half written); the X server then reports
that vblank's time (`ust`) and frame count (`msc`), and that time is the frame's presentation time, from which the
settle time counts (benchctl.devices.slm.present). No scaling,
filtering, dithering or colour management is on this path, and the output's CRTC gamma ramp must be the identity
(checked at open). A server without Present (rare: X.Org has had it since 1.15, Xvfb included) gets the frame
straight into the window with no vsync, and the frame counts as presented when XSync returned; `slm info` and the
run's devices.json say which (`presentation`).

X errors are caught synchronously: the X server reports a refused request (BadMatch, BadAlloc, ...) after the fact,
so each frame's requests are followed by a round trip and the errors reported meanwhile end the frame with one line,
before it is counted as presented. An X server that went away (stopped, restarted) ends the frame with one line too;
the next frame connects again and puts a new window on the output, or says in one line why it cannot.

Under a compositing window manager the window is redirected: Present's time is when the frame reached the window,
and the compositor puts it on the panel at one of its next repaints. The window asks to bypass compositing
(_NET_WM_BYPASS_COMPOSITOR, honoured by KWin, Mutter and picom); without a compositor on the SLM's output the time
is the panel's.

Why python-xlib rather than pyglet, SDL2 or GLFW: those draw through OpenGL (a texture sampled onto the window),
where exact gray levels depend on the driver's filtering and dithering settings, and none of them reports a
monitor's EDID, so the output would still have to be found through RandR. XPutImage writes the bytes themselves,
needs no GPU (Xvfb runs it unchanged) and the tests read the same pixels back with XGetImage; Present gives the
vsync and the timestamp the GL toolkits would (GLX_OML_sync_control), without GL. On Wayland, use the framebuffer
driver or an X11 session.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from benchctl.devices.errors import DeviceError
from benchctl.devices.lock import DeviceLock
from benchctl.devices.slm.base import SLM
from benchctl.devices.slm.desktop import DesktopOutput, connect, desktop_outputs
from benchctl.devices.slm.x_pixels import PixelLayout
from benchctl.profiles import SLMConfig

_GAMMA_TOLERANCE = 256  # one 8-bit step in the 16-bit gamma ramp
PRESENT_TIMEOUT_S = 2.0  # longest wait for a vblank (an output in power saving has none)


class DisplaySLM(SLM):
    """An SLM shown in a borderless window on one output of the X11 desktop (see module docstring)."""

    driver = "display"

    def __init__(self, config: SLMConfig, channels: Sequence[str] = ()) -> None:
        super().__init__(config, channels)
        self.output: DesktopOutput | None = None
        self._x: Any = None  # the X connection; None while open only after the X server went away
        self._window: Any = None
        self._gc: Any = None
        self._presenter: Any = None  # a present.Presenter, None where the X server has no Present extension
        self._layout: PixelLayout | None = None
        self._errors: list[Any] = []  # X errors the server reported and no frame has raised yet

    def _wanted(self) -> str:
        keys = {"edid_name": self.config.edid_name, "edid_serial": self.config.edid_serial,
                "output": self.config.output}
        return ", ".join(f"slm.{key} = {value!r}" for key, value in keys.items() if value is not None)

    def _device_lock(self) -> DeviceLock:
        return DeviceLock(f"slm:display:{self.config.x_display}:{self._wanted()}", self.label)

    @property
    def label(self) -> str:
        return f"SLM (display {self._wanted() or 'unnamed output'})"

    def _open(self) -> None:
        self._connect()

    def _connect(self) -> None:
        """Connect to the X display, find the profile's output, check it and cover it with the window."""
        self._x = connect(self.config.x_display)
        try:
            self._x.set_error_handler(lambda error, request: self._errors.append(error))
            self.output = self._choose(desktop_outputs(self._x))
            self._layout = PixelLayout.of_screen(self._x, self.output.screen)
            self._layout.check(self.bit_depth, f"{self.output.name} (screen {self.output.screen} of X display "
                                               f"{self._x.get_display_name()})")
            self._check_gamma(self.output)
            self._create_window(self.output)
        except BaseException:
            self._close()
            raise

    def _choose(self, outputs: list[DesktopOutput]) -> DesktopOutput:
        """The one output the profile names. An output whose EDID cannot be read is passed over unless it is the
        only candidate for an EDID the profile names: then which output is the SLM cannot be told."""
        config = self.config
        by_edid = config.edid_name is not None or config.edid_serial is not None
        named = [o for o in outputs if config.output is None or o.name == config.output]
        matching = [o for o in named
                    if (config.edid_name is None or (o.edid is not None and o.edid.name == config.edid_name))
                    and (config.edid_serial is None or (o.edid is not None and o.edid.serial == config.edid_serial))]
        there = "; ".join(o.describe() for o in outputs) or "none"
        unreadable = [o for o in named if o.edid_error is not None] if by_edid else []
        if not matching and unreadable:
            names = ", ".join(f"{o.name} (screen {o.screen})" for o in unreadable)
            raise DeviceError(f"no output of X display {self._x.get_display_name()} matches {self._wanted()}, and the "
                              f"EDID of {names} cannot be read: if that is the SLM, name it by connector (slm.output) "
                              f"(outputs: {there})")
        if len(matching) != 1:
            many = "no output" if not matching else f"{len(matching)} outputs"
            raise DeviceError(f"{many} of X display {self._x.get_display_name()} match {self._wanted()} "
                              f"(outputs: {there})")
        chosen = matching[0]
        if (chosen.height, chosen.width) != self.shape:
            raise DeviceError(f"{chosen.name} shows {chosen.width}x{chosen.height} but the profile says slm.width x "
                              f"slm.height = {self.config.width}x{self.config.height}; set the output's mode (xrandr) "
                              f"or fix the profile (outputs: {there})")
        return chosen

    def _check_gamma(self, output: DesktopOutput) -> None:
        """The CRTC's gamma ramp must be the identity, else the panel would not get the gray levels sent. A ramp
        of zeros is a virtual output's (Xvfb reports one): it has no gamma stage."""
        gamma = self._x.xrandr_get_crtc_gamma(output.crtc)
        for name in ("red", "green", "blue"):
            ramp = np.asarray(getattr(gamma, name), dtype=np.int64)
            if ramp.size > 1 and ramp.any():
                identity = np.round(np.arange(ramp.size) * 65535 / (ramp.size - 1))
                if np.abs(ramp - identity).max() > _GAMMA_TOLERANCE:
                    raise DeviceError(f"{output.name}: its {name} gamma ramp is not the identity, so the panel would "
                                      f"not get the gray levels sent: `xrandr --output {output.name} --gamma 1:1:1` "
                                      f"and turn off night-light / colour management for it")

    def _create_window(self, output: DesktopOutput) -> None:
        from Xlib import X, Xatom

        from benchctl.devices.slm.present import Presenter

        screen = self._x.screen(output.screen)
        self._window = screen.root.create_window(
            output.x, output.y, output.width, output.height, 0, screen.root_depth, X.InputOutput,
            X.CopyFromParent, override_redirect=True, background_pixel=screen.black_pixel, event_mask=0)
        self._window.set_wm_name("benchctl SLM")
        self._window.change_property(self._x.intern_atom("_NET_WM_BYPASS_COMPOSITOR"), Xatom.CARDINAL, 32, [1])
        self._window.map()
        self._gc = self._window.create_gc()
        self._presenter = Presenter.on(self._x, self._window, output.crtc)
        self._x.sync()
        self._raise_errors("the SLM's window")
        self._current = np.zeros(self.shape, self.gray_dtype)  # a new window shows its black background

    @property
    def presentation(self) -> str:
        """How frames reach the panel and what their presentation time is (for `slm info` and run records)."""
        if self._presenter is not None:
            return "X11 Present: vsync'd, presented_at = the vblank's time (ust) the X server reports"
        return "XPutImage into the window: no Present extension, no vsync; presented_at = when XSync returned"

    def info(self) -> dict[str, Any]:
        details = {"output": self.output.describe() if self.output else None,
                   "pixels": self._layout.describe() if self._layout else None}
        return {**super().info(), **details, "presentation": self.presentation if self.is_open else None}

    def _close(self) -> None:
        if self._x is not None:
            try:
                if self._window is not None:
                    self._window.destroy()
                self._x.close()
            except Exception:  # noqa: BLE001 - the X server may be gone; nothing left to release on its side
                pass
        self._x = self._window = self._gc = self._presenter = self._layout = None
        self._errors.clear()

    def _raise_errors(self, what: str) -> None:
        """DeviceError for the first X error reported since the last call (the others are its consequences)."""
        if self._errors:
            error, self._errors[:] = self._errors[0], []
            raise DeviceError(f"the X server refused {what}: {type(error).__name__} (request opcode "
                              f"{error.major_opcode}.{error.minor_opcode})")

    def _display(self, gray: np.ndarray, channel: str | None) -> float | None:
        """Show `gray` (see `_present`); after the X server went away, connect again first (once per frame)."""
        from Xlib.error import ConnectionClosedError

        lost = self._x is None
        for _ in range(2):
            try:
                if self._x is None:
                    self._connect()
                return self._present(gray)
            except ConnectionClosedError as exc:
                self._close()
                lost, reason = True, str(exc)
            except DeviceError as exc:
                if lost:
                    reason = str(exc)
                    break
                raise DeviceError(f"{self.label}: {exc}") from None
        raise DeviceError(f"{self.label}: lost its X display {self.config.x_display or '$DISPLAY'} (X server stopped "
                          f"or restarted?) and could not show the frame on it again: {reason}")

    def _present(self, gray: np.ndarray) -> float | None:
        """Write `gray` into a pixmap and present it at the next vblank: the vblank's time (time.monotonic()'s
        clock), or None without Present (the frame went straight into the window; XSync returned). DeviceError for
        an X error any of its requests caused."""
        assert self.output is not None and self._layout is not None
        image = self._layout.image(gray, self.bit_depth)
        if self._presenter is None:
            self._put(self._window, image)
            self._x.sync()
            self._raise_errors("the frame")
            return None
        pixmap = self._window.create_pixmap(self.output.width, self.output.height, self._layout.depth)
        try:
            self._put(pixmap, image)
            self._x.sync()
            self._raise_errors("the frame's pixels")
            requested = time.monotonic()
            ust_us = self._presenter.present(pixmap, PRESENT_TIMEOUT_S, lambda: self._raise_errors("presenting it"))
        except DeviceError:
            pixmap.free()
            self._x.sync()
            self._errors.clear()  # what the refused frame's own clean-up caused (freeing a pixmap never made)
            raise
        pixmap.free()
        return presented_time(ust_us, requested, time.monotonic())

    def _put(self, drawable: Any, image: np.ndarray) -> None:
        """A ZPixmap `image` (rows of pixel bytes) into `drawable`, in requests within the server's size limit."""
        from Xlib import X

        assert self.output is not None and self._layout is not None
        rows_per_request = max(1, (4 * self._x.display.info.max_request_length - 64) // image.shape[1])
        for top in range(0, image.shape[0], rows_per_request):
            rows = image[top:top + rows_per_request]
            drawable.put_image(self._gc, 0, top, self.output.width, rows.shape[0], X.ZPixmap, self._layout.depth, 0,
                               rows.tobytes())


def presented_time(ust_us: int, requested: float, received: float) -> float | None:
    """The presentation time on time.monotonic()'s clock from a Present `ust` (microseconds on the X server's
    CLOCK_MONOTONIC, which is this machine's when the server is local); None when it does not fall between the
    request and the notification's arrival (a remote display, another clock): then the arrival counts."""
    presented = ust_us * 1e-6
    return presented if requested <= presented <= received else None
