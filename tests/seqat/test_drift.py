"""Drift check (seed 003 §3.2): the window re-adjusted from its observations every N images."""

from __future__ import annotations

import numpy as np
import pytest

from seqat.errors import ConfigError
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight, StripSimConfig, simulate_strip


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


def test_the_refinement_follows_the_estimate_and_changes_no_result() -> None:
    """The drift check and the re-linearisation run once the update's estimate is out
    (``refine``): ``add_frame`` runs them and names them in its update; a caller that
    never calls ``refine`` has them run first in the next update and in finish(): every
    estimate the same, bit for bit."""
    f = simulate_strip(StripSimConfig(n_images=60, n_points=64), seed=3)
    a = SequentialAT(f.camera, SequentialOptions(drift_check_every=7))
    b = SequentialAT(f.camera, SequentialOptions(drift_check_every=7))
    ups_a, ups_b = [], []
    for k, fr in enumerate(f.frames()):
        ups_a.append(a.add_frame(fr))
        ups_b.append(b.add_frame(fr, refine=False))
        if ups_a[-1].stage == "sequential":  # the variances the next update reads first:
            assert a._w._diag is not None  # formed in the refinement, after a re-adjustment
        if k % 2:  # every other image refined by the caller, the others by the next update
            b.refine()
    seq = [u for u in ups_a if u.stage == "sequential"]
    assert seq and all(np.isfinite(u.drift_px) and u.refine_ms > 0 for u in seq)
    assert sum(np.isfinite(u.drift_m) for u in seq) >= 7  # the checks re-adjusted
    later = [u for u in ups_b if u.stage == "sequential"]
    assert all(np.isnan(u.drift_px) and np.isnan(u.refine_ms) for u in later)
    for ua, ub in zip(ups_a, ups_b, strict=True):  # each estimate is out before its refinement
        np.testing.assert_array_equal(ua.eop.eop, ub.eop.eop)
        np.testing.assert_array_equal(ua.eop.sigma, ub.eop.sigma)
    a.finish()
    b.finish()
    sa, sb = a.solution(), b.solution()
    np.testing.assert_array_equal([e.eop for e in sa.eops], [e.eop for e in sb.eops])
    np.testing.assert_array_equal([p.xyz_m for p in sa.points], [p.xyz_m for p in sb.points])
    assert a.relinearisations == b.relinearisations > 0


def test_drift_check_needs_relinearisation() -> None:
    with pytest.raises(ConfigError, match="drift_check_every"):
        SequentialOptions(drift_check_every=5, relinearise_px=None)


@pytest.mark.parametrize("named", [2, 20])
def test_a_singular_relinearisation_drops_a_few_points_or_is_skipped(
        short_strip: SimulatedFlight, monkeypatch: pytest.MonkeyPatch, named: int) -> None:
    """A re-linearisation that meets a singular system takes out the GPs its weakest
    direction lies on and tries again, when they are a few (points the data do not
    determine). When it names more than MAX_UNDETERMINED_AT_ONCE, the window as a whole lost
    its conditioning: the re-linearisation is skipped and no point is dropped (a weak-GPS
    block dropped 349 points at once, and 1725 later rays)."""
    from seqat import relinearise
    from seqat.information import RankDeficiency

    est = SequentialAT(short_strip.camera, SequentialOptions())
    for fr in list(short_strip.frames())[:30]:
        est.add_frame(fr)
    w = est._w
    gps = [k for k in w.keys if k[0] == "p"]
    assert len(gps) >= named
    offsets = np.array([w.offset[k] for k in gps[:named]])
    tries = []

    def singular(self: SequentialAT, threshold_px: float | None = None,
                 force: bool = False) -> None:
        tries.append(1)
        if len(tries) == 1:
            raise RankDeficiency("singular", offsets, offsets)

    monkeypatch.setattr(SequentialAT, "_relinearise", singular)
    n_points, skipped = len(est.undetermined), est.relinearisations_skipped
    est._relinearise_if_needed()
    if named <= relinearise.MAX_UNDETERMINED_AT_ONCE:
        assert len(est.undetermined) == n_points + named and len(tries) == 2
        assert est.relinearisations_skipped == skipped
    else:
        assert len(est.undetermined) == n_points and len(tries) == 1
        assert est.relinearisations_skipped == skipped + 1
        assert all(k in w.offset for k in gps[:named])


def _image_rows_removed(est: SequentialAT) -> np.ndarray:
    """The window's information minus its image rows (its factors in the window): with no
    image departed, the GPS/INS rows alone."""
    from seqat.assembly import factor_information
    from seqat.types import EOP_SIZE

    w = est._w
    rows = est._factors.in_window(w)
    assert rows is not None and w.L is not None
    e_idx, p_idx = rows.columns(w)
    n = w.x.size
    F = factor_information(rows.Je, rows.Jp, rows.w, rows.img,
                           np.concatenate([e_idx, p_idx], axis=1), n)
    L = w.L.toarray() if hasattr(w.L, "toarray") else np.asarray(w.L)
    nav = np.zeros(n)
    for key in w.keys:
        if key[0] == "e":
            row = est._nav_rows[key[1]]
            nav[w.index(key)] = row[12:] / row[EOP_SIZE:12] ** 2
    return (L - F.toarray()) - np.diag(nav)


def test_an_undetermined_point_leaves_with_its_rays_and_can_come_back(
        short_strip: SimulatedFlight) -> None:
    """A GP taken out as undetermined takes its rays' information out of the window (Sim
    gives its rows no weight), not only its own rows and columns of ``L``: those would
    keep the rays' image blocks, a control point at a depth the data do not determine (on
    Seneca's every second image 0.6 m between Seq-R and Sim). Its window rays wait again
    among the pending ones, so finish() brings the point back when they determine it:
    the finished Seq-F is then Sim's solution."""
    from seqat.simultaneous import SimOptions, SimultaneousAT

    opts = SequentialOptions(correlation_threshold=None, robust_scale=None,
                             nav_robust_scale=None)
    est = SequentialAT(short_strip.camera, opts)
    for fr in list(short_strip.frames())[:20]:
        est.add_frame(fr)
    w = est._w
    scale = float(np.abs(w.L.toarray() if hasattr(w.L, "toarray") else w.L).max())
    assert np.abs(_image_rows_removed(est)).max() < 1e-9 * scale
    gone = [k for k in w.keys if k[0] == "p"][:2]
    rays = {k[1]: int(np.count_nonzero(est._factors.in_window(w).pt == k[1])) for k in gone}
    est._drop_undetermined(gone)
    assert np.abs(_image_rows_removed(est)).max() < 1e-9 * scale
    assert est.undetermined == [est._point_ids[k[1]] for k in gone]
    assert {p: len(est._pending[p]) for p in rays} == rays
    for fr in list(short_strip.frames())[20:]:
        est.add_frame(fr)
    est.finish()
    assert est.undetermined == []
    sim = SimultaneousAT(short_strip.camera, SimOptions(robust_scale=None, nav_robust_scale=None),
                         refit_every_frame=False)
    for fr in short_strip.frames():
        sim.add_frame(fr)
    got, want = est.solution(), sim.solution()
    assert {p.point_id for p in got.points} == {p.point_id for p in want.points}
    a, b = np.array([e.eop for e in got.eops]), np.array([e.eop for e in want.eops])
    np.testing.assert_allclose(a[:, :3], b[:, :3], rtol=0, atol=1e-5)
    np.testing.assert_allclose(a[:, 3:], b[:, 3:], rtol=0, atol=1e-8)
