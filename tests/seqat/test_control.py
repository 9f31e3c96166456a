"""Ground control points in Sim, Seq-F and Seq-R (seqat.types.ControlPoint)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqat.errors import InputDataError
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight
from seqat.simultaneous import SimOptions, SimultaneousAT
from seqat.types import ControlPoint, PinholeCamera, Solution

#: A GNSS bias of the whole flight (m): the datum the nav gives is off by it.
NAV_BIAS = np.array([1.0, -0.8, 0.0, 0.0, 0.0, 0.0])


def _control(f: SimulatedFlight, sigma: tuple[float, float, float] = (0.01, 0.01, 0.01),
             where: tuple[int, ...] = (2, 16, 32, 45)) -> list[ControlPoint]:
    """Control points at truth, spread along the strip (ranks of their easting)."""
    order = np.argsort(f.truth_xyz[:, 0])
    return [ControlPoint(point_id=f.point_ids[j], xyz_m=f.truth_xyz[j],
                         sigma_m=np.asarray(sigma)) for j in order[list(where)]]


def _run(f: SimulatedFlight, method: str, control: list[ControlPoint],
         robust: float | None = 3.0) -> Solution:
    if method == "sim":
        est = SimultaneousAT(f.camera, SimOptions(robust_scale=robust),
                             refit_every_frame=False, control=control)
    else:
        est = SequentialAT(f.camera, SequentialOptions(
            correlation_threshold=None if method == "seq-f" else 0.1,
            engine="inverse" if method == "seq-f-inverse" else "information",
            robust_scale=robust), control=control)
    for fr in f.frames():
        est.add_frame(fr)
    if method != "sim":
        est.finish()
    return est.solution()


def _errors(sol: Solution, f: SimulatedFlight, leave_out: list[ControlPoint]) -> np.ndarray:
    """Coordinate errors of the adjusted points that are not control points, (m, 3)."""
    truth = dict(zip(f.point_ids, f.truth_xyz, strict=True))
    skip = {c.point_id for c in leave_out}
    return np.array([p.xyz_m - truth[p.point_id] for p in sol.points
                     if p.point_id not in skip])


def _biased(f: SimulatedFlight) -> SimulatedFlight:
    return dataclasses.replace(f, nav_eop=f.nav_eop + NAV_BIAS)


@pytest.mark.parametrize("method", ["seq-f", "seq-f-inverse"])
def test_sequential_with_control_equals_sim(short_strip: SimulatedFlight, method: str) -> None:
    """Sequential == batch with ground control (least squares, one linearisation at the
    end): the control rows enter the update of the image that first sees the point."""
    f = _biased(short_strip)
    ctrl = _control(f)
    sim = _run(f, "sim", ctrl, robust=None)
    seq = _run(f, method, ctrl, robust=None)
    ea = np.array([e.eop for e in sim.eops])
    eb = np.array([e.eop for e in seq.eops])
    assert np.max(np.abs(ea[:, :3] - eb[:, :3])) < 1e-5
    assert np.max(np.abs(ea[:, 3:] - eb[:, 3:])) < 1e-8
    pa = {p.point_id: p for p in sim.points}
    for p in seq.points:
        assert np.allclose(p.xyz_m, pa[p.point_id].xyz_m, rtol=0, atol=1e-5)
        assert np.allclose(p.sigma_m, pa[p.point_id].sigma_m, rtol=1e-4)
    assert seq.redundancy == sim.redundancy
    assert seq.sigma0 == pytest.approx(sim.sigma0, rel=1e-6)


@pytest.mark.parametrize("method", ["sim", "seq-r"])
def test_control_removes_a_gnss_bias(short_strip: SimulatedFlight, method: str) -> None:
    """A 1.3 m horizontal GNSS bias moves every point by it; four control points at 1 cm
    bring the other points back (every default: robust loss, Seq-R window)."""
    f = _biased(short_strip)
    ctrl = _control(f)
    free = _errors(_run(f, method, []), f, ctrl).mean(axis=0)
    held = _errors(_run(f, method, ctrl), f, ctrl).mean(axis=0)
    assert np.hypot(*free[:2]) > 1.0
    assert np.hypot(*held[:2]) < 0.15 * np.hypot(*free[:2])
    assert abs(held[2]) < 0.1


def test_a_control_point_needs_one_ray(short_strip: SimulatedFlight) -> None:
    """A tie point seen once is never adjusted; as a control point it is, at its surveyed
    coordinates within its sigma, in Sim and in the sequential stage."""
    f = short_strip
    # a point first seen after the initial stage, its rays but the first removed
    late = f.obs_image >= 20
    j = int(f.obs_point[np.flatnonzero(late)[0]])
    rows = np.flatnonzero(f.obs_point == j)
    keep = np.ones(f.obs_point.size, dtype=bool)
    keep[rows[1:]] = False
    one = dataclasses.replace(f, obs_image=f.obs_image[keep], obs_point=f.obs_point[keep],
                              obs_uv=f.obs_uv[keep])
    pid = f.point_ids[j]
    ctrl = [ControlPoint(point_id=pid, xyz_m=f.truth_xyz[j], sigma_m=np.full(3, 0.05))]
    for method in ("sim", "seq-r"):
        assert pid not in {p.point_id for p in _run(one, method, []).points}
        got = {p.point_id: p for p in _run(one, method, ctrl).points}[pid]
        assert np.all(np.abs(got.xyz_m - f.truth_xyz[j]) < 3 * 0.05)
        assert np.all(got.sigma_m < 0.05 + 1e-9) and np.all(got.sigma_m > 0)


def test_a_free_coordinate_adds_no_redundancy(short_strip: SimulatedFlight) -> None:
    """Planimetric control (sigma z = inf): two observations per point, not three."""
    f = short_strip
    base = _run(f, "sim", [], robust=None).redundancy
    xy = _control(f, sigma=(0.02, 0.02, np.inf))
    assert _run(f, "sim", xy, robust=None).redundancy == base + 2 * len(xy)
    seq = _run(f, "seq-f", xy, robust=None)
    assert seq.redundancy == base + 2 * len(xy)


def test_bad_control_points_are_input_errors() -> None:
    with pytest.raises(InputDataError, match="sigma_m"):
        ControlPoint(point_id="a", xyz_m=np.zeros(3), sigma_m=np.array([0.01, 0.0, 0.01]))
    with pytest.raises(InputDataError, match="finite sigma"):
        ControlPoint(point_id="a", xyz_m=np.zeros(3), sigma_m=np.full(3, np.inf))
    with pytest.raises(InputDataError, match="xyz_m"):
        ControlPoint(point_id="a", xyz_m=np.array([0.0, np.nan, 1.0]), sigma_m=np.ones(3))
    cp = ControlPoint(point_id="a", xyz_m=np.zeros(3), sigma_m=np.ones(3))
    cam = PinholeCamera(f_px=1000.0, cx_px=500.0, cy_px=400.0, width_px=1000, height_px=800)
    with pytest.raises(InputDataError, match="twice"):
        SimultaneousAT(cam, SimOptions(), control=[cp, cp])
    with pytest.raises(InputDataError, match="twice"):
        SequentialAT(cam, SequentialOptions(), control=[cp, cp])
