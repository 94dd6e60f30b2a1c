"""One registration mechanism for every device kind: the profile accepts exactly the drivers benchctl.drivers lists,
and every listed name builds a driver of its kind."""

from __future__ import annotations

import msgspec
import pytest

from benchctl.devices.camera import Camera
from benchctl.devices.focus import Focus
from benchctl.devices.laser import Laser
from benchctl.devices.slm import SLM
from benchctl.drivers import DRIVERS, driver_class, driver_names
from benchctl.profiles import CameraConfig, FocusConfig, LaserConfig, SLMConfig

BASES = {"laser": Laser, "slm": SLM, "camera": Camera, "focus": Focus}
CONFIGS = {"laser": LaserConfig, "slm": SLMConfig, "camera": CameraConfig, "focus": FocusConfig}


@pytest.mark.parametrize("kind", sorted(DRIVERS))
def test_every_listed_driver_is_a_driver_of_its_kind_with_its_own_name(kind: str) -> None:
    for name in driver_names(kind):  # type: ignore[arg-type]
        cls = driver_class(kind, name)  # type: ignore[arg-type]
        assert issubclass(cls, BASES[kind]), (kind, name)
        if kind != "laser":  # laser drivers are named by the registry alone
            assert cls.driver == name, (kind, name)


def _driver_refused(kind: str, name: str) -> bool:
    """Whether a [kind] section naming driver `name` is refused for that name (other keys left out may be missing:
    msgspec reads `driver` before it finds a required key absent)."""
    try:
        msgspec.convert({"driver": name}, CONFIGS[kind])
    except msgspec.ValidationError as exc:
        return "$.driver" in str(exc)
    return False


@pytest.mark.parametrize("kind", sorted(DRIVERS))
def test_the_profile_accepts_exactly_the_listed_drivers(kind: str) -> None:
    assert not any(_driver_refused(kind, name) for name in driver_names(kind))  # type: ignore[arg-type]
    assert _driver_refused(kind, "no-such-driver") and _driver_refused(kind, driver_names("laser" if kind != "laser"
                                                                                         else "slm")[0])


def test_the_genicam_and_hdmi_example_profile_chooses_those_drivers() -> None:
    from benchctl.devices.camera import camera_for
    from benchctl.devices.camera.genicam import GenicamCamera
    from benchctl.devices.slm.display import DisplaySLM
    from benchctl.profiles import load_profile

    profile = load_profile("genicam_hdmi")
    assert isinstance(camera_for(profile), GenicamCamera)
    assert isinstance(driver_class("slm", profile.slm.driver).for_profile(profile), DisplaySLM)  # type: ignore[union-attr]
