"""Results say what they were made with: `generate` prints and records which lookup tables (measured, the profile's
or linear, with checksums) and which optical model it used; `benchctl models` says when a checkpoint's validation is
below DPAC's and when it was not trained through the lookup tables or the optical model the bench now has."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from benchctl.calibration.setups import optical_setup
from benchctl.calibration.store import Calibration
from benchctl.cgh.learned import build_model
from benchctl.cli import main
from benchctl.holograms.checkpoint_notes import checkpoint_notes
from benchctl.holograms.checkpoints import Checkpoint
from benchctl.profiles import load_profile

FIT = {"zernike_waves": {"defocus": 0.1}, "waist_mm": 0.0, "offset_mm": [0.0, 0.0], "crosstalk_px": 0.0,
       "zero_order": 0.0, "residual": 0.2}


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def measured_table(store: Calibration, colour: str) -> Path:
    """A measured (linear, 2 pi at gray 256) lookup table for `colour` in the calibration store."""
    path = store.lut_path(colour)
    path.write_text("gray,phase_rad\n" + "".join(f"{g},{g * 0.0245436926}\n" for g in range(256)))
    store.record_lut(colour, {"grays": 9})
    return path.resolve()


def test_generate_prints_and_records_the_tables_and_model_it_used(tmp_path: Path, small_profile_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    store = Calibration.store(load_profile(small_profile_path))
    green = measured_table(store, "green")
    model = store.save_model("green", FIT).resolve()
    assert main(["generate", "chart:bars", "--colours", "green", "-o", str(tmp_path / "g"),
                 "-p", str(small_profile_path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == (f"lookup tables: red linear (uncalibrated); green measured ({green}, sha256 "
                      f"{sha256(green)[:12]}); blue linear (uncalibrated)")
    assert out[1] == f"optical model: fitted, {model} (sha256 {sha256(model)[:12]}) for green"
    metrics = json.loads((tmp_path / "g" / "metrics.json").read_text())
    assert metrics["calibration"] == {
        "lookup_tables": {"red": {"source": "linear"},
                          "green": {"source": "measured", "file": str(green), "sha256": sha256(green)},
                          "blue": {"source": "linear"}},
        "optical_model": {"file": str(model), "sha256": sha256(model), "colours": ["green"]}}


def test_generate_without_calibration_says_so(tmp_path: Path, small_profile_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["generate", "chart:bars", "--colours", "red", "-o", str(tmp_path / "g"),
                 "-p", str(small_profile_path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[:2] == ["lookup tables: red linear (uncalibrated); green linear (uncalibrated); blue linear "
                       "(uncalibrated)", "optical model: none (ideal)"]


def record(val: dict[str, float], dpac: dict[str, float] | None, optical_model: object = None) -> dict:
    colours = {c: {"metrics": {"val_psnr_amplitude_db": v, **({"val_dpac_psnr_amplitude_db": dpac[c]} if dpac
                                                               else {})}} for c, v in val.items()}
    return {"colours": colours, "training": {"optical_model": optical_model}}


def test_checkpoint_notes_compare_with_dpac_and_the_bench_it_meets(small_profile_path: Path) -> None:
    profile = load_profile(small_profile_path)
    assert checkpoint_notes(record({"red": 36.3, "green": 36.2}, {"red": 31.2, "green": 31.5}), profile) == []
    assert checkpoint_notes(record({"red": 26.96, "green": 36.2}, {"red": 33.1, "green": 31.5}), profile) == [
        "BELOW DPAC on its validation images (red 26.96 < 33.10 dB): not worth using yet"]
    assert checkpoint_notes(record({"red": 19.9}, None), profile) == ["no validation against DPAC recorded for red"]

    store = Calibration.store(profile)
    measured_table(store, "red")
    store.save_model("red", FIT)
    calibrated = store.applied(profile)
    assert checkpoint_notes(record({"red": 36.3, "green": 36.2}, {"red": 31.2, "green": 31.5}), calibrated) == [
        "trained on the ideal phase; the panel now shows red through lookup tables it was not trained through",
        "trained on the ideal optical model; the profile now has a fitted one (fine-tune with `benchctl train ... "
        "--model-calibration stored --resume`)"]
    assert checkpoint_notes(record({"green": 36.2}, {"green": 31.5}, {"green": FIT}), profile) == [
        "trained through a fitted optical model; the profile now has none"]


def test_models_shows_the_notes_of_the_checkpoint_it_would_use(tmp_path: Path, small_profile_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    profile = load_profile(small_profile_path)
    setups = {c.name: optical_setup(profile, c.name) for c in profile.channels}
    checkpoint = Checkpoint("ccnn", {c: s.geometry for c, s in setups.items()},
                            {c: build_model("ccnn", s).state_dict() for c, s in setups.items()},
                            metrics={c: {"val_psnr_amplitude_db": 11.0, "val_dpac_psnr_amplitude_db": 16.5}
                                     for c in setups})
    (tmp_path / "checkpoints" / "small").mkdir(parents=True)
    checkpoint.save(tmp_path / "checkpoints" / "small" / "ccnn.pt")
    measured_table(Calibration.store(profile), "blue")
    monkeypatch.chdir(tmp_path)
    assert main(["models", "-p", str(small_profile_path)]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("ccnn ")]
    assert line.endswith("yes (checkpoints/small/ccnn.pt; BELOW DPAC on its validation images (red 11.00 < 16.50 dB, "
                         "green 11.00 < 16.50 dB, blue 11.00 < 16.50 dB): not worth using yet; trained on the ideal "
                         "phase; the panel now shows blue through lookup tables it was not trained through)"), line
