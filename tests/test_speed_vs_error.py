"""The speed-against-error front: Pareto front on hand-made points, one row per method and budget."""

from __future__ import annotations

import math

import pytest

from benchctl.benchmarks.speed_vs_error import budgets_for, front_rows
from benchctl.optics.metrics import pareto_front


def test_pareto_front_on_hand_made_points() -> None:
    points = [(1.0, 20.0), (2.0, 25.0), (2.0, 24.0), (3.0, 25.0), (0.5, 10.0), (4.0, 30.0), (1.0, 20.0), (5.0, 29.0)]
    # (2, 24) is beaten by (2, 25) at the same time, (3, 25) by (2, 25), (5, 29) by (4, 30); equal points both stay.
    assert pareto_front(points) == [True, True, False, False, True, True, True, False]
    assert pareto_front([]) == []
    assert pareto_front([(1.0, 1.0)]) == [True]


def _row(method: str, iterations: object, target: str, seconds: float, psnr: float, run: object = "") -> dict:
    return {"method": method, "iterations": iterations, "iterations_run": run, "target": target,
            "seconds_per_frame": seconds, "propagation_seconds": 0.5, "psnr_amplitude_db": psnr,
            "ssim_amplitude": 0.5, "psnr_srgb_db": psnr + 1, "ssim_srgb": 0.6}


def test_front_has_one_row_per_method_and_budget_with_means() -> None:
    rows = []
    for target, offset in (("chart:siemens", 0.0), ("photo:coffee", 10.0)):
        rows += [_row("dpac", "", target, 0.01, 15 + offset), _row("gs", 10, target, 0.1, 14 + offset, 10),
                 _row("gs", 50, target, 0.4, 16 + offset, 40), _row("sgd", 10, target, 0.2, 22 + offset, 10)]
    front = front_rows(rows)
    assert [(r["method"], r["iterations"]) for r in front] == [("dpac", ""), ("gs", 10), ("gs", 50), ("sgd", 10)]
    gs50 = front[2]
    assert gs50["psnr_amplitude_db"] == pytest.approx(21.0) and gs50["seconds_per_frame"] == pytest.approx(0.4)
    assert gs50["psnr_amplitude_charts_db"] == 16.0 and gs50["psnr_amplitude_photos_db"] == 26.0
    assert gs50["x_propagation"] == pytest.approx(0.8) and gs50["iterations_run"] == 40 and gs50["targets"] == 2
    assert [r["front"] for r in front] == [True, False, False, True]
    assert front[0]["iterations_run"] == "" and not math.isnan(front[0]["psnr_amplitude_charts_db"])


def test_budgets_one_shot_once_iterative_and_refined_at_each() -> None:
    assert budgets_for("dpac", (10, 50)) == [None]
    assert budgets_for("ccnn-dcm4", (10, 50)) == [None]
    assert budgets_for("sgd", (10, 50)) == [10, 50]
    assert budgets_for("ccnn-dcm4+sgd", (10, 50)) == [10, 50]
