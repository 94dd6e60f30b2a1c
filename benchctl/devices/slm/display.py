"""The `display` SLM driver: an HDMI / DisplayPort SLM that is a monitor of the X11 desktop.

The output is chosen by what the profile names: the EDID's monitor name (`slm.edid_name`) and serial
(`slm.edid_serial`), which survive re-plugging, or the connector (`slm.output`, e.g. HDMI-A-1). Its mode must be
the profile's width x height (else the error names every output and mode there is). A borderless window
(override-redirect: no window manager moves, decorates or scales it) covers exactly that output, and each gray
frame is written into it with XPutImage as 32-bit pixels whose R, G and B bytes are the gray level: no scaling,
filtering, dithering or colour management is on that path, and the output's CRTC gamma ramp must be the
identity (checked at open). A frame counts as presented when the X server has executed the last of its
requests (XSync returned); that moment is recorded and the settle time starts from it.

Why python-xlib rather than pyglet, SDL2 or GLFW: those draw through OpenGL (a texture sampled onto the window),
where exact gray levels depend on the driver's filtering and dithering settings, and none of them reports a
monitor's EDID, so the output would still have to be found through RandR. XPutImage writes the bytes themselves,
needs no GPU (Xvfb runs it unchanged) and the tests read the same pixels back with XGetImage. The price: core X11
has no vsync, so a frame may tear while it is written; `settle_ms` must cover one refresh (16.7 ms at 60 Hz) on
top of the liquid crystal's response. On Wayland, use the framebuffer driver or an X11 session.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from benchctl.devices.errors import DeviceError
from benchctl.devices.lock import DeviceLock
from benchctl.devices.slm.base import SLM
from benchctl.devices.slm.desktop import DesktopOutput, connect, desktop_outputs
from benchctl.profiles import SLMConfig

_GAMMA_TOLERANCE = 256  # one 8-bit step in the 16-bit gamma ramp


class DisplaySLM(SLM):
    """An SLM shown in a borderless window on one output of the X11 desktop (see module docstring)."""

    driver = "display"

    def __init__(self, config: SLMConfig, channels: Sequence[str] = ()) -> None:
        super().__init__(config, channels)
        self.output: DesktopOutput | None = None
        self._x: Any = None
        self._window: Any = None
        self._gc: Any = None
        self._rows_per_request = 1

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
        if self.bit_depth != 8:
            raise DeviceError(f"{self.label}: the display driver shows 8-bit gray (24-bit desktop colour); the "
                              f"profile says slm.bit_depth = {self.bit_depth}")
        self._x = connect(self.config.x_display)
        try:
            self.output = self._choose(desktop_outputs(self._x))
            self._check_gamma(self.output)
            self._create_window(self.output)
        except BaseException:
            self._close()
            raise

    def _choose(self, outputs: list[DesktopOutput]) -> DesktopOutput:
        config = self.config
        matching = [o for o in outputs
                    if (config.output is None or o.name == config.output)
                    and (config.edid_name is None or (o.edid is not None and o.edid.name == config.edid_name))
                    and (config.edid_serial is None or (o.edid is not None and o.edid.serial == config.edid_serial))]
        there = "; ".join(o.describe() for o in outputs) or "none"
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
        from Xlib import X

        screen = self._x.screen(output.screen)
        self._window = screen.root.create_window(
            output.x, output.y, output.width, output.height, 0, screen.root_depth, X.InputOutput,
            X.CopyFromParent, override_redirect=True, background_pixel=screen.black_pixel, event_mask=0)
        self._window.set_wm_name("benchctl SLM")
        self._window.map()
        self._gc = self._window.create_gc()
        request_bytes = 4 * self._x.display.info.max_request_length - 64
        self._rows_per_request = max(1, request_bytes // (4 * output.width))
        self._x.sync()

    def _close(self) -> None:
        if self._x is not None:
            try:
                if self._window is not None:
                    self._window.destroy()
                self._x.close()
            except Exception:  # noqa: BLE001 - the X server may be gone; nothing left to release on its side
                pass
        self._x = self._window = self._gc = None

    def _display(self, gray: np.ndarray, channel: str | None) -> None:
        from Xlib import X

        assert self.output is not None
        pixels = np.repeat(gray[:, :, None], 4, axis=2)  # B, G, R, X bytes of 32-bit pixels (24-bit depth)
        pixels[:, :, 3] = 0
        for top in range(0, gray.shape[0], self._rows_per_request):
            rows = pixels[top:top + self._rows_per_request]
            self._window.put_image(self._gc, 0, top, rows.shape[1], rows.shape[0], X.ZPixmap, 24, 0, rows.tobytes())
        self._x.sync()
