"""The warning that the adjusted EOPs and the GPS/INS disagree as a whole
(pipeline.run.nav_agreement)."""

from __future__ import annotations

import numpy as np

from pipeline.common.tables import EopTable, NavTable
from pipeline.run.nav_agreement import nav_disagreement_warning

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
