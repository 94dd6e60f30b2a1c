"""Optical setups: each laser channel's `OpticalSetup`, built from the profile (its geometry) and the calibration
(the fitted optical model the profile carries), once, and handed to everything that computes or scores a hologram.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

from benchctl.devices.slm import SLM
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile


@functools.lru_cache(maxsize=6)
def _shared(setup: OpticalSetup) -> OpticalSetup:
    """The first setup equal to `setup`: its transfer functions are computed once, not once per caller."""
    return setup


def optical_setups(profile: Profile, channels: Sequence[str] | None = None) -> dict[str, OpticalSetup]:
    """The optical setup of each named laser channel of `profile` (all of them by default)."""
    names = list(channels) if channels is not None else [channel.name for channel in profile.channels]
    return {name: _shared(OpticalSetup.from_profile(profile, name)) for name in names}


def optimised_setup(setup: OpticalSetup, slm: SLM, channel: str) -> OpticalSetup:
    """`setup` as optimisers see it: through what `slm` drives where its table leaves phases out, or always when
    the fitted model has crosstalk (which blurs the driven phase's jumps)."""
    crosstalk = setup.field_model is not None and setup.field_model.has_crosstalk
    return setup.with_display(slm.display_model(channel, always=crosstalk))
