"""Drift check (seed 003 §3.2): the window re-adjusted from its observations every N images."""

from __future__ import annotations

import numpy as np
import pytest

from seqat.errors import ConfigError
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import StripSimConfig, simulate_strip


def test_drift_is_reported_and_small_on_the_paper_strip() -> None:
    f = simulate_strip(StripSimConfig(n_images=80, n_points=64), seed=1)
    est = SequentialAT(f.camera, SequentialOptions(drift_check_every=10))
    ups = [est.add_frame(fr) for fr in f.frames()]
    seq = [u for u in ups if u.stage == "sequential"]
    assert all(np.isfinite(u.drift_px) for u in seq)
    checked = [u.index for u in seq if np.isfinite(u.drift_m)]
    assert {10, 20, 30, 40, 50, 60, 70} <= set(checked)
    # a 0.3 m / 0.1 deg GPS/INS: the linear window is within centimetres of the refit
    assert max(u.drift_m for u in seq if np.isfinite(u.drift_m)) < 0.1
    assert max(u.drift_deg for u in seq if np.isfinite(u.drift_deg)) < 0.05
    assert max(u.drift_px for u in seq) < 1.0


def test_drift_check_needs_relinearisation() -> None:
    with pytest.raises(ConfigError, match="drift_check_every"):
        SequentialOptions(drift_check_every=5, relinearise_px=None)
