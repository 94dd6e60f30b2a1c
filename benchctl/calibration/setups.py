"""Optical setups: each laser channel's `OpticalSetup`, built from the profile (its geometry, `Profile.geometry`)
and the calibration (the fitted optical model the profile carries in `optics.model`), once, and handed to
everything that computes or scores a hologram. The one place that reads fitted optical models.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

from benchctl.calibration.files import fitted_model_entry
from benchctl.devices.slm import SLM
from benchctl.optics.fitted import FittedOptics
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile


def fitted_model(profile: Profile, channel: str) -> FittedOptics | None:
    """`channel`'s fitted optical model from the file the profile names (`optics.model`), checked
    (benchctl.calibration.files: one line naming file, key and value for a bad one); None without one."""
    entry = fitted_model_entry(profile, channel)
    return FittedOptics.from_dict(entry) if entry is not None else None


@functools.lru_cache(maxsize=3)
def _shared(setup: OpticalSetup) -> OpticalSetup:
    """The first setup equal to `setup`: its transfer functions are computed once, not once per caller."""
    return setup


def optical_setups(profile: Profile, channels: Sequence[str] | None = None) -> dict[str, OpticalSetup]:
    """The optical setup of each named laser channel of `profile` (all of them by default): its geometry, lit
    through the channel's fitted model where the profile names an optical model."""
    names = list(channels) if channels is not None else [channel.name for channel in profile.channels]
    return {name: _shared(OpticalSetup.of(profile.geometry(name), fitted_model(profile, name))) for name in names}


def optical_setup(profile: Profile, channel: str) -> OpticalSetup:
    """The optical setup of laser channel `channel` of `profile` (`optical_setups` of one)."""
    return optical_setups(profile, [channel])[channel]


def optimised_setup(setup: OpticalSetup, slm: SLM, channel: str) -> OpticalSetup:
    """`setup` as optimisers see it: through what `slm` drives where its table leaves phases out, or always when
    the fitted model has crosstalk (which blurs the driven phase's jumps)."""
    crosstalk = setup.field_model is not None and setup.field_model.has_crosstalk
    return setup.with_display(slm.display_model(channel, always=crosstalk))
