"""What a learned checkpoint's own record says about using it here (`benchctl models`): whether its validation
beat the classical reference (DPAC on the same images) and whether it was trained through the lookup tables and the
fitted optical model the profile's bench now has.

Training optimises the phase the network outputs, never quantised through a panel's lookup table (a measured table
can leave phases out: red on a panel whose stroke is 2 pi at a shorter wavelength), so a checkpoint meets the
measured tables only at inference; the fitted optical model it was trained through, if any, is in its record.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from benchctl.profiles import Profile

VALIDATION = "val_psnr_amplitude_db"
DPAC_VALIDATION = "val_dpac_psnr_amplitude_db"


def checkpoint_notes(record: Mapping[str, Any], profile: Profile) -> list[str]:
    """Notes on a checkpoint's record (`Checkpoint.metadata()`) for `profile` as calibration applies it: below
    DPAC on its validation images (per colour), DPAC's figure not recorded, trained without the measured lookup
    tables the panel now shows its colours through, or with another optical model than the profile's."""
    colours = record.get("colours", {})
    below, unknown = [], []
    for colour, entry in colours.items():
        metrics = entry.get("metrics", {})
        if VALIDATION not in metrics or DPAC_VALIDATION not in metrics:
            unknown.append(colour)
        elif metrics[VALIDATION] < metrics[DPAC_VALIDATION]:
            below.append(f"{colour} {metrics[VALIDATION]:.2f} < {metrics[DPAC_VALIDATION]:.2f} dB")
    notes = []
    if below:
        notes.append(f"BELOW DPAC on its validation images ({', '.join(below)}): not worth using yet")
    if unknown:
        notes.append(f"no validation against DPAC recorded for {', '.join(unknown)}")
    luts = profile.slm.lut if profile.slm is not None else {}
    tabled = [colour for colour in colours if colour in luts]
    if tabled:
        notes.append(f"trained on the ideal phase; the panel now shows {', '.join(tabled)} through lookup tables it "
                     "was not trained through")
    trained_model = record.get("training", {}).get("optical_model")
    has_model = profile.optics is not None and profile.optics.model is not None
    if has_model and not trained_model:
        notes.append("trained on the ideal optical model; the profile now has a fitted one (fine-tune with "
                     "`benchctl train ... --model-calibration stored --resume`)")
    elif trained_model and not has_model:
        notes.append("trained through a fitted optical model; the profile now has none")
    return notes
