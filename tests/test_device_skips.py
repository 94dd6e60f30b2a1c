"""tests/device_skips.py: with $BENCHCTL_REQUIRE_DEVICES=1 (CI) a skipped third-party device test fails the run."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

SUITE = '''
import pytest

@pytest.mark.third_party
@pytest.mark.skipif(True, reason="needs Debian's xvfb")
def test_skipped_by_its_marker():
    pass

@pytest.mark.third_party
def test_skipped_inside():
    pytest.skip("no camera")

@pytest.mark.skipif(True, reason="big-endian only")
def test_skipped_not_a_device_test():
    pass

@pytest.mark.third_party
def test_that_runs():
    pass
'''


def run(tmp_path: Path, require: str | None) -> tuple[int, str]:
    (tmp_path / "test_suite.py").write_text(SUITE)
    env = {key: value for key, value in os.environ.items() if key != "BENCHCTL_REQUIRE_DEVICES"}
    if require is not None:
        env["BENCHCTL_REQUIRE_DEVICES"] = require
    env["PYTHONPATH"] = str(Path(__file__).parent)
    done = subprocess.run([sys.executable, "-m", "pytest", "-p", "device_skips", "-p", "no:cacheprovider",
                           "--strict-markers", "-rA", str(tmp_path / "test_suite.py")], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    return done.returncode, done.stdout


def test_a_skipped_third_party_device_test_fails_only_where_devices_are_required(tmp_path: Path) -> None:
    code, out = run(tmp_path, None)
    assert code == 0 and re.search(r"\b1 passed, 3 skipped\b", out), out
    code, out = run(tmp_path, "1")
    assert code == 1, out
    assert re.search(r"\b1 failed, 1 passed, 1 skipped, 1 error\b", out), out  # a skipif skips in set-up: an error
    assert "test_suite.py::test_skipped_by_its_marker skipped (needs Debian's xvfb), but $BENCHCTL_REQUIRE_DEVICES=1" \
           in out
    assert "test_suite.py::test_skipped_inside skipped (no camera), but $BENCHCTL_REQUIRE_DEVICES=1" in out
    assert re.search(r"SKIPPED \[1\] test_suite.py:\d+: big-endian only", out), out
