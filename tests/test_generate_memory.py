"""generate's memory grows linearly with the SLM grid, within the bound the README states (2 KiB per pixel)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow,  # a subprocess that imports torch per case
              pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads Linux's /proc/self/status")]

BYTES_PER_PIXEL = 2048  # README, "Bounded input": measured 0.7-0.85 KiB (DPAC) and 0.8-0.95 KiB (SGD)
PROBE = r"""
import json, sys
from pathlib import Path
from benchctl.benchmarks.speed_vs_error import resized_profile
from benchctl.profiles import load_profile
from benchctl.holograms.generate import run_generate
rows, cols, method, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
profile = resized_profile(load_profile("simulated"), (rows, cols))
run_generate("chart:bars", profile, Path(out), method=method, iterations=5 if method == "sgd" else None)
status = Path("/proc/self/status").read_text()
print(json.dumps({"peak_kib": int(next(l for l in status.splitlines() if l.startswith("VmHWM:")).split()[1])}))
"""


def _peak_bytes(rows: int, cols: int, method: str, out: Path) -> int:
    """The child's own peak resident memory. VmHWM, not getrusage: ru_maxrss of an exec'd child starts at its
    parent's peak, which in a long pytest run hides the child's."""
    done = subprocess.run([sys.executable, "-c", PROBE, str(rows), str(cols), method, str(out)],
                          capture_output=True, text=True, timeout=240, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])["peak_kib"] * 1024


@pytest.mark.parametrize("method", ["dpac", "sgd"])
def test_generate_memory_per_grid_pixel_is_bounded(tmp_path: Path, method: str) -> None:
    """The peak memory added by quadrupling the grid, per added pixel: what a large grid will cost."""
    small = _peak_bytes(136, 240, method, tmp_path / "small")
    large = _peak_bytes(272, 480, method, tmp_path / "large")
    per_pixel = (large - small) / (272 * 480 - 136 * 240)
    assert 0 < per_pixel <= BYTES_PER_PIXEL, per_pixel
