"""The warnings that the adjusted EOPs and the GPS/INS disagree as a whole, or for the odd
fix (pipeline.run.nav_agreement)."""

from __future__ import annotations

import numpy as np

from pipeline.common.tables import EopTable, NavTable
from pipeline.run.nav_agreement import (
    MAX_FAULT_WARNINGS,
    nav_disagreement_warning,
    nav_fault_warnings,
)

#: The GPS/INS σ of the tests: 1.5 m, 2° (metres, radians).
SIGMA = np.r_[1.5, 1.5, 1.5, np.radians([2.0, 2.0, 2.0])]


def _tables(n: int, seed: int) -> tuple[EopTable, NavTable]:
    """``n`` images whose GPS/INS lies within its σ of the adjusted EOPs (one draw each)."""
    rng = np.random.default_rng(seed)
    eop = np.column_stack([rng.uniform(0, 500, (n, 2)), np.full(n, 120.0),
                           rng.uniform(-0.1, 0.1, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    ids = tuple(f"img_{i:03d}" for i in range(n))
    nav = eop + rng.normal(0.0, 1.0, (n, 6)) * SIGMA
    return (EopTable(image_ids=ids, eop=eop, sigma=np.full((n, 6), 0.01)),
            NavTable(image_ids=ids, times_s=np.arange(n, dtype=np.float64), eop=nav))


def _shift(nav: NavTable, rows: np.ndarray, by: np.ndarray) -> NavTable:
    eop = nav.eop.copy()
    eop[rows] += by
    return NavTable(image_ids=nav.image_ids, times_s=nav.times_s, eop=eop)


def test_a_consistent_flight_and_a_gnss_fault_here_and_there_are_not_flagged() -> None:
    eops, nav = _tables(40, seed=1)
    assert nav_disagreement_warning(eops, nav, SIGMA, camera_fixed=True) is None
    # a 10 m jump of 10 images of 40 (a quarter: the limit, not beyond it)
    jumped = _shift(nav, np.arange(10, 20), np.r_[0.0, 0.0, 10.0, 0.0, 0.0, 0.0])
    assert nav_disagreement_warning(eops, jumped, SIGMA, camera_fixed=True) is None


def test_half_the_flight_off_is_named_with_the_likely_cause() -> None:
    eops, nav = _tables(40, seed=2)
    # a bent block: positions 12 m and attitudes 10 degrees off for half the images
    bent = _shift(nav, np.arange(0, 40, 2),
                  np.r_[0.0, 0.0, 12.0, np.radians(10.0), 0.0, 0.0])
    fixed = nav_disagreement_warning(eops, bent, SIGMA, camera_fixed=True)
    assert fixed is not None and "\n" not in fixed
    assert fixed.startswith("the adjusted EOPs of 20 of 40 images lie beyond 3 σ of their "
                            "GPS/INS (r.m.s. ")
    assert "--self-calibration" in fixed
    calibrated = nav_disagreement_warning(eops, bent, SIGMA, camera_fixed=False)
    assert calibrated is not None and "--self-calibration" not in calibrated
    assert "lever arm" in calibrated and "GNSS step that lasted" in calibrated
    # attitude alone is enough, as is position alone
    for by in (np.r_[0.0, 0.0, 0.0, 0.0, np.radians(14.0), 0.0], np.r_[10.0, 0, 0, 0, 0, 0]):
        assert nav_disagreement_warning(eops, _shift(nav, np.arange(0, 40, 2), by), SIGMA,
                                        camera_fixed=True) is not None


def test_dropouts_and_images_left_out_are_not_judged() -> None:
    eops, nav = _tables(40, seed=3)
    bent = _shift(nav, np.arange(0, 40, 2), np.r_[0.0, 0.0, 12.0, 0.0, 0.0, 0.0])
    gaps = bent.eop.copy()
    gaps[::2] = np.nan  # every shifted image a GNSS dropout: the rest agree
    dropped = NavTable(image_ids=nav.image_ids, times_s=nav.times_s, eop=gaps)
    assert nav_disagreement_warning(eops, dropped, SIGMA, camera_fixed=True) is None
    few = EopTable(image_ids=eops.image_ids[:7], eop=eops.eop[:7], sigma=eops.sigma[:7])
    assert nav_disagreement_warning(few, bent, SIGMA, camera_fixed=True) is None


def test_the_odd_fix_beyond_five_sigma_is_named_with_its_offset() -> None:
    """A GNSS blunder the tie points overruled was a weight in run.json only: now a line
    names the image, the fix's offset and its component (Seneca with one height 40 m off:
    the warning below, and nothing for the clean flight)."""
    eops, nav = _tables(40, seed=4)
    assert nav_fault_warnings(eops, nav, SIGMA) == []  # clean: within ~3 σ
    faults = _shift(nav, np.array([7]), np.r_[0.0, 0.0, 12.0, 0.0, 0.0, 0.0])
    faults = _shift(faults, np.array([20]), np.r_[0.0, 0.0, 0.0, 0.0, 0.0, np.radians(30.0)])
    lines = nav_fault_warnings(eops, faults, SIGMA)
    assert len(lines) == 2 and all("\n" not in line for line in lines)
    assert lines[0].startswith("img_007: its GPS/INS position lies 1")
    assert "(Z +1" in lines[0] and "a GNSS fault?" in lines[0]
    assert lines[1].startswith("img_020: its GPS/INS attitude lies 2")
    assert "° from the adjusted one (κ +2" in lines[1] and "an INS fault?" in lines[1]
    # a dropout is not judged; many faults are counted beyond the first ten
    gaps = faults.eop.copy()
    gaps[7] = np.nan
    dropped = NavTable(image_ids=nav.image_ids, times_s=nav.times_s, eop=gaps)
    assert len(nav_fault_warnings(eops, dropped, SIGMA)) == 1
    many = _shift(nav, np.arange(0, 36, 3), np.r_[0.0, 0.0, 12.0, 0.0, 0.0, 0.0])
    lines = nav_fault_warnings(eops, many, SIGMA)
    assert len(lines) == MAX_FAULT_WARNINGS + 1 and lines[-1].startswith("2 more GPS/INS fix")
