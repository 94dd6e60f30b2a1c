"""Optical setups: each laser channel's `OpticalSetup`, built from the profile (its geometry, `Profile.geometry`)
and the calibration (the fitted optical model the profile carries in `optics.model`), once, and handed to
everything that computes or scores a hologram. The one place that reads fitted optical models.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from pathlib import Path

from benchctl.devices.slm import SLM
from benchctl.optics.fitted import FittedOptics
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile


@functools.lru_cache(maxsize=4)
def _read_models(path: str, mtime_ns: int, size: int) -> dict[str, FittedOptics]:
    data = json.loads(Path(path).read_text())
    return {name: FittedOptics.from_dict(entry) for name, entry in data.get("colours", {}).items()}


def fitted_models(path: Path) -> dict[str, FittedOptics]:
    """Each colour's fitted optical model in an optical-model file (model calibration's optical-model.json), read
    once per version of the file."""
    stat = Path(path).stat()
    return _read_models(str(path), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=3)
def _shared(setup: OpticalSetup) -> OpticalSetup:
    """The first setup equal to `setup`: its transfer functions are computed once, not once per caller."""
    return setup


def optical_setups(profile: Profile, channels: Sequence[str] | None = None) -> dict[str, OpticalSetup]:
    """The optical setup of each named laser channel of `profile` (all of them by default): its geometry, lit
    through the channel's fitted model where the profile names an optical model."""
    names = list(channels) if channels is not None else [channel.name for channel in profile.channels]
    path = profile.optics.model if profile.optics is not None else None
    models = fitted_models(path) if path is not None else {}
    return {name: _shared(OpticalSetup.of(profile.geometry(name), models.get(name))) for name in names}


def optical_setup(profile: Profile, channel: str) -> OpticalSetup:
    """The optical setup of laser channel `channel` of `profile` (`optical_setups` of one)."""
    return optical_setups(profile, [channel])[channel]


def optimised_setup(setup: OpticalSetup, slm: SLM, channel: str) -> OpticalSetup:
    """`setup` as optimisers see it: through what `slm` drives where its table leaves phases out, or always when
    the fitted model has crosstalk (which blurs the driven phase's jumps)."""
    crosstalk = setup.field_model is not None and setup.field_model.has_crosstalk
    return setup.with_display(slm.display_model(channel, always=crosstalk))
