"""Cameras that capture RAW frames: the `Camera` interface and its drivers (ptp, gphoto2, simulated)."""

from benchctl.devices.camera.base import RAW_FORMATS, Camera, RawFrame

__all__ = ["RAW_FORMATS", "Camera", "RawFrame"]
