"""Benchmark of Seq-R, Seq-F and Sim on simulated strips (seed 000 §3, Figs 4-11).

For each seed a strip is simulated (:func:`seqat.simulate.simulate_strip`) and streamed through
every method; the benchmark measures accuracy against the known truth, the time of each image's
update, the agreement of the sequential methods with the simultaneous baseline, and draws the
paper's figures. Only ``add_frame`` is timed (``ImageUpdate.update_ms`` and ``refine_ms`` are
measured inside it; an image's time is their sum, its update and the refinement after it):
the snapshots behind the per-image RMSE curves are taken between updates and never timed.

Methods
-------
direct : the GPS/INS EOPs and ground points intersected from them (no adjustment).
seq-r : :class:`seqat.sequential.SequentialAT` with a correlation threshold (one run per
    threshold).
seq-f : the same without a window cut.
sim : :class:`seqat.simultaneous.SimultaneousAT` refitting the whole block after every image
    (or, with ``sim_every_frame=False``, after every ``sim_refit_every``-th image).

Outputs in ``out_dir``: ``bench.json`` (:class:`~pipeline.bench.report.BenchReport`),
``bench.md`` (tables with the paper's values and computed PASS/FAIL against the targets) and
``figures/*.png`` (both rendered by :mod:`pipeline.bench.report`).
"""

from __future__ import annotations

import dataclasses
import datetime
import enum
import functools
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.bench.common import load_average, load_sim_config, machine, progress_bars
from pipeline.bench.report import (
    INITIAL_STAGE,
    SEQUENTIAL,
    TARGET_GP_DIFF_STD_M,
    TARGET_LATE_EARLY_RATIO,
    TARGET_MEDIAN_MS,
    TARGET_P99_MS,
    TARGET_RMSE_REL_TO_SIM,
    Accuracy,
    BenchReport,
    Check,
    Curve,
    DiffVsSim,
    Method,
    MethodRun,
    SeedResult,
    Series,
    Timing,
    Triple,
    mean_triple,
    render_markdown,
    rms_of,
    write_figures,
)
from seqat.errors import ConfigError
from seqat.geometry import intersect_rays, wrap_angle
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight, simulate_strip
from seqat.simultaneous import Covariance, SimOptions, SimultaneousAT
from seqat.types import FloatArray, ImageUpdate, Solution

#: The early and late blocks of the paper strip (0-based image indices, end excluded).
EARLY_BLOCK = (50, 100)
LATE_BLOCK = (300, 350)
#: Images per timing block.
BLOCK_IMAGES = 50
#: Rays must spread at least this much for a direct (intersected) ground point to count; the
#: sequential estimator's rule for a new point (SequentialOptions.min_ray_angle_deg).
DIRECT_MIN_RAY_ANGLE_DEG = SequentialOptions().min_ray_angle_deg
_NAN3: Triple = (math.nan, math.nan, math.nan)
#: The nine RMSE components compared with Sim, in Accuracy's order.
RMSE_COMPONENTS = ("X", "Y", "Z", "ω", "φ", "κ", "GP X", "GP Y", "GP Z")


# ---------------------------------------------------------------------------- metrics
@dataclass(frozen=True, eq=False)
class _Snapshot:
    """Estimates of the first ``len(eop)`` images and of some points (flight indices), world."""

    eop: FloatArray  # (n, 6)
    points: np.ndarray  # (m,) int
    xyz: FloatArray  # (m, 3)


def _rms(a: FloatArray, axis: int | None = 0) -> FloatArray:
    return np.sqrt(np.mean(a**2, axis=axis)) if a.size else np.full(3, np.nan)


def _triple(a: FloatArray) -> Triple:
    return (float(a[0]), float(a[1]), float(a[2]))


def _eop_diff(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Position (m) and wrapped attitude (deg) differences ``a - b``."""
    d = a - b
    return d[:, :3], np.degrees(wrap_angle(d[:, 3:]))


def _accuracy(snap: _Snapshot, flight: SimulatedFlight) -> Accuracy:
    n = snap.eop.shape[0]
    dpos, datt = _eop_diff(snap.eop, flight.truth_eop[:n])
    pos, att = _triple(_rms(dpos)), _triple(_rms(datt))
    gp = _triple(_rms(snap.xyz - flight.truth_xyz[snap.points]))
    return Accuracy.from_rmse(
        pos,
        att,
        gp,
        n_images=n,
        n_points=int(snap.points.size),
    )


def _common(a: _Snapshot, b: _Snapshot) -> tuple[FloatArray, FloatArray]:
    """Coordinates of the points in both snapshots, in the same order."""
    _, ia, ib = np.intersect1d(a.points, b.points, assume_unique=True, return_indices=True)
    return a.xyz[ia], b.xyz[ib]


def _gp_diff_std(a: _Snapshot, b: _Snapshot) -> Triple:
    xa, xb = _common(a, b)
    return _triple(np.std(xa - xb, axis=0)) if xa.shape[0] > 1 else _NAN3


def _diff_vs_sim(label: str, seq: _Snapshot, sim: _Snapshot) -> DiffVsSim:
    dpos, datt = _eop_diff(seq.eop, sim.eop)
    xa, xb = _common(seq, sim)
    return DiffVsSim(
        label=label,
        pos_rms_m=_triple(_rms(dpos)),
        att_rms_deg=_triple(_rms(datt)),
        gp_rms_m=_triple(_rms(xa - xb)),
        gp_std_m=_gp_diff_std(seq, sim),
        n_points=int(xa.shape[0]),
    )


def _percentile(a: FloatArray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else math.nan


def _blocks(n_images: int, first_timed: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """Early and late timing blocks: the paper strip's 50-100 and 300-350, or for a shorter
    strip the first and the last block of up to 50 images of the timed stage."""
    if n_images >= LATE_BLOCK[1] and first_timed <= EARLY_BLOCK[0]:
        return EARLY_BLOCK, LATE_BLOCK
    block = max(1, min(BLOCK_IMAGES, (n_images - first_timed) // 2))
    return (first_timed, first_timed + block), (n_images - block, n_images)


def _timing(series: Sequence[Series], mode: str) -> Timing:
    """Timing statistics, pooled over the runs in ``series`` (same strip length)."""
    ms = [np.asarray(s.update_ms, dtype=np.float64) for s in series]
    timed = [
        np.isfinite(m) & (np.asarray(s.stage) != INITIAL_STAGE)
        for m, s in zip(ms, series, strict=True)
    ]
    pooled = np.concatenate([m[t] for m, t in zip(ms, timed, strict=True)])
    first = int(np.flatnonzero(timed[0])[0]) if np.any(timed[0]) else 0
    early, late = _blocks(len(ms[0]), first)

    def block_median(b: tuple[int, int]) -> float:
        vals = np.concatenate(
            [m[b[0] : b[1]][t[b[0] : b[1]]] for m, t in zip(ms, timed, strict=True)]
        )
        return float(np.median(vals)) if vals.size else math.nan

    e, la = block_median(early), block_median(late)
    return Timing(
        mode=mode,
        n_timed=int(pooled.size),
        median_ms=_percentile(pooled, 50),
        p95_ms=_percentile(pooled, 95),
        p99_ms=_percentile(pooled, 99),
        max_ms=float(np.max(pooled)) if pooled.size else math.nan,
        mean_ms=float(np.mean(pooled)) if pooled.size else math.nan,
        early_images=early,
        late_images=late,
        early_median_ms=e,
        late_median_ms=la,
        late_early_ratio=la / e if e > 0 else math.nan,
    )


def _series(updates: Sequence[ImageUpdate]) -> Series:
    return Series(
        stage=tuple(u.stage for u in updates),
        update_ms=tuple(u.processing_ms for u in updates),
        window_images=tuple(u.window_images for u in updates),
        window_params=tuple(u.window_params for u in updates),
        gp_params=tuple(u.window_gp_params for u in updates),
        inverse_a=tuple(u.inverse_sizes[0] for u in updates),
        inverse_b=tuple(u.inverse_sizes[1] for u in updates),
        sim_reduced_size=tuple(u.sim_reduced_size for u in updates),
        sigma0=tuple(u.sigma0 for u in updates),
        rms_gp_sigma_m=tuple(rms_of(u.rms_gp_sigma_m) for u in updates),
    )


# ---------------------------------------------------------------------------- running
def _from_solution(sol: Solution, point_index: dict[str, int]) -> _Snapshot:
    return _Snapshot(
        eop=np.asarray([e.eop for e in sol.eops]).reshape(-1, 6),
        points=np.asarray([point_index[p.point_id] for p in sol.points], dtype=np.int64),
        xyz=np.asarray([p.xyz_m for p in sol.points]).reshape(-1, 3),
    )


def _sim_snapshot(est: SimultaneousAT, point_index: dict[str, int]) -> tuple[_Snapshot, int]:
    """Sim's current estimates (a Gauss-Newton solve from where it stands; converged after a
    per-frame refit) and the order of its reduced normal matrix."""
    st = est.export_state(Covariance.NONE)
    res = st.result
    eop = res.eop.copy()
    eop[:, :3] += st.origin
    pts = np.asarray([point_index[st.point_ids[j]] for j in st.selected], dtype=np.int64)
    return _Snapshot(eop=eop, points=pts, xyz=res.gp + st.origin), res.reduced_size


def _direct(flight: SimulatedFlight, n_images: int) -> _Snapshot:
    """GPS/INS EOPs and points intersected from them using the first ``n_images`` images."""
    keep = flight.obs_image < n_images
    oi, op = flight.obs_image[keep], flight.obs_point[keep]
    origin = np.round(flight.nav_eop[0, :3])  # conditioning of the intersection
    eop = flight.nav_eop[oi].copy()
    eop[:, :3] -= origin
    m = len(flight.point_ids)
    X, spread = intersect_rays(eop, flight.obs_uv[keep], op, m, flight.camera)
    ok = np.all(np.isfinite(X), axis=1) & (spread >= np.radians(DIRECT_MIN_RAY_ANGLE_DEG))
    pts = np.flatnonzero(ok)
    return _Snapshot(eop=flight.nav_eop[:n_images].copy(), points=pts, xyz=X[pts] + origin)


@dataclass(frozen=True, kw_only=True, eq=False)
class _Run:
    """One method's run on one strip, before it is reduced to a :class:`MethodRun`."""

    label: str
    method: Method
    threshold: float | None
    final: _Snapshot
    final_sigma0: float
    series: Series
    snapshots: dict[int, _Snapshot]  # images so far -> estimates (first seed only)
    run_s: float


def _sample_points(n: int, every: int) -> set[int]:
    """Image counts after which the curves are sampled (always including the last)."""
    return set(range(every, n + 1, every)) | {n}


def _run_sequential(
    flight: SimulatedFlight,
    threshold: float | None,
    samples: set[int],
    point_index: dict[str, int],
    tick: Callable[[], None],
    *,
    smoothing: bool = True,
) -> list[_Run]:
    """Seq-R (``threshold``) or Seq-F (``None``) with the default options.

    ``smoothing=False`` runs Seq-R without keeping the RTS gains (the real-time values and
    their timing without that cost; no smoothed entry).

    Snapshots and the main final solution are the real-time values (``smoothed=False``:
    parameters that left the Seq-R window keep their estimate at departure, as in the paper);
    Seq-R adds a second run entry with the RTS-smoothed final solution.
    """
    est = SequentialAT(
        flight.camera, SequentialOptions(correlation_threshold=threshold, smoothing=smoothing)
    )
    label = _seq_label(threshold) + ("" if smoothing else " without RTS gains")
    updates: list[ImageUpdate] = []
    snaps: dict[int, _Snapshot] = {}
    t0 = time.perf_counter()
    for k, frame in enumerate(flight.frames(), start=1):
        updates.append(est.add_frame(frame))
        if k in samples:
            snaps[k] = _from_solution(est.solution(smoothed=False), point_index)
        tick()
    sol = est.solution(smoothed=False)
    run_s = time.perf_counter() - t0
    method = Method.SEQ_F if threshold is None else Method.SEQ_R
    runs = [
        _Run(
            label=label,
            method=method,
            threshold=threshold,
            final=_from_solution(sol, point_index),
            final_sigma0=sol.sigma0,
            series=_series(updates),
            snapshots=snaps,
            run_s=run_s,
        )
    ]
    if threshold is not None and est.options.smoothing:
        smooth = est.solution(smoothed=True)
        runs.append(
            _Run(
                label=f"{label} RTS-smoothed",
                method=Method.SEQ_R_SMOOTHED,
                threshold=threshold,
                final=_from_solution(smooth, point_index),
                final_sigma0=smooth.sigma0,
                series=_series(()),
                snapshots={},
                run_s=run_s,
            )
        )
    return runs


def _run_sim(
    flight: SimulatedFlight,
    every_frame: bool,
    refit_every: int,
    samples: set[int],
    point_index: dict[str, int],
    tick: Callable[[], None],
) -> _Run:
    """Sim refitting after every image (``update_ms`` from ``add_frame``), or after every
    ``refit_every``-th image (the refit is timed; other images have NaN)."""
    est = SimultaneousAT(
        flight.camera, SimOptions(covariance_every_frame=False), refit_every_frame=every_frame
    )
    n = len(flight.image_ids)
    updates: list[ImageUpdate] = []
    refit_ms = np.full(n, np.nan)
    reduced = np.zeros(n, dtype=np.int64)
    snaps: dict[int, _Snapshot] = {}
    t0 = time.perf_counter()
    for k, frame in enumerate(flight.frames(), start=1):
        updates.append(est.add_frame(frame))
        refit = not every_frame and (k % refit_every == 0 or k == n)
        if refit:
            t1 = time.perf_counter()
            snap, reduced[k - 1] = _sim_snapshot(est, point_index)
            refit_ms[k - 1] = (time.perf_counter() - t1) * 1e3
            if k in samples:
                snaps[k] = snap
        elif every_frame and k in samples:
            snaps[k], _ = _sim_snapshot(est, point_index)  # untimed, already converged
        tick()
    sol = est.solution()
    series = _series(updates)
    if not every_frame:
        series = dataclasses.replace(
            series,
            update_ms=tuple(float(v) for v in refit_ms),
            sim_reduced_size=tuple(int(v) for v in reduced),
            sigma0=(math.nan,) * (n - 1) + (sol.sigma0,),
        )
    return _Run(
        label="Sim",
        method=Method.SIM,
        threshold=None,
        final=_from_solution(sol, point_index),
        final_sigma0=sol.sigma0,
        series=series,
        snapshots=snaps,
        run_s=time.perf_counter() - t0,
    )


def _direct_run(flight: SimulatedFlight, samples: set[int]) -> _Run:
    n = len(flight.image_ids)
    t0 = time.perf_counter()
    snaps = {k: _direct(flight, k) for k in sorted(samples)}
    return _Run(
        label="Direct (GPS/INS)",
        method=Method.DIRECT,
        threshold=None,
        final=_direct(flight, n),
        final_sigma0=math.nan,
        series=_series(()),
        snapshots=snaps,
        run_s=time.perf_counter() - t0,
    )


def _seq_label(threshold: float | None) -> str:
    return "Seq-F" if threshold is None else f"Seq-R ρ≥{threshold:g}"


def _method_run(run: _Run, flight: SimulatedFlight, sim_mode: str) -> MethodRun:
    timed = run.method in (Method.SEQ_R, Method.SEQ_F, Method.SIM)
    mode = sim_mode if run.method is Method.SIM else "every image (sequential stage)"
    return MethodRun(
        method=run.method.value,
        label=run.label,
        threshold=run.threshold,
        accuracy=_accuracy(run.final, flight),
        timing=_timing([run.series], mode) if timed else None,
        run_s=run.run_s,
        final_sigma0=run.final_sigma0,
        series=run.series if timed else None,
    )


def _curves(runs: Sequence[_Run], flight: SimulatedFlight) -> tuple[Curve, ...]:
    sim = next(r for r in runs if r.method is Method.SIM)
    out = []
    for r in runs:
        if not r.snapshots:
            continue
        ks = sorted(r.snapshots)
        acc = [_accuracy(r.snapshots[k], flight) for k in ks]
        diff = [
            (
                _gp_diff_std(r.snapshots[k], sim.snapshots[k])
                if k in sim.snapshots and r.method in SEQUENTIAL
                else _NAN3
            )
            for k in ks
        ]
        out.append(
            Curve(
                label=r.label,
                image_count=tuple(ks),
                pos_m=tuple(a.pos_m for a in acc),
                att_deg=tuple(a.att_deg for a in acc),
                gp_m=tuple(a.gp_m for a in acc),
                gp_diff_std_m=tuple(diff),
            )
        )
    return tuple(out)


# ---------------------------------------------------------------------------- summary, checks
def _summary(results: Sequence[SeedResult]) -> tuple[MethodRun, ...]:
    """Per method: mean over seeds of the RMSE per component; timing pooled over seeds."""
    out = []
    for i, first in enumerate(results[0].methods):
        runs = [r.methods[i] for r in results]
        accs = [m.accuracy for m in runs]
        pos, att = (
            mean_triple([a.pos_rmse_m for a in accs]),
            mean_triple([a.att_rmse_deg for a in accs]),
        )
        gp = mean_triple([a.gp_rmse_m for a in accs])
        acc = Accuracy.from_rmse(
            pos,
            att,
            gp,
            n_images=accs[0].n_images,
            n_points=int(round(np.mean([a.n_points for a in accs]))),
        )
        series = [m.series for m in runs if m.series is not None]
        timing = _timing(series, first.timing.mode) if series and first.timing is not None else None
        out.append(
            dataclasses.replace(
                first,
                accuracy=acc,
                timing=timing,
                run_s=float(np.mean([m.run_s for m in runs])),
                final_sigma0=float(np.mean([m.final_sigma0 for m in runs])),
                series=None,
            )
        )
    return tuple(out)


def _checks(results: Sequence[SeedResult], summary: Sequence[MethodRun]) -> tuple[Check, ...]:
    """Targets, evaluated on every seed; the value shown is the worst seed's (timing: pooled)."""
    checks = []
    for i, m in enumerate(summary):
        if m.method not in SEQUENTIAL:
            continue
        rel: list[tuple[float, str, int]] = []  # (signed relative difference, what, seed)
        std = []
        for r in results:
            sim = next(x for x in r.methods if x.method == Method.SIM).accuracy
            acc = r.methods[i].accuracy
            own = np.asarray(acc.pos_rmse_m + acc.att_rmse_deg + acc.gp_rmse_m)
            ref = np.asarray(sim.pos_rmse_m + sim.att_rmse_deg + sim.gp_rmse_m)
            rel_diff = (own - ref) / ref
            k = int(np.argmax(np.abs(rel_diff)))
            rel.append((float(rel_diff[k]), RMSE_COMPONENTS[k], r.seed))
            std.append(max(next(d for d in r.differences if d.label == m.label).gp_std_m))
        worst, what, seed = max(rel, key=lambda x: abs(x[0]))
        checks.append(
            Check(
                label=m.label,
                name=f"largest RMSE difference to Sim, relative (worst: {what}, seed {seed})",
                value=100 * worst,
                target=100 * TARGET_RMSE_REL_TO_SIM,
                unit="%",
                two_sided=True,
                passed=abs(worst) <= TARGET_RMSE_REL_TO_SIM,
            )
        )
        checks.append(
            Check(
                label=m.label,
                name="max std of GP difference to Sim",
                value=max(std),
                target=TARGET_GP_DIFF_STD_M,
                unit="m",
                two_sided=False,
                passed=max(std) <= TARGET_GP_DIFF_STD_M,
            )
        )
        if m.method == Method.SEQ_R and m.timing is not None:
            t = m.timing
            for name, value, target in (
                ("median update time", t.median_ms, TARGET_MEDIAN_MS),
                ("p99 update time", t.p99_ms, TARGET_P99_MS),
            ):
                checks.append(
                    Check(
                        label=m.label,
                        name=name,
                        value=value,
                        target=target,
                        unit="ms",
                        two_sided=False,
                        passed=value <= target,
                    )
                )
            checks.append(
                Check(
                    label=m.label,
                    name=(
                        f"median time images {t.late_images[0]}-"
                        f"{t.late_images[1]} / {t.early_images[0]}-"
                        f"{t.early_images[1]}"
                    ),
                    value=t.late_early_ratio,
                    target=TARGET_LATE_EARLY_RATIO,
                    unit="",
                    two_sided=False,
                    passed=t.late_early_ratio <= TARGET_LATE_EARLY_RATIO,
                )
            )
    return tuple(checks)


# ---------------------------------------------------------------------------- JSON
def _jsonable(obj: object) -> object:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, enum.Enum):
        return obj.value
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None  # JSON has no NaN
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


# ---------------------------------------------------------------------------- driver
def run_bench(
    config_path: Path,
    out_dir: Path,
    seeds: Sequence[int] = (1, 2, 3),
    thresholds: Sequence[float] = (0.1,),
    sim_every_frame: bool = True,
    progress: bool = True,
    *,
    sim_refit_every: int = 8,
    curve_every: int = 4,
) -> BenchReport:
    """Run the benchmark and write ``bench.json``, ``bench.md`` and ``figures/`` to ``out_dir``.

    Parameters
    ----------
    config_path : Path
        Simulation config (``kind: observations``, ``simulation:`` = StripSimConfig fields).
    out_dir : Path
    seeds : sequence of int
        One simulated strip per seed; figures and curves come from the first.
    thresholds : sequence of float
        Seq-R correlation thresholds (one run each); the first is the headline Seq-R.
    sim_every_frame : bool
        Sim refits after every image (seed 000's baseline); ``False``: after every
        ``sim_refit_every``-th image only (for strips where per-image refits are too slow).
    progress : bool
        Show rich progress bars.
    sim_refit_every : int
    curve_every : int
        Snapshots for the per-image RMSE curves every this many images (first seed).

    Returns
    -------
    BenchReport

    Raises
    ------
    ConfigError
        Bad config, or empty ``seeds``/``thresholds``, or non-positive intervals.
    """
    if not seeds or not thresholds:
        raise ConfigError("bench: at least one seed and one Seq-R threshold are needed")
    if sim_refit_every < 1 or curve_every < 1:
        raise ConfigError(
            f"bench: sim_refit_every and curve_every must be >= 1, got "
            f"{sim_refit_every}, {curve_every}"
        )
    cfg = load_sim_config(Path(config_path))
    out_dir = Path(out_dir)
    t_start = time.perf_counter()
    load_start = load_average()
    sim_mode = (
        "refit after every image"
        if sim_every_frame
        else f"refit after every {sim_refit_every}th image"
    )
    variants: list[float | None] = [*thresholds, None]
    results: list[SeedResult] = []
    curves: tuple[Curve, ...] = ()
    with progress_bars(progress) as bar:
        for s_i, seed in enumerate(seeds):
            flight = simulate_strip(cfg, seed)
            n = len(flight.image_ids)
            point_index = {p: j for j, p in enumerate(flight.point_ids)}
            samples = _sample_points(n, curve_every) if s_i == 0 else set()
            runs = [_direct_run(flight, samples)]
            for v in variants:
                task = bar.add_task(f"seed {seed} {_seq_label(v)}", total=n)
                runs += _run_sequential(
                    flight, v, samples, point_index, functools.partial(bar.advance, task)
                )
            task = bar.add_task(f"seed {seed} {_seq_label(thresholds[0])} no gains", total=n)
            runs += _run_sequential(
                flight, thresholds[0], set(), point_index, functools.partial(bar.advance, task),
                smoothing=False,
            )
            task = bar.add_task(f"seed {seed} Sim", total=n)
            runs.append(
                _run_sim(
                    flight,
                    sim_every_frame,
                    sim_refit_every,
                    samples,
                    point_index,
                    functools.partial(bar.advance, task),
                )
            )
            sim = runs[-1]
            diffs = tuple(
                _diff_vs_sim(r.label, r.final, sim.final) for r in runs if r.method in SEQUENTIAL
            )
            results.append(
                SeedResult(
                    seed=seed,
                    n_images=n,
                    n_points=len(flight.point_ids),
                    n_observations=int(flight.obs_image.size),
                    methods=tuple(_method_run(r, flight, sim_mode) for r in runs),
                    differences=diffs,
                )
            )
            if s_i == 0:
                curves = _curves(runs, flight)
    summary = _summary(results)
    checks = _checks(results, summary)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = write_figures(results[0], curves, out_dir / "figures")
    report = BenchReport(
        config_path=str(config_path),
        simulation=cfg,
        seeds=tuple(seeds),
        thresholds=tuple(thresholds),
        sim_mode=sim_mode,
        date=datetime.datetime.now(datetime.UTC).date().isoformat(),
        runtime_s=time.perf_counter() - t_start,
        machine=machine(load_start),
        results=tuple(results),
        summary=summary,
        checks=checks,
        curves=curves,
        figures=tuple(str(p.relative_to(out_dir)) for p in figures),
    )
    (out_dir / "bench.json").write_text(
        json.dumps(_jsonable(report), indent=1) + "\n", encoding="utf-8"
    )
    (out_dir / "bench.md").write_text(render_markdown(report), encoding="utf-8")
    return report
