"""Lookup-table files: exact round trips, every accepted format, errors that name file and line, per-channel
tables in show_phase, and tables spanning more or less than 2 pi encoding monotonically within a period."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.setups import optical_setup
from benchctl.cgh import SGD
from benchctl.devices.sim.slm import SimSLM
from benchctl.devices.slm import load_lut, lut_for, save_lut, slm_for
from benchctl.errors import BenchctlError
from benchctl.holograms.scene import compute_scene
from benchctl.optics.metrics import amplitude_scores, crop_roi, lsq_scale
from benchctl.optics.phase_encoding import PhaseLUT
from benchctl.profiles import SLMConfig, load_profile
from benchctl.targets import load_target, prepare_target

PI = math.pi
# A measured-looking 8-bit response: not linear, ~1.9 pi deep, with a flat step (equal neighbours allowed).
MEASURED = 1.9 * PI * np.sqrt(np.arange(256) / 255.0)
MEASURED[100] = MEASURED[99]


def config(width: int = 4, height: int = 1, **settings: object) -> SLMConfig:
    return SLMConfig(width=width, height=height, pitch_um=8.0, bit_depth=settings.pop("bit_depth", 8),
                     settle_ms=0.0, **settings)


def test_save_then_load_is_exact(tmp_path: Path) -> None:
    lut = PhaseLUT(MEASURED)
    path = save_lut(tmp_path / "luts" / "red.csv", lut)
    lines = path.read_text().splitlines()
    assert lines[0] == "gray,phase_rad" and len(lines) == 257
    assert lines[1] == "0,0.0" and lines[-1] == f"255,{1.9 * PI!r}"
    loaded = load_lut(path, 8)
    assert loaded.phases.dtype == np.float64
    assert loaded.phases.tolist() == MEASURED.tolist()


def test_one_phase_per_line_with_comments_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "green.txt"
    path.write_text("# 2-bit test table, radians\n0\n\n0.5   # gray 1\n1.5\n3.0\n")
    assert load_lut(path, 2).phases.tolist() == [0.0, 0.5, 1.5, 3.0]


def test_two_columns_with_header_in_any_order_and_separators(tmp_path: Path) -> None:
    path = tmp_path / "blue.csv"
    path.write_text("gray; phase\n2; 1.5\n0; 0\n3\t3.0\n1, 0.5\n")
    assert load_lut(path, 2).phases.tolist() == [0.0, 0.5, 1.5, 3.0]


def test_npy_table(tmp_path: Path) -> None:
    path = tmp_path / "red.npy"
    np.save(path, MEASURED.astype(np.float32))
    assert load_lut(path, 8).phases.tolist() == MEASURED.astype(np.float32).astype(np.float64).tolist()


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("short.csv", "0\n1\n2\n", "3 phases, expected 4 (one per gray level of a 2-bit SLM)"),
        ("long.txt", "0\n1\n2\n3\n4\n", "5 phases, expected 4"),
        ("empty.csv", "# nothing\n", "no phases in lookup table (expected 4, one per gray level)"),
        ("drop.csv", "0\n1\n0.5\n2\n", "line 3: phase of gray 2 (0.5 rad) is below that of gray 1 (1 rad); "
                                       "the table must be non-decreasing"),
        ("nan.csv", "gray,phase\n0,0\n1,nan\n2,1\n3,2\n", "line 3: phase of gray 1 is nan"),
        ("text.csv", "0\n1\nabc\n2\n", "line 3: phase 'abc' is not a number"),
        ("cols.csv", "0,0\n1,1,1\n", "line 2: expected 2 columns like the first row, got 3"),
        ("three.csv", "0,0,0\n", "line 1: expected 1 column (phase) or 2 (gray, phase), got 3"),
        ("range.csv", "0,0\n1,1\n4,2\n3,3\n", "line 3: gray level 4 outside 0..3"),
        ("dup.csv", "0,0\n1,1\n1,2\n3,3\n", "line 3: gray level 1 again (first on line 2)"),
        ("gap.csv", "0,0\n1,1\n3,3\n", "1 of 4 gray levels missing: 2"),
        ("float_gray.csv", "0,0\n1.5,1\n", "line 2: gray level '1.5' is not an integer"),
    ],
)
def test_bad_text_tables_name_file_and_line(tmp_path: Path, name: str, text: str, message: str) -> None:
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(BenchctlError) as info:
        load_lut(path, 2)
    assert str(info.value).startswith(f"{path}: ")
    assert message in str(info.value)


def test_two_column_table_decreasing_in_gray_order_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "order.csv"
    path.write_text("0,0\n2,1\n1,2\n3,3\n")  # gray 2 (line 2) has phase 1 below gray 1's 2 (line 3)
    with pytest.raises(BenchctlError, match=r"line 2: phase of gray 2 \(1 rad\) is below that of gray 1 \(2 rad\)"):
        load_lut(path, 2)


def test_bad_npy_tables_and_files(tmp_path: Path) -> None:
    np.save(tmp_path / "flat.npy", np.zeros((2, 2)))
    np.save(tmp_path / "short.npy", np.zeros(3))
    np.save(tmp_path / "nan.npy", np.array([0.0, 1.0, np.inf, 3.0]))
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    (tmp_path / "table.xlsx").write_bytes(b"")
    cases = {
        "flat.npy": "expected a 1-D array of 4 phases in radians, got shape (2, 2) float64",
        "short.npy": "3 phases, expected 4",
        "nan.npy": "index 2: phase of gray 2 is inf",
        "junk.npy": "not a readable .npy lookup table",
        "table.xlsx": "unknown lookup-table format '.xlsx' (use .csv, .txt or .npy)",
        "missing.csv": "cannot read lookup table: No such file or directory",
    }
    for name, message in cases.items():
        with pytest.raises(BenchctlError) as info:
            load_lut(tmp_path / name, 2)
        assert str(info.value).startswith(f"{tmp_path / name}: ")
        assert message in str(info.value), name


def test_save_refuses_a_non_csv_name(tmp_path: Path) -> None:
    with pytest.raises(BenchctlError, match="name the file .csv"):
        save_lut(tmp_path / "red.npy", PhaseLUT.linear(2))


def test_lut_for_uses_the_channels_file_else_the_linear_table(tmp_path: Path) -> None:
    path = save_lut(tmp_path / "red.csv", PhaseLUT(MEASURED))
    cfg = config(two_pi_gray=200.0, lut={"red": path})
    assert lut_for(cfg, "red").phases.tolist() == MEASURED.tolist()
    assert lut_for(cfg, "green").phases.tolist() == PhaseLUT.linear(8, 200.0).phases.tolist()
    assert lut_for(cfg, "green").phases[100].item() == pytest.approx(PI)


def test_show_phase_encodes_each_channel_through_its_own_table(tmp_path: Path) -> None:
    # red: 4 levels at 0, 0.5, 1.5, 3 rad; green: linear 2-bit (0, pi/2, pi, 3 pi/2)
    path = tmp_path / "red.csv"
    path.write_text("0\n0.5\n1.5\n3.0\n")
    slm = SimSLM(config(bit_depth=2, lut={"red": path}), ["red", "green"]).open()
    phase = np.array([[0.2, 1.1, 2.0, 2.4]])
    assert slm.show_phase(phase, "red").tolist() == [[0, 2, 2, 3]]
    assert slm.show_phase(phase, "green").tolist() == [[0, 1, 1, 2]]
    assert slm.lut("red").phases.tolist() == [0.0, 0.5, 1.5, 3.0]
    assert slm.info()["luts"] == {"red": str(path), "green": "linear, 2 pi = gray 4"}


def test_display_model_only_where_the_table_leaves_phases_out(tmp_path: Path) -> None:
    path = save_lut(tmp_path / "red.csv", PhaseLUT.linear(8, two_pi_gray=256 / 0.88))
    slm = SimSLM(config(width=64, height=8, lut={"red": path}, phase_offset_rad=0.7), ["red", "green"])
    assert slm.display_model("green") is None  # linear 8 bit: every phase within half a step
    assert slm.display_model("green", always=True) is not None  # a fitted crosstalk needs the driven phase
    shown = slm.display_model("red")
    assert shown is not None
    phase = torch.linspace(-PI, PI, 512).reshape(slm.shape)
    gray = slm.encode(phase, "red")
    assert torch.equal(shown(phase), torch.from_numpy(slm.driven(gray, "red")))
    # the driven phase is the table's, offset removed, unwrapped: it jumps where the gray levels wrap, not at pi
    driven = slm.driven(gray, "red")
    assert np.allclose(driven, slm.lut("red").phases[gray] - 0.7, atol=1e-6)
    assert np.allclose(np.remainder(driven + PI, 2 * PI) - PI, slm.decode(gray, "red"), atol=1e-6)
    wrapped = np.angle(np.exp(1j * (shown(phase) - phase).numpy()))
    assert np.abs(wrapped).max() > 0.3  # phases in the 0.75 rad gap move to its edges


def test_generated_sgd_optimises_what_a_short_stroke_panel_shows(tmp_path: Path, small_profile_path: Path) -> None:
    table = save_lut(tmp_path / "red.csv", PhaseLUT.linear(8, two_pi_gray=256 / 0.88))
    small_profile_path.write_text(small_profile_path.read_text() + f'[slm.lut]\nred = "{table}"\n')
    profile = load_profile(small_profile_path)
    # a flat field: SGD gets close enough that the missing stroke is most of what is left (charts' sharp edges
    # keep this 64 x 96 grid near 20 dB, where the gap costs only 0.1-0.5 dB)
    target = prepare_target(load_target("chart:white", profile.slm.shape), profile.slm.shape, profile.optics.roi)
    scored = compute_scene(target, Calibrated(profile), "sgd", iterations=40, colours=["red"]).colours[0].scores
    # the same SGD blind to the table, displayed and scored the same way
    slm, setup = slm_for(profile), optical_setup(profile, "red")
    recon = setup.reconstruct_roi(torch.from_numpy(slm.decode(slm.encode(SGD(target[0], setup, iterations=40), "red"),
                                                               "red")))
    wanted = crop_roi(target[0], profile.optics.roi)
    blind = amplitude_scores(recon * lsq_scale(recon, wanted), wanted)["psnr_amplitude_db"]
    assert scored["psnr_amplitude_db"] > blind + 2  # measured 30.5 against 26.3 dB


def cyclic_descents(row: np.ndarray) -> int:
    """How many times a sequence goes down, counting last -> first: 1 for a sawtooth over one period."""
    values = row.astype(np.int64)
    return int((np.diff(np.append(values, values[0])) < 0).sum())


def show_ramp(tmp_path: Path, span_pi: float) -> np.ndarray:
    """Show a phase ramp over one period [0, 2 pi) through a linear table file spanning span_pi * pi."""
    lut = PhaseLUT.linear(8, two_pi_gray=256 * 2 / span_pi)
    path = save_lut(tmp_path / "red.csv", lut)
    slm = SimSLM(config(width=1024, lut={"red": path}), ["red"]).open()
    ramp = np.arange(1024)[None, :] * (2 * PI / 1024)
    return slm.show_phase(ramp, "red")[0]


def test_table_spanning_less_than_two_pi_encodes_monotonically(tmp_path: Path) -> None:
    gray = show_ramp(tmp_path, 1.6)
    assert cyclic_descents(gray) == 1
    assert np.unique(gray).tolist() == list(range(256))  # every level used, the gap splits to 0 and 255
    # The wrap from 255 to 0 sits mid-gap, between 1.6 pi * 255/256 and 2 pi: 1.797 pi, sample 920 of 1024.
    (drop,) = np.flatnonzero(np.diff(gray.astype(np.int64)) < 0)
    assert gray[0] == 0 and gray[drop] == 255 and gray[drop + 1] == 0 and abs(drop + 1 - 920) <= 1


def test_table_spanning_more_than_two_pi_encodes_monotonically(tmp_path: Path) -> None:
    gray = show_ramp(tmp_path, 2.4)
    assert cyclic_descents(gray) == 1


def test_generate_and_slm_show_encode_through_the_measured_table(tmp_path: Path, small_profile_path: Path) -> None:
    """A table measured by lut_calibration (calibration/<profile>/) is used by `generate` and `slm show` as by a
    run: the same frames as with the table named in the profile, not the linear one's."""
    from benchctl.calibration.store import Calibration
    from benchctl.cli import main
    from benchctl.devices.sim.slm import read_displayed
    from benchctl.holograms.generate import run_generate
    from benchctl.images import read_image

    table = PhaseLUT.linear(8, two_pi_gray=256 / 0.88)
    named = tmp_path / "named.toml"
    named.write_text(small_profile_path.read_text() + f'[slm.lut]\nred = "{save_lut(tmp_path / "red.csv", table)}"\n')
    phase = np.linspace(-3.0, 3.0, 64 * 96, dtype=np.float32).reshape(64, 96)
    np.save(tmp_path / "phase.npy", phase)

    def frames(profile_path: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
        run_generate("chart:bars", load_profile(profile_path), tmp_path / name, method="dpac", colours=["red"])
        assert main(["slm", "show", str(tmp_path / "phase.npy"), "--channel", "red", "-p", str(profile_path)]) == 0
        return read_image(tmp_path / name / "phase_red.png"), read_displayed()[0]

    linear = frames(small_profile_path, "linear")
    expected = frames(named, "named")
    store = Calibration.store(load_profile(small_profile_path))
    save_lut(store.lut_path("red"), table)
    store.record_lut("red", {"grays": 33})  # what lut calibration records (lut.json is checked: calibration.files)
    measured = frames(small_profile_path, "measured")
    for seen, wanted, before in zip(measured, expected, linear):
        assert np.array_equal(seen, wanted) and not np.array_equal(seen, before)
    assert np.array_equal(measured[1], slm_for(load_profile(named)).encode(phase, "red"))
