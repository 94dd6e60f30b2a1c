"""The bench as calibrated: a profile with what was measured about its bench applied, built once and passed to
everything that computes, displays or scores a hologram instead of a bare profile.

It holds the profile in effect (the measured lookup tables for the channels whose table the profile does not name,
the fitted optical model unless the profile names one), one `OpticalSetup` per channel, the SLM as an encoder and the
stored registrations. Building it reads the calibration files once;
a new measurement makes a new one (`recalibrated`).
"""

from __future__ import annotations

import functools
from dataclasses import replace
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import msgspec
import numpy as np

from benchctl.calibration.store import Calibration
from benchctl.capture.focus import FocusMap
from benchctl.devices.slm import SLM, slm_for
from benchctl.profiles import Profile

if TYPE_CHECKING:
    import torch

    from benchctl.optics.setup import OpticalSetup


class Calibrated:
    """`profile` with `calibration` applied (None: the profile as configured, nothing measured: benchmarks and
    training on a grid no bench was calibrated for)."""

    def __init__(self, profile: Profile, calibration: Calibration | None = None, *,
                 distance_m: float | None = None, ideal: bool = False) -> None:
        """`distance_m`: every channel's target plane at that distance from the SLM instead of the profile's (holograms
        focused at another depth, through the same tables and fitted model). `ideal`: without any fitted optical
        model (stored or named by the profile), the lookup tables still applied: what holograms were before model
        calibration, to measure what it buys."""
        self.configured = profile
        self.calibration = calibration
        applied = calibration.applied(profile) if calibration is not None else profile
        if ideal and applied.optics is not None and applied.optics.model is not None:
            applied = msgspec.structs.replace(applied, optics=msgspec.structs.replace(applied.optics, model=None))
        self.profile = applied
        self.distance_m = distance_m
        self.ideal = ideal
        self._setups: dict[str, OpticalSetup] = {}

    @classmethod
    def stored(cls, profile: Profile) -> Calibrated:
        """`profile` with the calibration stored for it (`Calibration.store`)."""
        return cls(profile, Calibration.store(profile))

    def recalibrated(self) -> Calibrated:
        """This bench built again from its calibration's files (after a step stored a new measurement)."""
        return Calibrated(self.configured, self.calibration, distance_m=self.distance_m, ideal=self.ideal)

    def at_distance(self, distance_m: float) -> Calibrated:
        """This bench with every channel's target plane `distance_m` from the SLM."""
        return Calibrated(self.configured, self.calibration, distance_m=distance_m, ideal=self.ideal)

    def without_model(self) -> Calibrated:
        """This bench as if no optical model had been fitted (`ideal`)."""
        return Calibrated(self.configured, self.calibration, distance_m=self.distance_m, ideal=True)

    def setup(self, channel: str, *, as_displayed: bool = False) -> OpticalSetup:
        """`channel`'s optical setup (geometry and fitted model), built once; `as_displayed`: as optimisers see it,
        through what the SLM shows of a phase (`setups.optimised_setup`)."""
        # torch only here: the device commands take their profile from a Calibrated bench and never load it
        from benchctl.calibration.setups import optical_setups, optimised_setup

        if channel not in self._setups:
            setup = optical_setups(self.profile, [channel])[channel]
            self._setups[channel] = setup if self.distance_m is None else replace(setup, distance_m=self.distance_m)
        setup = self._setups[channel]
        return optimised_setup(setup, self.slm, channel) if as_displayed else setup

    def setups(self, channels: Sequence[str] | None = None) -> dict[str, OpticalSetup]:
        """The optical setup of each named channel (all of them by default)."""
        names = list(channels) if channels is not None else [channel.name for channel in self.profile.channels]
        return {name: self.setup(name) for name in names}

    @functools.cached_property
    def slm(self) -> SLM:
        """The profile's SLM as an encoder (phase <-> gray levels as displayed, through the tables in effect): the
        panel itself is not opened."""
        return slm_for(self.profile)

    def encode(self, phase: np.ndarray | torch.Tensor, channel: str) -> np.ndarray:
        """The SLM frame (gray levels) that shows `phase` for `channel`."""
        return self.slm.encode(phase, channel)

    def decode(self, gray: np.ndarray, channel: str) -> np.ndarray:
        """The phase an SLM frame shows for `channel` (the inverse of `encode`, to its gray-level step)."""
        return self.slm.decode(gray, channel)

    @functools.cached_property
    def focus_maps(self) -> dict[str, FocusMap]:
        """Colour -> stored focus calibration (steps <-> depth) valid for this geometry and focus device."""
        stored = self.calibration.focus_maps() if self.calibration is not None else {}
        return {colour: FocusMap.from_dict(entry) for colour, entry in stored.items()}

    @functools.cached_property
    def registrations(self) -> dict[str, dict[str, Any]]:
        """Colour -> stored camera-SLM registration valid for this geometry (empty without a calibration)."""
        return self.calibration.registrations() if self.calibration is not None else {}
