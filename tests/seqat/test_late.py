"""Late observations (docs/algorithm.md, *Late observations*): a frame carrying observations
of earlier images, in Sim, Seq-F and Seq-R."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqat.errors import InputDataError
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight, StripSimConfig, simulate_strip
from seqat.simultaneous import SimOptions, SimultaneousAT
from seqat.types import Frame, Solution

#: Sequential == batch of the same linearised system (as tests/seqat/test_sequential.py).
BATCH_REL_TOL = 1e-9


def late_frames(flight: SimulatedFlight, every: int = 3, delay: int = 1) -> list[Frame]:
    """The flight's frames with every ``every``-th observation of an image moved to a later
    frame as a late observation: to the frame of the point's next ray at least ``delay``
    images later (as the tracker emits it: with the image that matched it), if any. Some
    moved rays are a point's first (the point is born from the late ray and the new one),
    others arrive when the point is estimated already (a row of two existing parameters)."""
    frames = list(flight.frames())
    index = {fr.image_id: k for k, fr in enumerate(frames)}
    seen_at: dict[str, list[int]] = {}
    for k, fr in enumerate(frames):
        for pid in fr.point_ids:
            seen_at.setdefault(pid, []).append(k)
    keep: list[list[bool]] = [[True] * len(fr.point_ids) for fr in frames]
    late: list[list[tuple[str, str, np.ndarray]]] = [[] for _ in frames]
    n = 0
    for k, fr in enumerate(frames):
        for q, (pid, uv) in enumerate(zip(fr.point_ids, fr.uv_px, strict=True)):
            later = [m for m in seen_at[pid] if m >= k + delay]
            n += 1
            if n % every or not later or k < 1:
                continue
            keep[k][q] = False
            late[later[0]].append((fr.image_id, pid, uv))
    out = []
    for k, fr in enumerate(frames):
        sel = np.asarray(keep[k], dtype=bool)
        out.append(dataclasses.replace(
            fr, point_ids=tuple(p for p, s in zip(fr.point_ids, sel, strict=True) if s),
            uv_px=fr.uv_px[sel], late_image_ids=tuple(r[0] for r in late[k]),
            late_point_ids=tuple(r[1] for r in late[k]),
            late_uv_px=np.array([r[2] for r in late[k]]).reshape(-1, 2)))
    assert all(index[i] < k for k, fr in enumerate(out) for i in fr.late_image_ids)
    return out


def _eop_matrix(sol: Solution) -> np.ndarray:
    return np.array([e.eop for e in sol.eops])


def _columns(keys: list[tuple[str, int]]) -> list[tuple[str, int, int]]:
    return [(k, i, c) for (k, i) in keys for c in range(6 if k == "e" else 3)]


def test_sim_takes_late_observations_as_ordinary_ones(short_strip: SimulatedFlight) -> None:
    """The same observations, some arriving late: the same Sim solution."""
    frames = late_frames(short_strip)
    assert sum(fr.n_late for fr in frames) > 50
    a = SimultaneousAT(short_strip.camera, SimOptions(), refit_every_frame=False)
    b = SimultaneousAT(short_strip.camera, SimOptions(), refit_every_frame=False)
    for fr in short_strip.frames():
        a.add_frame(fr)
    for fr in frames:
        b.add_frame(fr)
    sa, sb = a.solution(), b.solution()
    np.testing.assert_allclose(_eop_matrix(sb), _eop_matrix(sa), rtol=0, atol=1e-7)
    assert sb.sigma0 == pytest.approx(sa.sigma0, rel=1e-9)
    assert sb.redundancy == sa.redundancy and len(sb.points) == len(sa.points)


@pytest.mark.parametrize("engine", ["information", "inverse"])
def test_seq_f_with_late_observations_equals_batch_of_same_linearisation(
        short_strip: SimulatedFlight, engine: str) -> None:
    """Late rays as pending rays (points born from a late ray and a new one) and as rows of
    two existing parameters: Seq-F equals the batch solution of its recorded rows."""
    est = SequentialAT(short_strip.camera, SequentialOptions(
        correlation_threshold=None, initial_images=5, max_update_iterations=3, engine=engine,
        relinearise_px=None), record=True)
    ups = [est.add_frame(fr) for fr in late_frames(short_strip)]
    assert sum(u.late_used for u in ups[5:]) > 30
    assert all(u.observations_skipped == 0 for u in ups)
    assert est.initial_state is not None and est.recorded
    keys0, x0, Q0 = est.initial_state
    cols = _columns(est._w.keys)
    pos = {c: k for k, c in enumerate(cols)}
    n = len(cols)
    N, c = np.zeros((n, n)), np.zeros(n)
    i0 = np.array([pos[k] for k in _columns(keys0)])
    N0 = np.linalg.inv(Q0)
    N[np.ix_(i0, i0)] += N0
    c[i0] += N0 @ x0
    for rec in est.recorded:
        idx = np.array([pos[k] for k in rec.columns])
        WA = rec.w[:, None] * rec.A
        N[np.ix_(idx, idx)] += rec.A.T @ WA
        c[idx] += WA.T @ rec.b
    x_batch = np.linalg.solve(N, c)
    Q_batch = np.linalg.inv(N)
    assert np.max(np.abs(est._w.x - x_batch)) / np.max(np.abs(x_batch)) < BATCH_REL_TOL
    sd = np.sqrt(np.diagonal(Q_batch))
    assert np.max(np.abs(est._w.Q - Q_batch) / np.outer(sd, sd)) < BATCH_REL_TOL


def test_seq_f_with_late_observations_agrees_with_sim(short_strip: SimulatedFlight) -> None:
    """Finished (re-linearised) Seq-F and Seq-R with late observations agree with Sim on the
    same observations as Seq-F without late ones does."""
    frames = late_frames(short_strip)
    sim = SimultaneousAT(short_strip.camera, SimOptions(), refit_every_frame=False)
    for fr in frames:
        sim.add_frame(fr)
    ref = _eop_matrix(sim.solution())
    for thr in (None, 0.1):
        est = SequentialAT(short_strip.camera, SequentialOptions(correlation_threshold=thr))
        for fr in frames:
            est.add_frame(fr)
        est.finish()
        sol = est.solution()
        E = _eop_matrix(sol)
        assert np.sqrt(np.mean((E - ref)[:, :3] ** 2)) < 0.01  # metres
        assert np.degrees(np.sqrt(np.mean((E - ref)[:, 3:] ** 2))) < 0.003


@pytest.mark.parametrize("options", [
    {},  # re-opened
    {"reopen_max_age": 0},  # the paper: skipped
    {"smoothing_lag": 10},  # finalised: skipped
    {"smoothing": False},  # re-opened with the frozen value
])
def test_seq_r_late_ray_of_a_departed_image(options: dict[str, object]) -> None:
    """Late rays arriving 8 images after their image, which left the Seq-R window (of ~10
    images at this threshold) in between: re-opened (or skipped where it cannot re-open),
    never an exception; sigmas finite and positive."""
    f = simulate_strip(StripSimConfig(n_images=60, n_points=80), seed=3)
    frames = late_frames(f, every=4, delay=8)
    est = SequentialAT(f.camera, SequentialOptions(correlation_threshold=0.5,
                                                   **options))  # type: ignore[arg-type]
    ups = [est.add_frame(fr) for fr in frames]
    late_at = [k for k, fr in enumerate(frames) if fr.n_late]
    assert late_at and sum(u.images_left_window for u in ups) > 10  # images did leave
    for u in ups[10:]:  # the sequential stage
        assert np.all(np.isfinite(u.eop.sigma)) and np.all(u.eop.sigma > 0)
        assert np.isfinite(u.sigma0) and u.sigma0 > 0
    used = sum(u.late_used for u in ups)
    skipped = sum(u.observations_skipped for u in ups)
    if options.get("reopen_max_age") == 0:
        assert skipped > 0 and est.reopened == 0
    elif not options.get("smoothing_lag"):
        assert used == sum(fr.n_late for fr in frames) and est.reopened > 0
    est.finish()
    sol = est.solution()
    assert all(np.all(np.isfinite(e.sigma)) and np.all(e.sigma > 0) for e in sol.eops)
    assert all(np.all(np.isfinite(p.xyz_m)) for p in sol.points)


def test_frame_validation_of_late_observations() -> None:
    base = {"image_id": "b", "nav_eop": np.zeros(6), "nav_sigma": np.ones(6),
            "point_ids": ("p",), "uv_px": np.zeros((1, 2))}
    fr = Frame(**base, late_image_ids=("a",), late_point_ids=("p",),
               late_uv_px=[[1.0, 2.0]])  # type: ignore[arg-type]
    assert fr.n_late == 1 and fr.late_uv_px.shape == (1, 2)
    bad = [({"late_image_ids": ("a",), "late_point_ids": (), "late_uv_px": np.zeros((0, 2))},
            "late image ids"),
           ({"late_image_ids": ("b",), "late_point_ids": ("q",), "late_uv_px": np.zeros((1, 2))},
            "frame's own image"),
           ({"late_image_ids": ("a", "a"), "late_point_ids": ("q", "q"),
             "late_uv_px": np.zeros((2, 2))}, "appears twice"),
           ({"late_image_ids": ("a",), "late_point_ids": ("q",),
             "late_uv_px": [[np.nan, 0.0]]}, "finite")]
    for kw, text in bad:
        with pytest.raises(InputDataError, match=text):
            Frame(**base, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("stage", ["initial", "sequential", "sim"])
def test_late_observation_of_an_unknown_image_is_an_input_error(
        short_strip: SimulatedFlight, stage: str) -> None:
    frames = list(short_strip.frames())
    k = 2 if stage != "sequential" else 8
    est = (SimultaneousAT(short_strip.camera) if stage == "sim"
           else SequentialAT(short_strip.camera, SequentialOptions(initial_images=5)))
    for fr in frames[:k]:
        est.add_frame(fr)
    bad = dataclasses.replace(frames[k], late_image_ids=("nowhere",), late_point_ids=("x",),
                              late_uv_px=np.zeros((1, 2)))
    with pytest.raises(InputDataError, match="late observation of image 'nowhere'"):
        est.add_frame(bad)
