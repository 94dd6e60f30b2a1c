"""Counts that scale memory are bounded by an estimate of the peak against the machine's memory (one line naming the
count and the largest that fits), the dry run says the estimate, and frames are averaged as they are decoded."""

from __future__ import annotations

import gc
import weakref
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import one_error_line

from benchctl.capture.raw import RawImage, average_frames, decode_raw
from benchctl.cli import main
from benchctl.dng import dng_bytes
from benchctl.errors import BadValueError
from benchctl.memory import INTERPRETER_BYTES, exposure_estimate, fit_estimate, memory_limit
from benchctl.profiles import load_profile


def test_frames_are_averaged_as_they_are_decoded() -> None:
    """A generator of decoded frames is consumed one at a time: when a frame is decoded, no earlier one but the
    first (the reference for the grid) is still alive."""
    alive: list[weakref.ref[RawImage]] = []
    seen_alive: list[int] = []

    def frames() -> Iterator[RawImage]:
        for k in range(6):
            gc.collect()
            seen_alive.append(sum(ref() is not None for ref in alive[1:]))
            mosaic = np.full((24, 32), 2048 + 100 * k, np.uint16)  # LibRaw reads none much smaller
            image = decode_raw(dng_bytes(mosaic, black_level=2048, white_level=16383))
            alive.append(weakref.ref(image))
            yield image
            del image  # this generator's own reference

    mean = average_frames(frames())
    assert seen_alive == [0, 0, 0, 0, 0, 0]
    np.testing.assert_allclose(mean.mosaic, np.full((24, 32), 250 / (16383 - 2048)), rtol=1e-6)
    assert mean.source == "mean of 6 frames (<bytes> .. <bytes>)"


def test_the_memory_limit_is_the_machines_unless_set(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("BENCHCTL_MAX_MEMORY", raising=False)
    machine = memory_limit()
    assert machine is not None and machine > 2**30
    for text, value in (("8G", 8 * 2**30), ("512M", 512 * 2**20), ("1.5GiB", 3 * 2**29), ("123456", 123456)):
        monkeypatch.setenv("BENCHCTL_MAX_MEMORY", text)
        assert memory_limit() == value
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", "lots")
    with pytest.raises(BadValueError, match=r"\$BENCHCTL_MAX_MEMORY must be a size such as 8G, 512M or a number of "
                                            r"bytes, got 'lots'"):
        memory_limit()


def capture_with(tmp_path: Path, **parameters: int) -> Path:
    path = tmp_path / "capture.toml"
    path.write_text('procedure = "colour-capture"\n[parameters]\nlut_calibration = "skip"\n'
                    + "".join(f"{key} = {value}\n" for key, value in parameters.items()))
    return path


def test_frames_beyond_the_memory_are_one_line_and_the_largest_that_fits_runs(
        tmp_path: Path, bench_profile_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", "1G")
    rows, cols = 300, 440  # the bench profile's [sim.sensor]
    raw = 2.2 * rows * cols
    largest = int((2**30 - INTERPRETER_BYTES - 32 * rows * cols - 3 * raw) // raw)
    assert exposure_estimate(load_profile(bench_profile_path), largest, 3).peak <= 2**30
    procedure = capture_with(tmp_path, frames=largest + 1, dark_frames=3)
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert line.startswith(f"benchctl: error: {procedure}: frames = {largest + 1} (with dark_frames = 3) needs about ")
    assert line.endswith(f"at the peak of an exposure of RAW frames of 440 x 300 px (290 kB held per frame), above "
                         f"the 1.07 GB of memory here: at most frames = {largest} ($BENCHCTL_MAX_MEMORY sets the "
                         "limit)")
    assert main(["run", str(capture_with(tmp_path, frames=largest, dark_frames=3)), "-p", str(bench_profile_path),
                 "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "memory: about 1.07 GB at the peak of an exposure of RAW frames of 440 x 300 px (290 kB held per frame); " \
           "limit 1.07 GB" in out


def test_model_calibration_patterns_and_fit_steps_are_bounded(tmp_path: Path, bench_profile_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", "1G")
    procedure = tmp_path / "model.toml"
    for key, value, most in (("patterns", 10**6, "at most patterns = "), ("fit_steps", 10**9, "at most fit_steps = ")):
        procedure.write_text(f'procedure = "model-calibration"\n[parameters]\n{key} = {value}\nregistration = '
                             '"stored"\n')
        line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
        assert line.startswith(f"benchctl: error: {procedure}: {key} = {value} (with "), line
        assert "at the peak of the model fit on a padded grid of " in line and most in line, line
    profile = load_profile(bench_profile_path)
    exposure = exposure_estimate(profile, 2, 1).peak  # the procedure's defaults
    assert fit_estimate(profile, 1, True, 120).peak > exposure + 1
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", str(int(exposure) + 1))  # the exposures fit, no fit does
    procedure.write_text('procedure = "model-calibration"\n[parameters]\nregistration = "stored"\n')
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert line.endswith("not even patterns = 1 fits ($BENCHCTL_MAX_MEMORY sets the limit)"), line


def test_a_procedure_parameter_of_the_same_name_but_another_kind_is_no_count(small_profile_path: Path) -> None:
    from types import SimpleNamespace

    from benchctl.memory import check_memory

    profile = load_profile(small_profile_path)
    assert check_memory(profile, SimpleNamespace(frames=["first.dng"], patterns="grid"), "mine.py") == []
    (line,) = check_memory(profile, SimpleNamespace(frames=3, dark_frames=1), "mine.py")
    assert line.startswith("memory: about ") and "RAW frames of 5280 x 3528 px" in line
