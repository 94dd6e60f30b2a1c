"""The `eos` focus driver: the Canon EOS body's own lens, driven over PTP with DriveLens (0x9155) in live view.

A step is one DriveLens of the profile's `drive_size` (Far: +1, Near: -1). The body answers OK even when the lens
ignored a drive (at an end stop, or busy), so the position is counted: `home` drives Near by the large step
`home_drives` times, surely into the near end stop, which is position 0 from then on; every later step adds its
sign. Steps are neither equal in size nor free of backlash: the focus calibration measures both.

The lens belongs to the camera: a run drives it through the run's open camera (`on_camera`); a command that opens
the focus alone (`benchctl focus ...`) opens the camera for itself and holds it until it closes.
"""

from __future__ import annotations

from benchctl.devices.camera.ptp_camera import PtpCamera
from benchctl.devices.errors import DeviceError
from benchctl.devices.focus.base import Focus
from benchctl.devices.lock import DeviceLock
from benchctl.profiles import FocusConfig, Profile

HOME_SIZE = 3  # the large step: the quickest way into the end stop


class EosFocus(Focus):
    """The lens of a `ptp` camera; see the module docstring."""

    driver = "eos"
    unit = "drive"

    def __init__(self, config: FocusConfig, camera: PtpCamera, owns_camera: bool) -> None:
        super().__init__(config)
        self.camera = camera
        self._owns_camera = owns_camera

    @classmethod
    def for_profile(cls, profile: Profile) -> EosFocus:
        """The lens of the profile's camera, which the focus opens and closes itself."""
        camera = PtpCamera.for_profile(profile)
        return cls(profile.section("focus"), camera, owns_camera=True)

    @classmethod
    def on_camera(cls, config: FocusConfig, camera: PtpCamera) -> EosFocus:
        """The lens of `camera`, which its owner keeps open (a run's camera)."""
        return cls(config, camera, owns_camera=False)

    def _device_lock(self) -> DeviceLock:
        usb_id = self.camera.config.usb_id
        return DeviceLock(f"focus:eos:{usb_id}", f"lens focus (EOS {usb_id})")

    def _open(self) -> None:
        if self._owns_camera:
            self.camera.open()
        elif not self.camera.is_open:
            raise DeviceError("EOS lens focus: the camera that drives it is not open")

    def _close(self) -> None:
        if self._owns_camera:
            self.camera.close()

    def _identity(self) -> dict[str, str]:
        return {"body": self.camera.identity().get("model", "?"), "drive size": str(self.config.drive_size)}

    def _drive(self, steps: int) -> int | None:
        for _ in range(abs(steps)):
            self.camera.drive_lens(steps > 0, self.config.drive_size)
        return None

    def ground_truth(self) -> dict[str, float] | None:
        """The simulated body's lens, in drives of the profile's size."""
        if self.camera.config.transport != "sim":
            return None
        from benchctl.devices.sim.eos_usb import DRIVE_STEPS
        from benchctl.devices.sim.focus_mechanics import Mechanism

        mechanism, per_drive = Mechanism(), DRIVE_STEPS[self.config.drive_size]
        return {"true_steps": mechanism.true_steps / per_drive,
                "backlash_steps": mechanism.config.backlash_steps / per_drive}

    def _home(self) -> None:
        for _ in range(self.config.home_drives):
            self.camera.drive_lens(False, HOME_SIZE)
