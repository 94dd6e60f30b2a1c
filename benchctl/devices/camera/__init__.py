"""Cameras that capture RAW frames: the `Camera` interface and its drivers (ptp, gphoto2, simulated).

`open_camera(profile)` builds the driver the profile's [camera] section names (`camera_for`) and opens it:

    with open_camera(profile) as camera:
        frames = camera.capture(Path("raw"), frames=3)
"""

from __future__ import annotations

from benchctl.devices.camera.base import RAW_FORMATS, Camera, RawFrame
from benchctl.profiles import Profile

__all__ = ["RAW_FORMATS", "Camera", "RawFrame", "camera_for", "open_camera"]


def camera_for(profile: Profile) -> Camera:
    """The profile's camera driver, not yet connected: enough to ask what it knows without the device.
    `ptp` with transport "sim" talks PTP to the simulated EOS body, which delivers what the simulated bench
    renders."""
    config = profile.require("camera").camera
    assert config is not None
    if config.driver == "sim":
        from benchctl.devices.camera.sim import SimCamera

        return SimCamera(config, profile)
    if config.driver == "gphoto2":
        from benchctl.devices.camera.gphoto2 import Gphoto2Camera

        return Gphoto2Camera(config)
    from benchctl.devices.camera.ptp_camera import PtpCamera

    if config.transport != "sim":
        return PtpCamera(config)
    from benchctl.devices.camera.base import PREVIEW_WIDTH
    from benchctl.devices.sim.bench import LiveView, render_capture
    from benchctl.devices.sim.eos_usb import SimEosTransport

    def image_source() -> tuple[bytes, str]:
        frame = render_capture(profile, exposure_s=config.exposure_s, iso=config.iso)
        return frame.data, frame.file_name

    view = LiveView(profile)
    return PtpCamera(config, SimEosTransport(image_source, live_view=lambda: view.jpeg(
        PREVIEW_WIDTH, exposure_s=config.exposure_s, iso=config.iso)))


def open_camera(profile: Profile) -> Camera:
    """The profile's camera, opened (use it as a context manager so it is closed again)."""
    return camera_for(profile).open()
