"""The calibration files as typed models, checked like profiles: optical-model.json (model calibration's fit, or a
file the profile names in `[optics] model`), registration.json and the lookup-table index lut.json.

A file is checked where it is read: `checked_json` decodes it with the models below (benchctl.schema: every failure
is one line naming the file, the key path, the value and its allowed range) and returns it as parsed, so a
hand-edited or damaged file is refused before a number of it is used. `check_calibration` checks every
calibration file a run will use (`benchctl profile check`, `benchctl run --dry-run`); `calibration_used` says which
tables and model a result was made with, with checksums (`benchctl generate`'s metrics.json).

Imports no torch (`profile check` must start instantly); the optics package turns a checked entry into a model.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from msgspec import Meta

from benchctl.errors import BenchctlError
from benchctl.files import file_sha256, read_capped
from benchctl.profiles import NonNegative, NonNegativeInt, ZernikeTerm, waist_problem
from benchctl.schema import Model, decode, fail

if TYPE_CHECKING:
    from benchctl.profiles import Profile, SLMConfig

# Above 10 waves (RMS) a wavefront error is a unit slip (nanometres or radians written as waves), not a bench: the
# simulated aberrated bench has 0.4-0.9, and at 10 waves of spherical aberration the phase of a quarter-size grid
# (272 x 480) already changes by more than pi between neighbouring pixels near the panel's corners.
MAX_WAVES = 10.0
# Crosstalk of more than a few pixels (sigma) would blur every hologram's fringes away; fits give 0.03-0.1.
MAX_CROSSTALK_PX = 5.0
# A beam centred further than this many waists (1/e^2 radii) off the panel lights none of it (exp(-2 * 3^2)).
MAX_BEAM_MISS_WAISTS = 3.0

Waves = Annotated[float, Meta(ge=-MAX_WAVES, le=MAX_WAVES)]
# What a calibration was made for (benchctl.calibration.store.geometry): compared as a whole, never read key by key.
Geometry = dict[str, str | int | float | bool | list[int | float | bool] | None]


class Entry(Model, kw_only=True):
    """What every colour's entry of a calibration file records: for which geometry it was made, and when."""

    geometry: Geometry | None = None
    created: str | None = None


class FittedColour(Entry, kw_only=True):
    """One colour of optical-model.json (benchctl.optics.fitted.FittedOptics in profile units, and how it was
    fitted)."""

    zernike_waves: dict[ZernikeTerm, Waves] = {}  # ANSI/OSA RMS-normalised terms, waves
    waist_mm: NonNegative = 0.0  # Gaussian 1/e^2 radius of the beam; 0: uniform illumination
    offset_mm: tuple[float, float] = (0.0, 0.0)  # [rows, cols] from the panel's centre to the beam's centre
    crosstalk_px: Annotated[float, Meta(ge=0, le=MAX_CROSSTALK_PX)] = 0.0  # blur (sigma) of the driven phase
    zero_order: Annotated[float, Meta(ge=0, lt=1)] = 0.0  # amplitude fraction the panel leaves unmodulated
    # written by model calibration, shown in reports
    residual: NonNegative | None = None
    initial_residual: NonNegative | None = None
    held_out_residual: NonNegative | None = None  # on captures the fit did not see
    patterns: NonNegativeInt | None = None
    held_out: NonNegativeInt | None = None
    flat: bool = False
    camera_blur_px: NonNegative = 0.0
    crosstalk_fitted_px: NonNegative | None = None
    focus_depths_mm: list[Annotated[float, Meta(gt=0)]] = []  # the depths each pattern was captured at (none: target)


class OpticalModelFile(Model, kw_only=True):
    """optical-model.json: the fitted model per laser colour."""

    profile: str | None = None
    colours: dict[str, FittedColour]


class StoredRegistration(Entry, kw_only=True):
    """One colour of registration.json (benchctl.capture.registration.Registration.to_dict, and where from)."""

    homography: list[list[float]]  # 3 x 3: target-plane px (x, y, 1) -> camera active-area px
    rms_px: NonNegative  # reprojection error, camera px
    # how the fit went (a homography known otherwise, e.g. a simulator's, comes without them)
    max_px: NonNegative | None = None
    inliers: NonNegativeInt | None = None
    points: NonNegativeInt | None = None
    through_model: bool = False


class RegistrationFile(Model, kw_only=True):
    """registration.json: the camera-SLM registration per laser colour."""

    profile: str | None = None
    colours: dict[str, StoredRegistration]


class LutIndexEntry(Entry, kw_only=True):
    """One colour of lut.json: which table file was measured (in the same folder), from how many gray levels."""

    file: str
    grays: NonNegativeInt | None = None
    run: str | None = None


LutIndex = dict[str, LutIndexEntry]  # lut.json: colour -> its table


class FocusColour(Entry, kw_only=True):
    """One colour of focus.json (benchctl.capture.focus.FocusMap.to_dict, and which focus device it was made with)."""

    focus: str  # the [focus] driver and port it holds for
    coefficients: Annotated[list[float], Meta(min_length=2, max_length=3)]  # depth mm = c0 + c1 s + c2 s^2
    approach: Annotated[int, Meta(ge=-1, le=1)]
    backlash_steps: float
    overshoot_steps: NonNegativeInt
    repeatability_steps: NonNegative | None = None
    range_steps: tuple[float, float]
    residual_mm: NonNegative
    points: list[dict[str, float]] = []
    run: str | None = None


class FocusFile(Model, kw_only=True):
    """focus.json: the focus calibration per laser colour."""

    profile: str | None = None
    unit: str = "step"
    colours: dict[str, FocusColour]


def checked_json(path: Path, model: Any) -> dict[str, Any] | None:
    """The JSON object in the file at `path` as parsed, after checking it against `model` (one of the models
    above; None if there is no file). A BenchctlError names the file, the key and what is wrong."""
    path = Path(path)
    try:
        data = json.loads(read_capped(path, "calibration"))
    except FileNotFoundError:
        return None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BenchctlError(f"{path}: not a JSON calibration file: {exc}") from None
    if not isinstance(data, dict):
        raise fail(path, "(top level)", f"expected a JSON object {{...}}, got {type(data).__name__}")
    decode(data, model, path)
    if model is RegistrationFile:
        for colour, entry in data["colours"].items():
            if [len(row) for row in entry["homography"]] != [3, 3, 3]:
                raise fail(path, f"colours.{colour}.homography", f"expected 3 x 3 numbers, got {entry['homography']}")
    return data


def fitted_model_entry(profile: Profile, channel: str) -> dict[str, Any] | None:
    """`channel`'s entry of the optical model the profile names (`optics.model`), checked, also against the panel;
    None when the profile names no model or the model has no entry for the channel."""
    if profile.optics is None or profile.optics.model is None:
        return None
    path = profile.optics.model
    data = checked_json(path, OpticalModelFile)
    if data is None:
        raise BenchctlError(f"{path}: optical model not found (named by {profile.path} or its calibration)")
    entry = data["colours"].get(channel)
    if entry is not None and profile.slm is not None:
        _check_beam(path, channel, entry, profile.slm)
    return entry


def _check_beam(path: Path, channel: str, entry: dict[str, Any], slm: SLMConfig) -> None:
    """A Gaussian beam must light the panel: at least MIN_WAIST_PX pixels wide, its centre within
    MAX_BEAM_MISS_WAISTS waists of it."""
    waist = float(entry.get("waist_mm", 0.0))
    problem = waist_problem(waist, slm)
    if problem:
        raise fail(path, f"colours.{channel}.waist_mm", problem)
    if not waist:
        return
    half = (slm.height * slm.pitch_um * 5e-4, slm.width * slm.pitch_um * 5e-4)  # mm
    offset = entry.get("offset_mm", (0.0, 0.0))
    miss = math.hypot(*(max(abs(float(o)) - h, 0.0) for o, h in zip(offset, half)))
    if miss > MAX_BEAM_MISS_WAISTS * waist:
        raise fail(path, f"colours.{channel}.offset_mm",
                   f"a beam of waist {waist:g} mm centred at {list(offset)} mm misses the "
                   f"{half[0] * 2:g} x {half[1] * 2:g} mm panel by {miss:g} mm (more than {MAX_BEAM_MISS_WAISTS:g} "
                   "waists): no light would reach it")


def check_calibration(profile: Profile, registration: Path | None = None, focus: Path | None = None) -> list[str]:
    """Check every calibration file a run on `profile` will use: the profile as calibration applies it (its
    `optics.model` and `slm.lut` files, stored ones included), `registration` (a registration.json) and `focus` (a
    focus.json, where the profile has a [focus] device), if given. The first bad file is a BenchctlError naming it,
    the key and the value; otherwise one line per file checked."""
    from benchctl.devices.slm.lut import load_lut  # numpy only

    lines = []
    model = profile.optics.model if profile.optics else None
    if model is not None:
        colours = [c.name for c in profile.channels if fitted_model_entry(profile, c.name) is not None]
        lines.append(f"optical model {model}: {', '.join(colours) or 'no entry for these channels'}")
    if profile.slm is not None:
        for colour, path in profile.slm.lut.items():
            load_lut(path, profile.slm.bit_depth)
            lines.append(f"lookup table {colour}: {path}")
    if registration is not None:
        data = checked_json(registration, RegistrationFile)
        if data is not None:
            lines.append(f"registration {registration}: {', '.join(data['colours']) or 'no colours'}")
    if focus is not None and profile.focus is not None:
        data = checked_json(focus, FocusFile)
        if data is not None:
            lines.append(f"focus {focus}: {', '.join(data['colours']) or 'no colours'}")
    return [f"calibration: {line}: OK" for line in lines]


def calibration_used(profile: Profile, own_tables: Mapping[str, Path]) -> dict[str, Any]:
    """What calibration `profile` (as calibration applies it) uses, for metrics and terminals: per laser channel its
    lookup table ("measured" in calibration/<profile>/, "profile" where the profile names it in `own_tables`, or
    "linear": uncalibrated), each file with its SHA-256, and the fitted optical model (file, SHA-256, colours) or
    None for the ideal model."""
    luts = profile.slm.lut if profile.slm is not None else {}
    tables: dict[str, Any] = {}
    for channel in profile.channels:
        path = luts.get(channel.name)
        if path is None:
            tables[channel.name] = {"source": "linear"}
        else:
            source = "profile" if channel.name in own_tables else "measured"
            tables[channel.name] = {"source": source, "file": str(path), "sha256": file_sha256(path)}
    model = profile.optics.model if profile.optics is not None else None
    fitted = None
    if model is not None:
        fitted = {"file": str(model), "sha256": file_sha256(model),
                  "colours": [c.name for c in profile.channels if fitted_model_entry(profile, c.name) is not None]}
    return {"lookup_tables": tables, "optical_model": fitted}


def calibration_lines(used: Mapping[str, Any]) -> list[str]:
    """`calibration_used`'s answer for a terminal, one line per kind (checksums shortened to 12 digits)."""
    tables = [f"{colour} {entry['source']}" + (f" ({entry['file']}, sha256 {entry['sha256'][:12]})"
                                               if "file" in entry else " (uncalibrated)")
              for colour, entry in used["lookup_tables"].items()]
    model = used["optical_model"]
    return [f"lookup tables: {'; '.join(tables) or 'none'}",
            "optical model: " + (f"fitted, {model['file']} (sha256 {model['sha256'][:12]}) for "
                                 f"{', '.join(model['colours']) or 'no colour here'}" if model else "none (ideal)")]
