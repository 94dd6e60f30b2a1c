"""The README's Python example runs as written (on the small test bench, with fewer iterations) and scores what it
says it scores: the same figures as `benchctl generate` for that colour."""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path

import pytest

from benchctl.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_example() -> str:
    text = README.read_text()
    start = text.index("### In Python (a notebook)")
    return re.search(r"```python\n(.*?)```", text[start:], re.S)[1]


def test_the_readme_python_example_runs_and_agrees_with_generate(tmp_path: Path, small_profile_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    code = readme_example()
    for old, new in (('load_profile("simulated")', f"load_profile({str(small_profile_path)!r})"),
                     ("iterations=50", "iterations=5")):
        assert code.count(old) == 1, old
        code = code.replace(old, new)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(code, str(README), "exec"), {})
    match = re.fullmatch(r"PSNR (\d+\.\d\d) dB, SSIM (\d\.\d{3}) \(amplitude\)\n", printed.getvalue())
    assert match is not None, printed.getvalue()

    monkeypatch.chdir(tmp_path)
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["generate", "photo:coffee", "--method", "sgd", "--iterations", "5", "--colours", "green",
                     "-o", str(tmp_path / "g"), "-p", str(small_profile_path)]) == 0
    green = json.loads((tmp_path / "g" / "metrics.json").read_text())["colours"]["green"]
    # printed to 2 and 3 decimals, recorded to 4: equal up to that rounding
    assert float(match[1]) == pytest.approx(green["psnr_amplitude_db"], abs=0.0051)
    assert float(match[2]) == pytest.approx(green["ssim_amplitude"], abs=0.00051)
