"""Calibration kept between runs, per hardware profile: the camera-SLM registration and the SLM lookup tables.

    calibration/<profile name>/registration.json   per colour: homography (target-plane px -> camera active
                                                    area px), reprojection error, when, for what (`validity`)
    calibration/<profile name>/lut-<colour>.csv    measured gray -> phase table (benchctl.devices.slm.lut format)
    calibration/<profile name>/lut.json            when and for which geometry each table was measured
    calibration/<profile name>/optical-model.json  per colour: fitted wavefront error (Zernike waves) and beam,
                                                    residual, when, for which geometry (model calibration)
    calibration/<profile name>/focus.json          per colour: focus steps <-> depth, backlash, repeatability (focus
                                                    calibration), for which focus device
    calibration/<profile name>/rejected/           calibrations that failed their acceptance test
                                                    (calibration.acceptance), `<run>-<file>`, kept for inspection only

The root is $BENCHCTL_CALIBRATION_DIR, else ./calibration. A colour's stored calibration is used only while what
`validity` records for it is unchanged (its optical geometry, the SLM's bit depth and flips, the camera); one older
than STALE_DAYS is used with a warning. Each run copies the calibration it uses into its own folder, so resuming it
or reading its report later sees the same numbers.
"""

from __future__ import annotations

import os
import shutil
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import msgspec

from benchctl.calibration.files import FocusFile, LutIndex, OpticalModelFile, RegistrationFile, checked_json
from benchctl.errors import BenchctlError
from benchctl.files import ensure_dir, file_sha256, write_json
from benchctl.profiles import Profile

CALIBRATION_ENV = "BENCHCTL_CALIBRATION_DIR"
REGISTRATION_FILE = "registration.json"
LUT_INDEX = "lut.json"
MODEL_FILE = "optical-model.json"
FOCUS_FILE = "focus.json"
REJECTED = "rejected"
STALE_DAYS = 30


def calibration_root() -> Path:
    """Where calibrations are kept: $BENCHCTL_CALIBRATION_DIR, else ./calibration."""
    return Path(os.environ.get(CALIBRATION_ENV) or "calibration")


def validity(profile: Profile, channel: str) -> dict[str, Any]:
    """What a colour's stored calibration holds for: the channel's optical geometry (the fingerprint
    `Geometry.to_dict`), the SLM's bit depth and flips, and the camera; a stored entry is used while all of it is
    unchanged."""
    slm, camera = profile.require("slm").slm, profile.camera
    assert slm is not None
    return {**profile.geometry(channel).to_dict(), "bit_depth": slm.bit_depth, "flip": [slm.flip_y, slm.flip_x],
            "camera": f"{camera.driver} {camera.model}".strip() if camera else None}


class Calibration:
    """The calibration files of one profile in one folder (the shared store, or a run's own copy)."""

    def __init__(self, folder: Path, profile: Profile) -> None:
        self.folder = Path(folder)
        self.profile = profile
        complete = profile.slm is not None and profile.optics is not None
        self.validity = {c.name: validity(profile, c.name) for c in profile.channels} if complete else {}

    def _valid(self, colour: str, entry: dict[str, Any]) -> bool:
        return colour in self.validity and entry.get("geometry") == self.validity[colour]

    def _for(self, colour: str) -> dict[str, Any]:
        """What an entry stored for `colour` now is valid for."""
        if colour not in self.validity:
            raise BenchctlError(f"{self.profile.path}: no laser channel {colour!r} to calibrate")
        return self.validity[colour]

    @classmethod
    def store(cls, profile: Profile) -> Calibration:
        """The shared store for `profile`, keyed by its name."""
        return cls(calibration_root() / profile.name, profile)

    # -- registration ---------------------------------------------------------------------------------------------

    def registrations(self) -> dict[str, dict[str, Any]]:
        """Colour -> stored registration (a dict with "homography", "rms_px", ...) valid for this geometry."""
        data = checked_json(self.folder / REGISTRATION_FILE, RegistrationFile)
        if not data:
            return {}
        return {colour: entry for colour, entry in data.get("colours", {}).items() if self._valid(colour, entry)}

    def save_registration(self, colour: str, registration: dict[str, Any]) -> Path:
        """Store one colour's registration (other colours' entries stay)."""
        path = ensure_dir(self.folder) / REGISTRATION_FILE
        data = checked_json(path, RegistrationFile) or {"profile": self.profile.name, "colours": {}}
        data["colours"][colour] = {**registration, "geometry": self._for(colour), "created": _now()}
        return write_json(path, data)

    # -- lookup tables ----------------------------------------------------------------------------------------------

    def lut_files(self) -> dict[str, Path]:
        """Colour -> measured lookup-table file valid for this geometry."""
        index = checked_json(self.folder / LUT_INDEX, LutIndex) or {}
        return {colour: self.folder / entry["file"] for colour, entry in index.items()
                if self._valid(colour, entry) and (self.folder / entry["file"]).is_file()}

    def lut_path(self, colour: str) -> Path:
        """Where the lookup table of `colour` is written."""
        return ensure_dir(self.folder) / f"lut-{colour}.csv"

    def record_lut(self, colour: str, details: dict[str, Any]) -> None:
        """Note in the index that lut-<colour>.csv was just measured (with `details` on how)."""
        path = ensure_dir(self.folder) / LUT_INDEX
        index = checked_json(path, LutIndex) or {}
        index[colour] = {"file": self.lut_path(colour).name, "geometry": self._for(colour), "created": _now(),
                         **details}
        write_json(path, index)

    def lut_info(self) -> dict[str, dict[str, Any]]:
        """The index entries of the valid tables."""
        index = checked_json(self.folder / LUT_INDEX, LutIndex) or {}
        return {colour: index[colour] for colour in self.lut_files()}

    # -- fitted optical model -------------------------------------------------------------------------------------

    def models(self) -> dict[str, dict[str, Any]]:
        """Colour -> fitted optical model entry (FittedOptics.to_dict() plus residual, created) for this geometry."""
        data = checked_json(self.folder / MODEL_FILE, OpticalModelFile) or {}
        return {colour: entry for colour, entry in data.get("colours", {}).items() if self._valid(colour, entry)}

    def save_model(self, colour: str, entry: dict[str, Any]) -> Path:
        """Store one colour's fitted model; entries fitted for another geometry are dropped (they no longer apply)."""
        path = ensure_dir(self.folder) / MODEL_FILE
        data: dict[str, Any] = {"profile": self.profile.name, "colours": self.models()}
        data["colours"][colour] = {**entry, "geometry": self._for(colour), "created": _now()}
        return write_json(path, data)

    # -- focus ------------------------------------------------------------------------------------------------------

    def focus_device(self) -> str:
        """The focus device a focus calibration holds for: the [focus] driver and where it is reached."""
        focus = self.profile.section("focus")
        return f"{focus.driver} {focus.port or 'camera lens'}"

    def focus_maps(self) -> dict[str, dict[str, Any]]:
        """Colour -> stored focus calibration entry valid for this geometry and focus device."""
        data = checked_json(self.folder / FOCUS_FILE, FocusFile) or {}
        device = self.focus_device() if self.profile.focus else None
        return {colour: entry for colour, entry in data.get("colours", {}).items()
                if self._valid(colour, entry) and entry.get("focus") == device}

    def save_focus(self, colour: str, entry: dict[str, Any]) -> Path:
        """Store one colour's focus calibration (other colours' valid entries stay)."""
        path = ensure_dir(self.folder) / FOCUS_FILE
        data: dict[str, Any] = {"profile": self.profile.name, "unit": entry.pop("unit", "step"),
                                "colours": self.focus_maps()}
        data["colours"][colour] = {**entry, "focus": self.focus_device(), "geometry": self._for(colour),
                                   "created": _now()}
        return write_json(path, data)

    def rejected_path(self, run: str, name: str) -> Path:
        """Where a calibration run `run` measured but did not store (it failed its acceptance test) is kept for
        inspection: rejected/<run>-<name>, which nothing reads and runs do not copy."""
        return ensure_dir(self.folder / REJECTED) / f"{run}-{name}"

    # -- use ----------------------------------------------------------------------------------------------------------

    def checksums(self) -> dict[str, str]:
        """File name -> SHA-256 of every calibration file here (what a run's copy is checked against on resume)."""
        if not self.folder.is_dir():
            return {}
        return {item.name: file_sha256(item) for item in sorted(self.folder.iterdir()) if item.is_file()}

    def copy_to(self, folder: Path) -> Calibration:
        """Copy every calibration file into `folder` (a run's own copy) and return the copy."""
        ensure_dir(folder)
        if self.folder.is_dir():
            for item in self.folder.iterdir():
                if item.is_file():
                    shutil.copy2(item, folder / item.name)
        return Calibration(folder, self.profile)

    def applied(self, profile: Profile) -> Profile:
        """`profile` with the measured lookup tables for the channels whose table the profile does not name, and
        the fitted optical model unless the profile names one."""
        files = self.lut_files()
        slm = profile.slm
        if slm is not None and files:
            luts = {**{c: p.resolve() for c, p in files.items()}, **slm.lut}
            profile = msgspec.structs.replace(profile, slm=msgspec.structs.replace(slm, lut=luts))
        return self.with_model(profile)

    def with_model(self, profile: Profile) -> Profile:
        """`profile` with this calibration's fitted optical model, unless the profile names one or none is stored."""
        if profile.optics is None or profile.optics.model is not None or not self.models():
            return profile
        model = (self.folder / MODEL_FILE).resolve()
        return msgspec.structs.replace(profile, optics=msgspec.structs.replace(profile.optics, model=model))

    def state(self, colours: list[str]) -> tuple[list[dict[str, Any]], list[str]]:
        """For the report: one row per colour (registration and lookup table in use) and warnings."""
        rows, warnings = [], []
        registrations, luts, models = self.registrations(), self.lut_info(), self.models()
        explicit = self.profile.slm.lut if self.profile.slm else {}
        for colour in colours:
            reg, lut = registrations.get(colour), luts.get(colour)
            if colour in explicit:
                lut_text = f"profile file {explicit[colour]}"
            elif lut:
                lut_text = f"measured {lut['created']}"
            else:
                lut_text = "none: linear (uncalibrated)"
                warnings.append(f"{colour}: SLM lookup table not calibrated (linear); run the lut-calibration "
                                "procedure")
            reg_text = f"{reg['created']}, rms {reg['rms_px']:.2f} px" if reg else "none"
            for label, entry in (("registration", reg), ("lookup table", lut)):
                if entry and _age(entry["created"]) > timedelta(days=STALE_DAYS):
                    warnings.append(f"{colour}: {label} is stale (made {entry['created']}, over {STALE_DAYS} days ago)")
            model = models.get(colour)
            model_text = (f"fitted {model['created']}, residual {model['residual']:.3f}: "
                          + ", ".join(f"{k} {v:+.3f}" for k, v in model["zernike_waves"].items())
                          + f" waves; beam waist {model['waist_mm']:.2f} mm"
                          + f"; crosstalk {model.get('crosstalk_px', 0.0):.3f} px"
                          + f"; zero order {model.get('zero_order', 0.0):.3f}" if model else "none: ideal model")
            rows.append({"colour": colour, "registration": reg_text, "lookup table": lut_text,
                         "optical model": model_text})
        return rows, warnings


def _now() -> str:
    return datetime.now().isoformat(timespec="seconds")


def _age(created: str) -> timedelta:
    try:
        return datetime.now() - datetime.fromisoformat(created)
    except ValueError:
        return timedelta(0)
