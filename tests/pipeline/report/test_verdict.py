"""The surveyor's numbers and words: mean and σ per axis, the ASPRS class, the verdict, the
stage warnings, the residual order, the arrow key (no run needed)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.report.asprs import asprs_class_cm, asprs_table, bias_words, verdict_lines
from pipeline.report.figures import key_length_m
from pipeline.report.html import class_cm
from pipeline.report.stage_warnings import collect_warnings

#: Hand-made residuals (m): x alternates ±2 cm (no bias), z is -6 cm ± 1 cm (a bias).
RESIDUALS_M = np.array([[0.02, 0.01, -0.05], [-0.02, 0.03, -0.07],
                        [0.02, 0.01, -0.05], [-0.02, 0.03, -0.07]])


def test_mean_and_std_per_axis() -> None:
    t = asprs_table(RESIDUALS_M)
    assert (t.mean_x_m, t.mean_y_m, t.mean_z_m) == pytest.approx((0.0, 0.02, -0.06))
    # sample standard deviation (n - 1): sqrt(4 * 0.02^2 / 3) etc.
    assert t.std_x_m == pytest.approx(0.02 * np.sqrt(4 / 3))
    assert t.std_y_m == pytest.approx(0.01 * np.sqrt(4 / 3))
    assert t.std_z_m == pytest.approx(0.01 * np.sqrt(4 / 3))
    # RMSE^2 = mean^2 + std^2 (n - 1) / n
    assert t.rmse_z_m == pytest.approx(np.sqrt(0.06**2 + t.std_z_m**2 * 3 / 4))
    one = asprs_table(RESIDUALS_M[:1])
    assert one.mean_z_m == pytest.approx(-0.05) and np.isnan(one.std_z_m)


@pytest.mark.parametrize(("rmse_m", "expected"), [
    (0.0, 0.63), (0.0063, 0.63), (0.0064, 1.25), (0.060, 7.5), (0.075, 7.5), (0.0751, 10.0),
    (10.0, 1000.0), (10.01, None), (float("nan"), None)])
def test_asprs_class_for_given_rmse(rmse_m: float, expected: float | None) -> None:
    assert asprs_class_cm(rmse_m) == expected


def test_classes_are_written_as_surveyors_write_them() -> None:
    assert class_cm(7.5) == "7.5 cm" and class_cm(10.0) == "10 cm" and class_cm(None) == "–"


def test_verdict_words() -> None:
    t = asprs_table(np.tile(RESIDUALS_M, (10, 1)))  # 40 points: no caveat
    lines = verdict_lines(t, "seq-r", has_truth=False)
    assert lines[0].startswith("40 check points") and "RMSE_V = 6.1 cm" in lines[0]
    assert not any("indicative" in line for line in lines)
    assert "meets the 5 cm horizontal accuracy class" in lines[1]
    assert "meets the 7.5 cm vertical accuracy class" in lines[2]
    bias = bias_words(t)
    assert bias is not None and "dz mean -6.0 cm" in bias and "dx" not in bias
    few = verdict_lines(asprs_table(RESIDUALS_M), "seq-r", has_truth=False)
    assert any("Only 4 check points" in line and "at least 30" in line for line in few)
    none = verdict_lines(None, "seq-r", has_truth=False)
    assert none[0].startswith("No check points") and "precision" in " ".join(none)
    assert "agreement" in " ".join(none) and "simulated" not in " ".join(none)


def test_every_stage_warning_in_one_list() -> None:
    run = {"warnings": ["w1"], "skipped": [{"image": "a.jpg", "reason": "unreadable"}]}
    ortho = {"warnings": ["no DSM"], "skipped": ["b"]}
    ref = {"converged": False, "termination": "NO_CONVERGENCE", "iterations": 50,
           "n_observations_left_out": 3}
    sfm = {"unregistered": ["c"], "note": None}
    found = collect_warnings(run, ortho, ref, sfm, ("cp9",), ("no reference",))
    assert [w.stage for w in found] == ["run", "run", "ortho", "ortho", "reference", "sfm",
                                        "check points", "report"]
    assert found[1].message == "image a.jpg skipped: unreadable"
    assert "did not converge" in found[4].message and "cp9" in found[6].message
    assert collect_warnings({}, None, None, None, (), ()) == ()


def test_arrow_key_is_a_round_length() -> None:
    assert key_length_m(0.061) == pytest.approx(0.05)
    assert key_length_m(0.02) == pytest.approx(0.02)
    assert key_length_m(0.0001) == pytest.approx(0.001)
