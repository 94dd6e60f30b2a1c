"""Counts that scale memory are bounded by an estimate of the peak against the machine's memory (one line naming the
count and the largest that fits), the dry run says the estimate, and frames are averaged as they are decoded."""

from __future__ import annotations

import gc
import os
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
from benchctl.memory import decode_estimate, exposure_estimate, fit_estimate, hologram_estimate, memory_limit, size_text
from benchctl.profiles import load_profile


@pytest.mark.slow
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
    profile = load_profile(bench_profile_path)
    base = exposure_estimate(profile, 0, 3, colours=3)
    largest = int((2**30 - base.peak) // base.per["frames"])
    assert exposure_estimate(profile, largest, 3, colours=3).peak <= 2**30
    assert exposure_estimate(profile, largest + 1, 3, colours=3).peak > 2**30
    procedure = capture_with(tmp_path, frames=largest + 1, dark_frames=3)
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert line.startswith(f"benchctl: error: {procedure}: frames = {largest + 1} (with dark_frames = 3) needs about ")
    assert line.endswith(f"at the peak of an exposure of RAW frames of 440 x 300 px (290 kB held per frame), above "
                         f"the 1.07 GB of memory here: at most frames = {largest} ($BENCHCTL_MAX_MEMORY sets the "
                         "limit)")
    assert main(["run", str(capture_with(tmp_path, frames=largest, dark_frames=3)), "-p", str(bench_profile_path),
                 "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "memory: about 1.07 GB at the run's peak, an exposure of RAW frames of 440 x 300 px (290 kB held per " \
           "frame); limit 1.07 GB of memory here" in out


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
    exposure = max(exposure_estimate(profile, 2, 1, colours=3).peak,  # the procedure's defaults
                   decode_estimate(profile, colours=3).peak)
    assert fit_estimate(profile, 1, True, 120, colours=3).peak > exposure + 1
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", str(int(exposure) + 1))  # the exposures fit, no fit does
    procedure.write_text('procedure = "model-calibration"\n[parameters]\nregistration = "stored"\n')
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert line.endswith("not even patterns = 1 fits ($BENCHCTL_MAX_MEMORY sets the limit)"), line


def test_a_hologram_beyond_the_memory_is_refused_before_anything_is_written(
        tmp_path: Path, small_profile_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Each colour keeps its optical setup: the three colours do not fit a limit that one does."""
    profile = load_profile(small_profile_path)
    one, three = hologram_estimate(profile, 1), hologram_estimate(profile, len(profile.channels))
    assert len(profile.channels) == 3 and three.peak > one.peak
    limit = int(one.peak) + 1
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", str(limit))
    argv = ["generate", "chart:siemens", "-m", "dpac", "-p", str(small_profile_path), "-o"]
    line = one_error_line(capsys, argv + [str(tmp_path / "all")])
    assert line == (f"benchctl: error: generate chart:siemens: the run needs about {size_text(three.peak)} at the peak "
                    f"of {three.what}, above the {size_text(limit)} of memory here ($BENCHCTL_MAX_MEMORY sets the "
                    "limit)")
    assert not (tmp_path / "all").exists()
    assert main(argv + [str(tmp_path / "green"), "--colours", "green"]) == 0
    assert sorted(path.name for path in (tmp_path / "green").iterdir()) == [
        "metrics.json", "phase_green.png", "reconstruction.png", "target.png"]


def test_a_procedure_parameter_of_the_same_name_but_another_kind_is_no_count(small_profile_path: Path) -> None:
    from types import SimpleNamespace

    from benchctl.memory import check_memory, peak_lines, run_estimates

    profile = load_profile(small_profile_path)
    assert check_memory(profile, SimpleNamespace(frames=["first.dng"], patterns="grid"), "mine.py") == []
    (line,) = peak_lines(check_memory(profile, SimpleNamespace(frames=3, dark_frames=1), "mine.py"))
    assert line.startswith("memory: about ") and "RAW frames of 5280 x 3528 px" in line
    kinds = [e.what for e in run_estimates(profile, SimpleNamespace(frames=3, dark_frames=1, method="dpac"))]
    assert [kind.split(" ")[0] for kind in kinds] == ["an", "decoding", "a"], kinds  # exposure, decoding, hologram


def fake_system(root: Path, available_kb: int, cgroup: str, files: dict[str, str]) -> tuple[Path, Path]:
    """A /proc with MemAvailable, this process's cgroup line and 256 resident pages, and a cgroup tree with `files`
    (path under the cgroup root -> content)."""
    proc, cgroups = root / "proc", root / "cgroup"
    (proc / "self").mkdir(parents=True)
    (proc / "meminfo").write_text(f"MemTotal:       32000000 kB\nMemFree:          100000 kB\n"
                                  f"MemAvailable:   {available_kb} kB\n")
    (proc / "self" / "cgroup").write_text(cgroup + "\n")
    (proc / "self" / "statm").write_text("9000 256 100 1 0 500 0\n")
    for name, text in files.items():
        (cgroups / name).parent.mkdir(parents=True, exist_ok=True)
        (cgroups / name).write_text(text)
    return proc, cgroups


@pytest.mark.parametrize("cgroup, files, room", [
    ("0::/", {"cgroup.controllers": "memory"}, None),  # v2, no limit anywhere: MemAvailable
    ("0::/job", {"cgroup.controllers": "memory", "job/memory.max": "max\n", "job/memory.current": "1\n"}, None),
    ("0::/job", {"cgroup.controllers": "memory", "job/memory.max": f"{4 * 2**30}\n",
                 "job/memory.current": f"{3 * 2**30}\n", "job/memory.stat": f"anon 1\ninactive_file {2**29}\n"},
     int(1.5 * 2**30)),  # v2: 4 GiB limit, 3 GiB used of which 0.5 GiB reclaimable file cache
    ("0::/a/b", {"cgroup.controllers": "memory", "a/memory.max": f"{2**30}\n", "a/memory.current": f"{2**29}\n",
                 "a/b/memory.max": "max\n", "a/b/memory.current": "0\n"}, 2**29),  # an ancestor's limit
    ("4:memory:/job", {"memory/job/memory.limit_in_bytes": f"{2**31}\n", "memory/job/memory.usage_in_bytes":
                       f"{2**30}\n", "memory/job/memory.stat": "total_inactive_file 0\n"}, 2**30),  # v1
    ("4:memory:/elsewhere", {"memory/memory.limit_in_bytes": "9223372036854771712\n",
                             "memory/memory.usage_in_bytes": "5\n"}, None),  # v1 namespaced: its root, unlimited
])
def test_the_limit_is_what_is_available_now_within_any_cgroup_limit(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cgroup: str, files: dict[str, str], room: int | None) -> None:
    """The limit compared with total RAM, so a 19.3 GB training run was accepted on a machine whose other jobs left
    less; now it is this process's resident memory plus what is available (MemAvailable, or a cgroup's limit minus
    its usage where that is less), less a margin."""
    from benchctl import memory

    proc, cgroups = fake_system(tmp_path, 8 * 2**20, cgroup, files)  # 8 GiB available
    monkeypatch.setattr(memory, "PROC", proc)
    monkeypatch.setattr(memory, "CGROUP_ROOT", cgroups)
    monkeypatch.delenv("BENCHCTL_MAX_MEMORY", raising=False)
    available = 8 * 2**30 if room is None else room
    assert memory.available_memory() == available
    margin = max(int(0.1 * available), 256 * 2**20)
    assert memory_limit() == 256 * os.sysconf("SC_PAGE_SIZE") + available - margin


def test_a_training_step_larger_than_what_is_available_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                  capsys: pytest.CaptureFixture[str],
                                                                  small_profile_path: Path) -> None:
    from benchctl import memory

    proc, cgroups = fake_system(tmp_path, 4 * 2**20, "0::/", {"cgroup.controllers": "memory"})  # 4 GiB available
    monkeypatch.setattr(memory, "PROC", proc)
    monkeypatch.setattr(memory, "CGROUP_ROOT", cgroups)
    monkeypatch.delenv("BENCHCTL_MAX_MEMORY", raising=False)
    line = one_error_line(capsys, ["train", "--method", "holonet", "--profile", str(small_profile_path), "--data",
                                   "procedural:2", "--out", str(tmp_path / "out"), "--size", "1088x1920"])
    assert line.startswith("benchctl: error: one training step of holonet on 1088 x 1920 with --batch-size 1 needs "
                           "about 9.29 GB, above the 3.87 GB this process may grow to now: "), line


HALF_SIZE = {"width = 1920": "width = 960", "height = 1088": "height = 544", "roi = [880, 1600]": "roi = [440, 800]",
             "shape = [3528, 5280]": "shape = [1764, 2640]", "margin = [52, 72]": "margin = [26, 36]",
             "settle_ms = 100": "settle_ms = 0"}
# The run's own peak: VmHWM starts afresh at exec, while ru_maxrss keeps the forking parent's (pytest's) peak.
PEAK_OF_RUN = """\
import re, sys
from pathlib import Path
from benchctl.cli import main
code = main(["run", sys.argv[1], "--profile", sys.argv[2], "--out", sys.argv[3]])
print(code, int(re.search(r"VmHWM:\\s+(\\d+) kB", Path("/proc/self/status").read_text())[1]) * 1024)
"""


@pytest.mark.slow
@pytest.mark.timeout(1200)
@pytest.mark.parametrize("procedure", [
    'procedure = "colour-capture"\n[parameters]\ncolours = ["green"]\nframes = 1\ndark_frames = 0\n'
    'lut_calibration = "skip"\nexposure = "fixed"\n',
    'procedure = "citl"\n[parameters]\ncolours = ["green"]\niterations = 1\nbaseline = false\nframes = 1\n'
    'dark_frames = 0\n'], ids=["colour-capture", "citl"])
def test_the_estimate_holds_the_peak_of_a_real_run(tmp_path: Path, procedure: str) -> None:
    """The simulated bench at half size in each dimension (a 2640 x 1764 RAW frame, a 960 x 544 SLM), one colour,
    run in a process of its own: its peak resident memory is below the dry run's estimate, which is at most 1.3 x
    it. Before, the estimate was the exposure's alone (401 MiB here; at full size 899 MB printed, 1.47 GB measured
    for a CITL run): holograms, the decoding of a frame and the setups a run keeps were not counted."""
    import subprocess
    import sys

    from conftest import truly_registered

    from benchctl.memory import run_estimates
    from benchctl.runner.procedure import load_procedure

    text = (Path(__file__).resolve().parents[1] / "hardware_profiles" / "simulated.toml").read_text()
    for old, new in HALF_SIZE.items():
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    profile_path = tmp_path / "half.toml"
    profile_path.write_text(text.replace('name = "simulated"', 'name = "half"'))
    profile = truly_registered(load_profile(profile_path))
    path = tmp_path / "p.toml"
    path.write_text(procedure)
    estimate = max(e.peak for e in run_estimates(profile, load_procedure(path).params))
    done = subprocess.run([sys.executable, "-c", PEAK_OF_RUN, str(path), str(profile_path), str(tmp_path / "runs")],
                          capture_output=True, text=True, timeout=1100, check=True)
    code, peak = (int(word) for word in done.stdout.split()[-2:])
    assert code == 0, done.stderr[-2000:]
    assert peak <= estimate <= 1.3 * peak, (peak / 2**20, estimate / 2**20)
