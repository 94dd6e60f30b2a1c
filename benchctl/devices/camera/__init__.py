"""Cameras that capture RAW frames: the `Camera` interface and its drivers (benchctl.drivers lists them).

`open_camera(profile)` builds the driver the profile's [camera] section names (`camera_for`) and opens it:

    with open_camera(profile) as camera:
        frames = camera.capture(Path("raw"), frames=3)
"""

from __future__ import annotations

from benchctl.devices.camera.base import RAW_FORMATS, Camera, FrameSize, RawFrame
from benchctl.drivers import driver_class
from benchctl.profiles import Profile

__all__ = ["RAW_FORMATS", "Camera", "FrameSize", "RawFrame", "camera_for", "frame_size", "open_camera"]


def camera_for(profile: Profile) -> Camera:
    """The profile's camera driver, not yet connected: enough to ask what it knows without the device."""
    driver: type[Camera] = driver_class("camera", profile.section("camera").driver)
    return driver.for_profile(profile)


def open_camera(profile: Profile) -> Camera:
    """The profile's camera, opened (use it as a context manager so it is closed again)."""
    return camera_for(profile).open()


def frame_size(profile: Profile) -> FrameSize:
    """One RAW frame of the profile's camera (the simulated camera where it has no [camera] section) as its driver
    expects it without the device: pixels, file bytes, seconds per capture (estimates of time, disk and memory)."""
    driver: type[Camera] = driver_class("camera", profile.camera.driver if profile.camera else "sim")
    return driver.frame_size(profile)
