"""GTSAM fixed-lag smoother beside Seq-R on the benchmark's simulated strip (same run, same seed).

Optional benchmark dependency: GTSAM's Python wheel (``pip install gtsam``, or the project's
``bench`` extra); nothing else in seqat imports this module or needs gtsam.

What is compared
----------------
For each seed the strip of :mod:`pipeline.bench.strip` (``simulation:`` of a ``kind: observations``
config, :func:`seqat.simulate.simulate_strip`) is streamed image by image through

* **Seq-R**: :class:`seqat.sequential.SequentialAT` with
  ``SequentialOptions(correlation_threshold=0.1)``, as ``seqat bench`` runs it; the time is
  ``ImageUpdate.processing_ms`` of each ``add_frame``, the update and the re-linearisation
  after it (as GTSAM's update re-linearises inside; sequential stage; the initial simultaneous
  adjustment of the first ``initial_images`` images is excluded, as in ``seqat bench``), and
  the CPU time (``time.process_time``) of the whole ``add_frame`` call;
* **GTSAM** ``gtsam.IncrementalFixedLagSmoother`` (iSAM2 underneath; in gtsam 4.3 it is in the
  main ``gtsam`` module, not ``gtsam_unstable``), once per lag. The time is the
  ``smoother.update(...)`` call alone (``update_ms``, and its CPU time); building the image's
  factors, initial values and timestamps, the landmark triangulations included, is reported apart
  (``build_ms``). Both are reported over the same images as Seq-R's timed ones, so the ratio of
  medians is a same-run, same-images ratio.

The GTSAM problem (one update per image)
----------------------------------------
* Pose ``X(i)`` per image: ``Pose3`` world-from-camera in GTSAM's camera frame (x right, y down,
  z forward; OpenCV), i.e. ``R_gtsam = R @ diag(1, -1, -1)`` with seqat's camera-to-world
  ``R = Rx(omega) Ry(phi) Rz(kappa)`` (camera x right, y up, looking along -z;
  docs/conventions.md), and the projection centre minus a local origin (the rounded first nav
  position, for conditioning, as the seqat estimators do). Intrinsics ``Cal3_S2(f, f, 0, cx,
  cy)``: GTSAM's ``u = f x/z + cx, v = f y/z + cy`` is then seqat's ``u = cx - f p_x/p_z,
  v = cy + f p_y/p_z`` exactly (:func:`check_conversion`: the simulated noise-free image points
  are reproduced to < 1e-6 px, also in ``tests/pipeline/bench/test_bench_gtsam.py``).
* GPS/INS prior ``PriorFactorPose3`` on the nav EOP. Its error is ``Logmap(prior^-1 pose)``,
  tangent order **rotation first** (body frame of the GTSAM camera), then translation (also in
  that body frame). The nav sigmas are mapped to first order (:func:`prior_covariance`): for
  the angles, ``d xi = diag(1, -1, -1) J d[omega, phi, kappa]`` with the body-frame Jacobian
  of the Euler sequence ``J = [Rz(k)^T Ry(p)^T e_x, Rz(k)^T e_y, e_z]``; for the position
  ``d t_body = R_gtsam^T d X0``. The resulting 6 x 6 covariance is used as a
  ``noiseModel.Diagonal`` whenever its correlations are below 1e-3, otherwise as a full
  ``noiseModel.Gaussian`` (the paper strip has equal angle sigmas and an isotropic position
  sigma, so only the non-orthogonality of ``J`` at phi != 0 correlates the angles: up to 0.024
  at its 0.5 deg attitude wander; both kinds occur and are reported). An infinite nav sigma
  (GNSS dropout) is replaced by 1e6.
* Image points: ``GenericProjectionFactorCal3_S2`` with an isotropic ``sigma_px`` noise.
  A landmark ``L(j)`` enters once it has been seen in two images whose poses are still in the
  smoother; its initial value is ``gtsam.triangulatePoint3`` (DLT) from those rays with the
  current pose estimates (the new image: its nav EOP); its earlier observations are added then.
  (Seq-R waits for an 8 deg ray spread before a point is born; GTSAM takes it at two rays.)
* Timestamps: the image index. A pose has its image's index; a landmark the index of the last
  image that saw it (re-sent with every new observation), so a landmark is marginalised only
  after every pose seeing it. The smoother marginalises keys whose timestamp is below
  ``current - lag``: the window holds ``lag + 1`` images. Observations of a landmark that was
  already marginalised, or of departed poses, are dropped and counted.
* iSAM2: Gauss-Newton, relinearise threshold 0.01 (tangent units), ``relinearizeSkip = 1``;
  one ``update`` per image (``extra_updates`` more empty updates can be asked for: each is one
  more iSAM2 step, timed into ``update_ms``).
* Sigmas (``--sigma pose``, ``--sigma all``; one more run per lag and kind): Seq-R's update
  publishes the new image's EOP sigmas and the r.m.s. sigma of the window's GPs (the
  precision monitoring after every image of docs/algorithm.md), GTSAM's ``update`` nothing of
  the kind. Such a run then reads ``marginalCovariance`` of the new pose (``pose``), and of
  every landmark in the smoother (``all``), after each update; the time is reported as
  ``σ`` and its ratio column is against update + σ per image (an error there ends the run
  as one in ``update`` does). The updates of such a run are themselves slower than the plain
  run's (iSAM2 keeps what the marginals computed in its Bayes tree), which its ``update``
  column shows.
* Estimates: after every update ``calculateEstimate()`` (outside ``update_ms``; its own time is
  reported as ``calculate_estimate_ms``) refreshes the latest estimate of every key still in
  the smoother (and tells which keys are still there); a departed key keeps its last estimate
  before marginalisation (like Seq-R's ``solution(smoothed=False)``). The final table uses these.
* A GTSAM exception in ``update`` (``IndeterminantLinearSystemException`` at marginalisation,
  cheirality, ...) ends that run: it is reported (image, type, message) with the accuracy of
  the images processed so far, and the benchmark goes on.

Threads: the PyPI gtsam 4.3 wheel links neither TBB nor OpenMP (checked from its bundled
libraries, reported in the JSON), so iSAM2 runs on one thread; numpy/BLAS are limited to one
thread (threadpoolctl, plus ``OMP_NUM_THREADS`` etc.: set them in the environment for
``seqat bench gtsam``; ``python -m pipeline.bench.gtsam`` sets them itself before numpy) and
the process's thread count is recorded while GTSAM runs.

Outputs in ``--out``: ``bench_gtsam.json`` and ``bench_gtsam.md``. Re-run::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \\
        seqat bench gtsam --config configs/paper_sim.yaml --seed 1 --seed 2 --seed 3 \\
        --lag 10 --lag 20 --lag 25 --lag 400 --out docs/bench_gtsam

(defaults: ``--config configs/paper_sim.yaml --seed 1 --lag 10 --lag 20 --out out/bench``;
``--extra-updates N``; with gtsam installed elsewhere: ``PYTHONPATH=/path/to/gtsam-pkgs seqat
bench gtsam ...``; without gtsam the command exits 2 with one line naming the ``bench``
extra). Lag 25 is Seq-R's median window on this strip; lag 400 (longer than the strip) never
marginalises: plain iSAM2, the batch solution.

Findings (docs/bench_gtsam/bench_gtsam.md): no GTSAM error at any lag tried (0-3, 5, 10, 20,
25, 50, 400; seeds 1-3, not every pair); the accuracy of a departed landmark grows with the lag
(later images still tie it through shared points): lag 25 matches Seq-R's real-time values,
lag 400 the RTS-smoothed ones; lags 0-2 leave GPs off by 0.2-2.8 m (presumably the marginals,
linearised at two-ray triangulations; not verified). With ``--sigma`` (seeds 1-3, lags 10 and
25; docs/bench_gtsam_sigma/bench_gtsam.md): the new pose's marginal costs about one more
update (lag 25: 1.14 ms update, 2.45 ms with it), every landmark's ten (12.7 ms).
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # before numpy is imported (python -m); importers keep their env
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from pipeline.bench.common import load_average, load_sim_config, machine  # noqa: E402
from pipeline.bench.gtsam_report import render_markdown, summary_table  # noqa: E402
from pipeline.bench.report import INITIAL_STAGE  # noqa: E402
from pipeline.run.store import to_jsonable  # noqa: E402
from seqat.errors import ConfigError  # noqa: E402
from seqat.geometry import angles_from_rotation, project, rotation_matrix, wrap_angle  # noqa: E402
from seqat.sequential import SequentialAT, SequentialOptions  # noqa: E402
from seqat.simulate import SimulatedFlight, simulate_strip  # noqa: E402
from seqat.types import FloatArray, PinholeCamera  # noqa: E402

#: seqat camera frame (x right, y up, z back) -> GTSAM/OpenCV camera frame (x right, y down,
#: z forward): a half turn about x, its own inverse.
CAM_FLIP = np.diag([1.0, -1.0, -1.0])
#: Correlations of the mapped prior covariance below this: use a diagonal noise model.
DIAGONAL_CORRELATION_TOL = 1e-3
#: Stand-in for an infinite nav sigma (no constraint) in the GTSAM prior.
UNCONSTRAINED_SIGMA = 1e6
#: iSAM2 relinearisation threshold (tangent units: rad, m).
RELINEARIZE_THRESHOLD = 0.01
#: Seq-R as seqat bench runs it.
SEQ_R_THRESHOLD = 0.1
#: The error (exit 2) of ``seqat bench gtsam`` when gtsam cannot be imported.
MISSING_GTSAM = ("seqat bench gtsam needs the optional package gtsam "
                 "(pip install 'seqat[bench]')")
#: ``seqat bench gtsam`` defaults.
DEFAULT_CONFIG = Path("configs/paper_sim.yaml")
DEFAULT_SEEDS = (1,)
DEFAULT_LAGS = (10, 20)
#: ``--sigma`` choices: the marginal covariances a GTSAM run reads after each update, as
#: Seq-R publishes them (its ``ImageUpdate``: the new image's EOP sigmas and the r.m.s. sigma
#: of the window's GPs): ``pose`` the new pose's, ``all`` that and every landmark's.
SIGMA_KINDS = {"pose": "σ new pose", "all": "σ new pose, landmarks"}


def _gtsam():  # type: ignore[no-untyped-def]
    """The gtsam module, imported on first use (:class:`ConfigError` without it)."""
    try:
        import gtsam
    except ImportError as err:
        raise ConfigError(MISSING_GTSAM) from err
    return gtsam


# ---------------------------------------------------------------------------- conversion
def eop_to_pose3(eop: FloatArray, origin: FloatArray):  # type: ignore[no-untyped-def]
    """seqat EOP ``[X, Y, Z, omega, phi, kappa]`` (world) -> GTSAM ``Pose3`` world-from-camera
    (GTSAM camera frame) in the local frame ``world - origin``."""
    gtsam = _gtsam()
    e = np.asarray(eop, dtype=np.float64)
    R = rotation_matrix(e[3], e[4], e[5]) @ CAM_FLIP
    return gtsam.Pose3(gtsam.Rot3(R), np.asarray(e[:3] - origin, dtype=np.float64))


def pose3_to_eop(pose, origin: FloatArray) -> FloatArray:  # type: ignore[no-untyped-def]
    """Inverse of :func:`eop_to_pose3`."""
    R = np.asarray(pose.rotation().matrix()) @ CAM_FLIP
    out = np.empty(6)
    out[:3] = np.asarray(pose.translation()).reshape(3) + origin
    out[3:] = angles_from_rotation(R)
    return out


def calibration(camera: PinholeCamera):  # type: ignore[no-untyped-def]
    """seqat's ideal pinhole camera as GTSAM ``Cal3_S2`` (square pixels, no skew)."""
    return _gtsam().Cal3_S2(camera.f_px, camera.f_px, 0.0, camera.cx_px, camera.cy_px)


def attitude_jacobian(omega: float, phi: float, kappa: float) -> FloatArray:
    """``d xi / d[omega, phi, kappa]``: body-frame (right) rotation increment of the GTSAM
    camera, ``R_gtsam(a + da) = R_gtsam(a) Exp(J da)`` to first order."""
    Rz = rotation_matrix(0.0, 0.0, kappa)
    Ry = rotation_matrix(0.0, phi, 0.0)
    J_seqat = np.column_stack([Rz.T @ Ry.T @ [1.0, 0.0, 0.0], Rz.T @ [0.0, 1.0, 0.0],
                               [0.0, 0.0, 1.0]])
    return CAM_FLIP @ J_seqat


def prior_covariance(eop: FloatArray, sigma: FloatArray) -> FloatArray:
    """First-order 6 x 6 covariance of the GPS/INS prior in ``Pose3`` tangent order
    ``[rotation (body), translation (body)]``."""
    e = np.asarray(eop, dtype=np.float64)
    s = np.where(np.isfinite(sigma), sigma, UNCONSTRAINED_SIGMA)
    J = attitude_jacobian(e[3], e[4], e[5])
    Rg = rotation_matrix(e[3], e[4], e[5]) @ CAM_FLIP
    cov = np.zeros((6, 6))
    cov[:3, :3] = J @ np.diag(s[3:] ** 2) @ J.T
    cov[3:, 3:] = Rg.T @ np.diag(s[:3] ** 2) @ Rg
    return cov


def _correlation(cov: FloatArray) -> float:
    d = np.sqrt(np.diag(cov))
    c = cov / np.outer(d, d)
    return float(np.max(np.abs(c - np.diag(np.diag(c)))))


def prior_noise(eop: FloatArray, sigma: FloatArray):  # type: ignore[no-untyped-def]
    """The prior's noise model and the largest correlation of its mapped covariance."""
    gtsam = _gtsam()
    cov = prior_covariance(eop, sigma)
    rho = _correlation(cov)
    if rho < DIAGONAL_CORRELATION_TOL:
        return gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.diag(cov))), rho
    return gtsam.noiseModel.Gaussian.Covariance(cov), rho


def check_conversion(flight: SimulatedFlight) -> dict[str, float]:
    """Largest pixel difference over every observation of ``flight`` between a
    ``PinholeCameraCal3_S2`` built from the true EOP and (a) :func:`seqat.geometry.project`,
    (b) the observed uv (equal to (a) for a noise-free simulation), and the largest EOP round
    trip error (m, rad)."""
    gtsam = _gtsam()
    origin = np.round(flight.truth_eop[0, :3])
    K = calibration(flight.camera)
    oi, oj = flight.obs_image, flight.obs_point
    ref = project(flight.truth_eop[oi], flight.truth_xyz[oj], flight.camera)
    uv = np.empty_like(ref)
    cams = [gtsam.PinholeCameraCal3_S2(eop_to_pose3(e, origin), K) for e in flight.truth_eop]
    for k in range(oi.size):
        uv[k] = cams[oi[k]].project(flight.truth_xyz[oj[k]] - origin)
    back = np.asarray([pose3_to_eop(c.pose(), origin) for c in cams])
    d = back - flight.truth_eop
    return {
        "max_px_vs_seqat_project": float(np.max(np.abs(uv - ref))),
        "max_px_vs_observed": float(np.max(np.abs(uv - flight.obs_uv))),
        "max_roundtrip_m": float(np.max(np.abs(d[:, :3]))),
        "max_roundtrip_rad": float(np.max(np.abs(wrap_angle(d[:, 3:])))),
    }


# ---------------------------------------------------------------------------- runs
def _threads() -> int:
    try:
        for line in Path("/proc/self/status").read_text(encoding="utf-8").splitlines():
            if line.startswith("Threads:"):
                return int(line.split()[1])
    except OSError:
        pass
    return -1


def gtsam_thread_libraries() -> list[str]:
    """Bundled/linked libraries of the gtsam wheel that could start threads (TBB, OpenMP)."""
    gtsam = _gtsam()
    root = Path(gtsam.__file__).resolve().parent.parent
    names = [p.name for d in (root / "gtsam.libs", root / "gtsam") if d.is_dir()
             for p in d.iterdir()]
    return sorted(n for n in names if any(s in n.lower() for s in ("tbb", "omp")))


@dataclass(kw_only=True)
class _MethodRun:
    label: str
    lag: int | None
    update_ms: list[float]
    build_ms: list[float]
    timed: list[bool]
    cpu_ms: list[float]  # CPU time (process_time) of the same call: Seq-R's whole add_frame
    eop: FloatArray  # (n_processed, 6)
    point_idx: np.ndarray
    xyz: FloatArray
    extra: dict[str, object] = field(default_factory=dict)
    failure: dict[str, object] | None = None


def run_seq_r(flight: SimulatedFlight) -> _MethodRun:
    """Seq-R with ``correlation_threshold=0.1`` (``seqat bench``'s headline run)."""
    est = SequentialAT(flight.camera, SequentialOptions(correlation_threshold=SEQ_R_THRESHOLD))
    ups, cpu_ms = [], []
    for f in flight.frames():
        c0 = time.process_time()
        ups.append(est.add_frame(f))
        cpu_ms.append((time.process_time() - c0) * 1e3)
    sol = est.solution(smoothed=False)
    index = {p: j for j, p in enumerate(flight.point_ids)}
    smooth = est.solution(smoothed=True)
    sm_pts = np.asarray([index[p.point_id] for p in smooth.points], dtype=np.int64)
    timed = [u.stage != INITIAL_STAGE for u in ups]
    win = [u.window_images for u, t in zip(ups, timed, strict=True) if t]
    return _MethodRun(
        label=f"Seq-R ρ≥{SEQ_R_THRESHOLD:g}",
        lag=None,
        update_ms=[u.processing_ms for u in ups],
        build_ms=[math.nan] * len(ups),
        timed=timed,
        cpu_ms=cpu_ms,
        eop=np.asarray([e.eop for e in sol.eops]).reshape(-1, 6),
        point_idx=np.asarray([index[p.point_id] for p in sol.points], dtype=np.int64),
        xyz=np.asarray([p.xyz_m for p in sol.points]).reshape(-1, 3),
        extra={
            "window_images_median": float(np.median(win)) if win else math.nan,
            "window_images_max": int(max(win)) if win else 0,
            "smoothed": {
                "eop": np.asarray([e.eop for e in smooth.eops]).reshape(-1, 6),
                "point_idx": sm_pts,
                "xyz": np.asarray([p.xyz_m for p in smooth.points]).reshape(-1, 3),
            },
        },
    )


def run_gtsam(flight: SimulatedFlight, lag: int, *, extra_updates: int = 0,
              sigma: str | None = None) -> _MethodRun:
    """Stream ``flight`` through ``gtsam.IncrementalFixedLagSmoother`` with a lag of ``lag``
    images (module docstring). ``sigma`` (a key of :data:`SIGMA_KINDS`): after each update
    (and outside ``update_ms``), the marginal covariances Seq-R publishes are read with
    ``smoother.marginalCovariance``; their time is ``extra["sigma_ms"]`` and is added to the
    run's CPU time."""
    if sigma is not None and sigma not in SIGMA_KINDS:
        raise ConfigError(f"seqat bench gtsam: --sigma: expected one of {sorted(SIGMA_KINDS)}, "
                          f"got {sigma!r}")
    gtsam = _gtsam()
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    n = len(flight.image_ids)
    origin = np.round(flight.nav_eop[0, :3])
    K = calibration(flight.camera)
    pix = gtsam.noiseModel.Isotropic.Sigma(2, flight.sigma_px)
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
    params.relinearizeSkip = 1
    smoother = gtsam.IncrementalFixedLagSmoother(float(lag), params)

    bounds = np.searchsorted(flight.obs_image, np.arange(n + 1))
    pending: dict[int, list[tuple[int, FloatArray]]] = {}  # point -> rays before entering
    entered: set[int] = set()  # landmarks in the smoother now
    departed_pts: set[int] = set()
    alive_poses: set[int] = set()
    latest_pose: dict[int, object] = {}
    latest_pt: dict[int, FloatArray] = {}
    update_ms: list[float] = []
    build_ms: list[float] = []
    cpu_ms: list[float] = []
    estimate_ms: list[float] = []
    sigma_ms: list[float] = []
    max_rho = 0.0
    noise_kinds: set[str] = set()
    counts = {"landmarks_entered": 0, "triangulation_failed": 0, "obs_dropped_departed": 0,
              "factors": 0}
    window_vars: list[int] = []
    iterations: list[int] = []
    threads_before = threads_max = _threads()
    failure = None
    processed = 0
    for i in range(n):
        t0 = time.perf_counter()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {}
        xk = X(i)
        pose0 = eop_to_pose3(flight.nav_eop[i], origin)
        values.insert(xk, pose0)
        stamps[xk] = float(i)
        noise, rho = prior_noise(flight.nav_eop[i], flight.nav_sigma)
        max_rho = max(max_rho, rho)
        noise_kinds.add("diagonal" if rho < DIAGONAL_CORRELATION_TOL else "full Gaussian")
        graph.add(gtsam.PriorFactorPose3(xk, pose0, noise))
        for k in range(bounds[i], bounds[i + 1]):
            j = int(flight.obs_point[k])
            uv = flight.obs_uv[k]
            if j in entered:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(uv, pix, xk, L(j), K))
                stamps[L(j)] = float(i)
                continue
            if j in departed_pts:
                counts["obs_dropped_departed"] += 1
                continue
            rays = [(ii, u) for ii, u in pending.get(j, []) if ii in alive_poses]
            counts["obs_dropped_departed"] += len(pending.get(j, [])) - len(rays)
            rays.append((i, uv))
            pending[j] = rays
            if len(rays) < 2:
                continue
            poses = [pose0 if ii == i else latest_pose[ii] for ii, _ in rays]
            try:
                p = np.asarray(gtsam.triangulatePoint3(
                    poses, K, [np.asarray(u, dtype=np.float64) for _, u in rays], 1e-9, False
                )).reshape(3)
            except RuntimeError:
                counts["triangulation_failed"] += 1
                continue
            if not np.all(np.isfinite(p)) or any(ps.transformTo(p)[2] <= 0 for ps in poses):
                counts["triangulation_failed"] += 1
                continue
            values.insertPoint3(L(j), p)
            stamps[L(j)] = float(i)
            for ii, u in rays:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(u, pix, X(ii), L(j), K))
            entered.add(j)
            del pending[j]
            counts["landmarks_entered"] += 1
        counts["factors"] += graph.size()
        t1, c1 = time.perf_counter(), time.process_time()
        try:
            res = smoother.update(graph, values, stamps)
            for _ in range(extra_updates):
                smoother.update()
        except Exception as exc:  # noqa: BLE001 - any GTSAM error ends the run, reported
            failure = {"image": i, "type": type(exc).__name__, "message": str(exc)[:2000]}
            break
        t2 = time.perf_counter()
        cpu_ms.append((time.process_time() - c1) * 1e3)
        threads_max = max(threads_max, _threads())
        build_ms.append((t1 - t0) * 1e3)
        update_ms.append((t2 - t1) * 1e3)
        iterations.append(int(res.getIterations()))
        processed = i + 1
        # Bookkeeping, outside update_ms: latest estimates, the keys still in the smoother.
        t3 = time.perf_counter()
        est = smoother.calculateEstimate()
        estimate_ms.append((time.perf_counter() - t3) * 1e3)
        alive_poses = set()
        alive_pts = set()
        for key in est.keys():
            sym = gtsam.Symbol(key)
            idx = int(sym.index())
            if chr(sym.chr()) == "x":
                latest_pose[idx] = est.atPose3(key)
                alive_poses.add(idx)
            else:
                latest_pt[idx] = np.asarray(est.atPoint3(key)).reshape(3)
                alive_pts.add(idx)
        departed_pts |= entered - alive_pts
        entered &= alive_pts
        window_vars.append(len(alive_poses) + len(alive_pts))
        if sigma is not None:  # what Seq-R publishes after each image (its update_ms has it)
            t4, c4 = time.perf_counter(), time.process_time()
            try:
                smoother.marginalCovariance(xk)
                if sigma == "all":
                    for j in alive_pts:
                        smoother.marginalCovariance(L(j))
            except Exception as exc:  # noqa: BLE001 - as an update's error: ends the run
                failure = {"image": i, "type": type(exc).__name__, "message": str(exc)[:2000]}
                sigma_ms.append(math.nan)  # one per processed image, as update_ms
                break
            sigma_ms.append((time.perf_counter() - t4) * 1e3)
            cpu_ms[-1] += (time.process_time() - c4) * 1e3
    pts = np.asarray(sorted(latest_pt), dtype=np.int64)
    return _MethodRun(
        label=f"GTSAM iFLS lag {lag}" + (f" + {SIGMA_KINDS[sigma]}" if sigma else ""),
        lag=lag,
        update_ms=update_ms,
        build_ms=build_ms,
        timed=[True] * processed,
        cpu_ms=cpu_ms,
        eop=np.asarray([pose3_to_eop(latest_pose[i], origin) for i in range(processed)]
                       ).reshape(-1, 6),
        point_idx=pts,
        xyz=np.asarray([latest_pt[j] + origin for j in pts]).reshape(-1, 3),
        extra={
            **counts,
            "images_processed": processed,
            "window_variables_median": float(np.median(window_vars)) if window_vars else 0.0,
            "isam2_iterations_total": int(sum(iterations)),
            "extra_updates": extra_updates,
            "calculate_estimate_ms": _stats(estimate_ms),
            "sigma": sigma,
            "sigma_ms": sigma_ms,
            "prior_max_correlation": max_rho,
            "prior_noise_models": sorted(noise_kinds),
            "threads_before": threads_before,  # process threads before the run
            "threads_max": threads_max,  # largest count seen after an update
        },
        failure=failure,
    )


# ---------------------------------------------------------------------------- metrics
def _rms(a: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.square(a)))) if a.size else math.nan


def accuracy(eop: FloatArray, idx: np.ndarray, xyz: FloatArray,
             flight: SimulatedFlight, common: np.ndarray | None = None) -> dict[str, object]:
    """RMSE against truth: position (m) and attitude (deg) over the images estimated, ground
    points over the points estimated (and over ``common`` point indices, the points every
    method estimated); per component and the r.m.s. over the three (as the figures of
    ``seqat bench``)."""
    n = eop.shape[0]
    d = eop - flight.truth_eop[:n]
    dpos, datt = d[:, :3], np.degrees(wrap_angle(d[:, 3:]))
    dgp = xyz - flight.truth_xyz[idx] if idx.size else np.zeros((0, 3))
    in_common = np.isin(idx, common) if common is not None else np.zeros(idx.size, bool)
    return {
        "gp_rmse_common_m": _rms(dgp[in_common]),
        "n_points_common": int(in_common.sum()),
        "n_images": int(n),
        "n_points": int(idx.size),
        "pos_rmse_m": _rms(dpos),
        "att_rmse_deg": _rms(datt),
        "gp_rmse_m": _rms(dgp),
        "pos_rmse_xyz_m": [_rms(dpos[:, c]) for c in range(3)],
        "att_rmse_opk_deg": [_rms(datt[:, c]) for c in range(3)],
        "gp_rmse_xyz_m": [_rms(dgp[:, c]) for c in range(3)],
    }


def _stats(ms: Sequence[float]) -> dict[str, float]:
    a = np.asarray([m for m in ms if math.isfinite(m)], dtype=np.float64)
    if not a.size:
        return {"n": 0, "median_ms": math.nan, "p95_ms": math.nan, "max_ms": math.nan,
                "mean_ms": math.nan}
    return {"n": int(a.size), "median_ms": float(np.median(a)),
            "p95_ms": float(np.percentile(a, 95)), "max_ms": float(np.max(a)),
            "mean_ms": float(np.mean(a))}


def _select(ms: Sequence[float], images: Sequence[int]) -> list[float]:
    return [ms[i] for i in images if i < len(ms)]


# ---------------------------------------------------------------------------- driver
def run_gtsam_bench(
    config_path: Path | str,
    seeds: Sequence[int],
    lag_images: Sequence[int],
    out_dir: Path | str,
    *,
    extra_updates: int = 0,
    sigmas: Sequence[str] = (),
) -> dict:
    """Run Seq-R and GTSAM's fixed-lag smoother (one run per lag, and one more per lag and
    ``sigmas`` kind: :data:`SIGMA_KINDS`) on one simulated strip per seed; write
    ``bench_gtsam.json`` and ``bench_gtsam.md`` to ``out_dir``; return the report.

    Timing rows pool the per-image times over the seeds on Seq-R's timed images (its
    sequential stage); ``ratio`` is a method's median over a GTSAM run's median in the same
    run: of its update alone, or, for a run that reads sigmas, of its update plus the
    marginal covariances (per image), what Seq-R's update time holds too.
    """
    gtsam = _gtsam()
    import importlib.metadata

    if not seeds or not lag_images:
        raise ConfigError("seqat bench gtsam: at least one seed and one lag are needed")
    if any(lag < 0 for lag in lag_images):
        raise ConfigError(f"seqat bench gtsam: --lag: expected lags >= 0 images, got "
                          f"{list(lag_images)}")
    cfg = load_sim_config(Path(config_path))
    out = Path(out_dir)
    t_start = time.perf_counter()
    load_start = load_average()
    seed_results = []
    pooled: dict[str, dict[str, list[float]]] = {}
    with threadpool_limits(limits=1):
        for seed in seeds:
            flight = simulate_strip(cfg, seed)
            runs = [run_seq_r(flight)]
            runs += [run_gtsam(flight, lag, extra_updates=extra_updates, sigma=kind)
                     for lag in lag_images for kind in (None, *dict.fromkeys(sigmas))]
            timed_images = [i for i, t in enumerate(runs[0].timed) if t]
            sm = runs[0].extra["smoothed"]
            common = sm["point_idx"]
            for r in runs:
                common = np.intersect1d(common, r.point_idx)
            rows = []
            for r in runs:
                upd = _select(r.update_ms, timed_images)
                bld = _select(r.build_ms, timed_images)
                tot = [a + b for a, b in zip(upd, bld, strict=True)] if r.lag is not None else []
                sig = (_select(r.extra["sigma_ms"], timed_images)  # type: ignore[arg-type]
                       if r.extra.get("sigma") else [])
                with_sigma = [a + b for a, b in zip(upd, sig, strict=True)] if sig else []
                p = pooled.setdefault(r.label, {"update": [], "build": [], "total": [],
                                                "cpu": [], "sigma": [], "update_sigma": []})
                p["update"] += upd
                p["cpu"] += _select(r.cpu_ms, timed_images)
                p["build"] += bld if r.lag is not None else []
                p["total"] += tot
                p["sigma"] += sig
                p["update_sigma"] += with_sigma
                rows.append({
                    "label": r.label,
                    "lag_images": r.lag,
                    "update": _stats(upd),
                    "cpu": _stats(_select(r.cpu_ms, timed_images)),
                    "build": _stats(bld) if r.lag is not None else None,
                    "update_plus_build": _stats(tot) if r.lag is not None else None,
                    "sigma": _stats(sig) if sig else None,
                    "update_plus_sigma": _stats(with_sigma) if sig else None,
                    "update_all_images": _stats(r.update_ms),
                    "accuracy": accuracy(r.eop, r.point_idx, r.xyz, flight, common),
                    "failure": r.failure,
                    "extra": {k: v for k, v in r.extra.items()
                              if k not in ("smoothed", "sigma_ms")},
                    "update_ms": [round(v, 4) for v in r.update_ms],
                    "build_ms": [round(v, 4) for v in r.build_ms] if r.lag is not None else None,
                })
            rows.insert(1, {
                "label": f"{runs[0].label} RTS-smoothed (same run)",
                "lag_images": None, "update": None, "cpu": None, "build": None,
                "update_plus_build": None, "sigma": None, "update_plus_sigma": None,
                "update_all_images": None,
                "accuracy": accuracy(sm["eop"], sm["point_idx"], sm["xyz"], flight, common),
                "failure": None, "extra": {}, "update_ms": None, "build_ms": None,
            })
            seed_results.append({
                "seed": seed,
                "n_images": len(flight.image_ids),
                "n_points": len(flight.point_ids),
                "n_observations": int(flight.obs_image.size),
                "timed_images": [timed_images[0], timed_images[-1] + 1] if timed_images else [],
                "methods": rows,
            })
    # The conversion check on the first seed's strip without noise (same geometry).
    quiet = dataclasses.replace(cfg, sigma_px=1e-12, sigma_position_m=1e-12,
                                sigma_attitude_deg=1e-12)
    conversion = check_conversion(simulate_strip(quiet, seeds[0]))
    summary = []
    gt_medians = {}
    for row in seed_results[0]["methods"]:
        label = row["label"]
        runs = [x for r in seed_results for x in r["methods"] if x["label"] == label]
        p = pooled.get(label)
        mean_acc = {k: float(np.mean([x["accuracy"][k] for x in runs]))
                    for k in ("pos_rmse_m", "att_rmse_deg", "gp_rmse_m", "gp_rmse_common_m")}
        summary.append({
            "label": label,
            "update": _stats(p["update"]) if p else None,
            "cpu": _stats(p["cpu"]) if p else None,
            "build": _stats(p["build"]) if p and p["build"] else None,
            "update_plus_build": _stats(p["total"]) if p and p["total"] else None,
            "sigma": _stats(p["sigma"]) if p and p["sigma"] else None,
            "update_plus_sigma": _stats(p["update_sigma"]) if p and p["update_sigma"] else None,
            "accuracy_mean_over_seeds": mean_acc,
            "failures": sum(x["failure"] is not None for x in runs),
        })
        if label.startswith("GTSAM"):  # the reference: the update, with its sigmas if read
            ref = summary[-1]["update_plus_sigma"] or summary[-1]["update"]
            gt_medians[label] = (ref["median_ms"], summary[-1]["cpu"]["median_ms"])
    for s in summary:
        for key, clock in (("ratio_to_gtsam_median", "update"), ("cpu_ratio_to_gtsam_median",
                                                                  "cpu")):
            col = 0 if clock == "update" else 1
            own = s["update_plus_sigma"] if clock == "update" and s["update_plus_sigma"] \
                else s[clock]  # a run that reads sigmas: its update + σ, as its reference
            s[key] = {g: (own["median_ms"] / m[col]
                          if own and m[col] and math.isfinite(m[col]) else math.nan)
                      for g, m in gt_medians.items()}
    report = {
        "config_path": str(config_path),
        "seeds": list(seeds),
        "lag_images": list(lag_images),
        "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "runtime_s": time.perf_counter() - t_start,
        "machine": to_jsonable(machine(load_start)),
        "uptime": _uptime(),
        "gtsam": {
            "version": importlib.metadata.version("gtsam"),
            "smoother": f"{gtsam.IncrementalFixedLagSmoother.__module__}."
                        "IncrementalFixedLagSmoother",
            "thread_libraries": gtsam_thread_libraries(),
            "relinearize_threshold": RELINEARIZE_THRESHOLD,
            "relinearize_skip": 1,
            "extra_updates": extra_updates,
            "sigmas": list(dict.fromkeys(sigmas)),
        },
        "env": {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                                "MKL_NUM_THREADS")},
        "python": platform.python_version(),
        "conversion_check_noise_free_seed0": conversion,
        "summary": summary,
        "results": seed_results,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_gtsam.json").write_text(json.dumps(to_jsonable(report), indent=1) + "\n",
                                          encoding="utf-8")
    (out / "bench_gtsam.md").write_text(render_markdown(report), encoding="utf-8")
    return report


def _uptime() -> str:
    try:
        up = float(Path("/proc/uptime").read_text(encoding="utf-8").split()[0])
    except (OSError, ValueError, IndexError):
        up = math.nan
    la = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    return (f"up {up / 60:.0f} min, load average {la[0]:.2f}, {la[1]:.2f}, {la[2]:.2f} "
            f"({os.cpu_count()} CPUs)")


def main(argv: Sequence[str] | None = None) -> dict:
    """Command-line entry (``seqat bench gtsam ARGS``, or ``python -m`` on ``sys.argv``): run
    :func:`run_gtsam_bench`, print the summary table and return the report."""
    ap = argparse.ArgumentParser(prog=None if argv is None else "seqat bench gtsam",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                    help=f"kind: observations config (default {DEFAULT_CONFIG})")
    ap.add_argument("--seed", type=int, action="append",
                    help=f"seed of one simulated strip (repeat; default {DEFAULT_SEEDS})")
    ap.add_argument("--lag", type=int, action="append",
                    help=f"smoother lag in images (repeat; default {DEFAULT_LAGS})")
    ap.add_argument("--out", type=Path, default=Path("out/bench"))
    ap.add_argument("--extra-updates", type=int, default=0,
                    help="empty smoother updates after each image's (timed with it)")
    ap.add_argument("--sigma", action="append", choices=sorted(SIGMA_KINDS), default=[],
                    help="one more GTSAM run per lag that reads, after each update, the "
                         "marginal covariances Seq-R publishes: 'pose' (the new pose's) or "
                         "'all' (and every landmark's); repeat for both")
    args = ap.parse_args(argv)
    report = run_gtsam_bench(args.config, args.seed or DEFAULT_SEEDS, args.lag or DEFAULT_LAGS,
                             args.out, extra_updates=args.extra_updates, sigmas=args.sigma)
    print("\n".join(summary_table(report)))
    print(f"written: {args.out / 'bench_gtsam.json'}, {args.out / 'bench_gtsam.md'}")
    return report


if __name__ == "__main__":
    main()
