"""``seqat bench faults``: seeded blunders, a GNSS jump and a dropout (issue 7).

Three cases, each with several seeds:

* ``strip`` — the paper strip (``configs/paper_sim.yaml``), simulated in memory;
* ``block`` — a simulated block of three serpentine strips (:data:`BLOCK`);
* ``rendered`` — the rendered sample flight (``sample_data/autzen_rendered``): one clean
  ``seqat run`` tracks its tie points, then every variant replays that ``observations.csv``
  (faults written into a copy of the flight folder) through :func:`pipeline.run.runner.run_flight`,
  so data snooping, the dropout bridge and ``run.json`` are measured end to end.

Faults (:mod:`pipeline.bench.faults.injection`): tie-point blunders on 5 % and 20 % of the
observations (10-100 px, random direction); one GNSS position jump of 5 m; one 30 s dropout
(the images' whole nav is missing: ``inf`` σ, start value from the past, 6-DoF resection on
the estimator's window as in :mod:`pipeline.run.sources`).

Variants per fault: Seq-R (ρ ≥ 0.1, RTS-smoothed final solution) with data snooping on
(``snooping_critical``, ``min_rays`` 3) and off (the defaults), and for blunders the
*oracle*: the same run without the blundered observations (snooping off). Scores against
truth: EOP and GP RMSE, GPs off by more than :attr:`FaultBenchOptions.gp_outlier_m`,
precision / recall of the rejections, whether the jump was flagged, dropout cameras' errors
against their neighbours', sequential update times. Outputs: ``faults.json`` (every number),
``faults.md`` (tables, :mod:`pipeline.bench.faults.report`).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from pipeline.bench.common import load_average, load_sim_config, machine, progress_bars
from pipeline.bench.faults.cases import (
    BLOCK,
    CASES,
    OFF,
    ON,
    ORACLE,
    SIM,
    Case,
    FaultBenchOptions,
    FaultBenchReport,
    FaultRun,
    FaultSetup,
    Outcome,
    Scenario,
)
from pipeline.bench.faults.flight import FolderCase
from pipeline.bench.faults.injection import (
    detection,
    gap_stats,
    inject_blunders,
    pick_dropout,
    pick_jump,
)
from pipeline.bench.faults.report import render_fault_markdown
from pipeline.common.rmse import rmse
from pipeline.flight.dropout import predict_missing, resect_from_known
from pipeline.run.store import to_jsonable
from seqat.errors import ConfigError, SeqatError
from seqat.geometry import wrap_angle
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight, StripSimConfig, simulate_strip
from seqat.simultaneous import SimOptions, SimultaneousAT
from seqat.surface import without_off_surface
from seqat.types import EOP_SIZE, FloatArray, ImageUpdate


def _snooping_options(options: FaultBenchOptions, snooping: bool,
                      initial_images: int | None = None) -> SequentialOptions:
    base = SequentialOptions(correlation_threshold=options.threshold)
    if initial_images is not None:
        base = dataclasses.replace(base, initial_images=initial_images)
    if not snooping:
        return base
    return dataclasses.replace(base, snooping_critical=options.snooping_critical,
                               min_rays=options.min_rays)


class _SimCase(Case):
    """A simulated flight streamed through :class:`SequentialAT` in memory."""

    def __init__(self, name: str, flight: SimulatedFlight) -> None:
        self.name, self.flight = name, flight
        self.image_ids, self.point_ids = flight.image_ids, flight.point_ids
        self.times_s, self.truth_eop = flight.times_s, flight.truth_eop
        self.truth_xyz = dict(enumerate(flight.truth_xyz))
        self.obs_image, self.obs_point, self.obs_uv = flight.obs_image, flight.obs_point, (
            flight.obs_uv)
        self.width_px, self.height_px = flight.camera.width_px, flight.camera.height_px
        self.first_sequential = SequentialOptions().initial_images
        self._last: Outcome | None = None  # the previous run (start values of SIM)

    def run(self, sc: Scenario, options: FaultBenchOptions,
            tick: Callable[[], None]) -> Outcome:
        if sc.variant == SIM:
            return self._run_sim(sc, tick)
        f = self.flight
        nav = f.nav_eop.copy()
        if sc.jump is not None:
            nav[sc.jump[0], :3] += sc.jump[1]
        fl = dataclasses.replace(f, obs_image=f.obs_image[sc.keep], obs_point=f.obs_point[sc.keep],
                                 obs_uv=sc.uv_px[sc.keep], nav_eop=nav)
        gap = {int(i) for i in sc.gap}
        missing = nav.copy()
        missing[sorted(gap)] = np.nan
        start = predict_missing(missing, f.times_s)
        est = SequentialAT(f.camera, _snooping_options(options, sc.snooping))
        updates: list[ImageUpdate] = []
        known: dict[str, FloatArray] = {}
        skipped = 0
        for i, frame in enumerate(fl.frames()):
            if i in gap:
                res, _ = resect_from_known(frame.point_ids, frame.uv_px, known, f.camera,
                                           sigma_px=frame.sigma_px, start_eop=start[i])
                if res.eop is None:
                    skipped += 1
                    tick()
                    continue
                frame = dataclasses.replace(frame, nav_eop=start[i],
                                            nav_sigma=np.full(EOP_SIZE, np.inf),
                                            initial_eop=res.eop)
            upd = est.add_frame(frame)
            updates.append(upd)
            if i + 1 in gap and upd.n_points_total:  # as sources.Initialiser: the window's GPs
                known = {p.point_id: p.xyz_m for p in est.window_solution().points}
            tick()
        est.finish()
        out = _outcome(est, updates, self.image_ids, self.point_ids, skipped)
        self._last = out
        return out

    def _run_sim(self, sc: Scenario, tick: Callable[[], None]) -> Outcome:
        """Sim (one adjustment at the end) of the dropout the previous run had: the same
        images (those it could not resect are left out), its final EOPs as start values."""
        f, last = self.flight, self._last
        assert last is not None, "SIM runs after a sequential run of the same dropout"
        gap = {int(i) for i in sc.gap}
        est = SimultaneousAT(f.camera, SimOptions(), refit_every_frame=False)
        skipped = 0
        for i, frame in enumerate(f.frames()):
            tick()
            if i in gap:
                if not np.all(np.isfinite(last.eop[i])):
                    skipped += 1
                    continue
                frame = dataclasses.replace(frame, nav_sigma=np.full(EOP_SIZE, np.inf),
                                            initial_eop=last.eop[i])
            est.add_frame(frame)
        sol, _ = without_off_surface(est.solution(), est.control)  # as seqat run publishes
        img = {iid: i for i, iid in enumerate(self.image_ids)}
        pts = {pid: j for j, pid in enumerate(self.point_ids)}
        eop = np.full((len(self.image_ids), EOP_SIZE), np.nan)
        for e in sol.eops:
            eop[img[e.image_id]] = e.eop
        return Outcome(eop=eop, point_index=np.asarray([pts[p.point_id] for p in sol.points],
                                                        dtype=np.int64),
                        xyz_m=np.asarray([p.xyz_m for p in sol.points]).reshape(-1, 3),
                        sigma0=sol.sigma0, sequential_ms=np.zeros(0), rejections=frozenset(),
                        nav_downweighted=(), skipped=skipped)


def _outcome(est: SequentialAT, updates: Sequence[ImageUpdate], image_ids: Sequence[str],
             point_ids: Sequence[str], skipped: int) -> Outcome:
    sol, _ = without_off_surface(est.solution(), est.control)  # as seqat run publishes
    img = {iid: i for i, iid in enumerate(image_ids)}
    pts = {pid: j for j, pid in enumerate(point_ids)}
    eop = np.full((len(image_ids), EOP_SIZE), np.nan)
    for e in sol.eops:
        eop[img[e.image_id]] = e.eop
    return Outcome(
        eop=eop, point_index=np.asarray([pts[p.point_id] for p in sol.points], dtype=np.int64),
        xyz_m=np.asarray([p.xyz_m for p in sol.points]).reshape(-1, 3), sigma0=sol.sigma0,
        sequential_ms=np.asarray([u.update_ms for u in updates if u.stage == "sequential"]),
        rejections=frozenset((img[i], pts[p]) for i, p, _ in est.rejections),
        nav_downweighted=tuple((img[i], g) for i, g in est.nav_downweighted), skipped=skipped)


# ---------------------------------------------------------------------------- scoring
def _pct(a: FloatArray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else math.nan


def _score(case: Case, seed: int, sc: Scenario, out: Outcome, options: FaultBenchOptions,
           min_rays: int, run_s: float) -> FaultRun:
    d = out.eop - case.truth_eop
    d[:, 3:] = np.degrees(wrap_angle(d[:, 3:]))
    est = np.all(np.isfinite(out.eop), axis=1)
    pos_err = np.linalg.norm(d[:, :3], axis=1)
    att_err = np.abs(d[:, 3:]).max(axis=1)
    with_truth = np.asarray([j in case.truth_xyz for j in out.point_index], dtype=bool)
    gp_d = out.xyz_m[with_truth] - np.asarray(
        [case.truth_xyz[int(j)] for j in out.point_index[with_truth]]).reshape(-1, 3)
    det = det_t = None
    if sc.injected:
        det = detection(sc.injected, out.rejections)
        counts = np.bincount(case.obs_point[sc.keep], minlength=len(case.point_ids))
        testable = frozenset(b for b in sc.injected if counts[b[1]] >= min_rays)
        det_t = detection(testable, out.rejections - (sc.injected - testable))
    flagged, jump_err = None, math.nan
    if sc.jump is not None:
        flagged = (sc.jump[0], "position") in out.nav_downweighted
        jump_err = float(pos_err[sc.jump[0]])
    gap_p = gap_a = None
    if sc.gap.size:
        gap_p = gap_stats(np.where(est, pos_err, np.nan), sc.gap, options.neighbours)
        gap_a = gap_stats(np.where(est, att_err, np.nan), sc.gap, options.neighbours)
    ms = out.sequential_ms
    return FaultRun(
        case=case.name, seed=seed, fault=sc.fault, variant=sc.variant,
        n_images=int(est.sum()), n_points=int(out.point_index.size),
        pos_rmse_m=rmse(d[est, :3]), att_rmse_deg=rmse(d[est, 3:]),
        gp_rmse_m=rmse(gp_d),
        gp_outliers=int(np.count_nonzero(np.linalg.norm(gp_d, axis=1) > options.gp_outlier_m)),
        sigma0=out.sigma0, update_ms_median=_pct(ms, 50), update_ms_p95=_pct(ms, 95),
        update_ms_max=float(ms.max()) if ms.size else math.nan,
        rejected=len(out.rejections),
        nav_downweighted=tuple(f"{case.image_ids[i]}: {g}" for i, g in out.nav_downweighted),
        detection=det, detection_testable=det_t, jump_flagged=flagged, jump_error_m=jump_err,
        dropout_position=gap_p, dropout_attitude=gap_a, skipped=out.skipped, run_s=run_s)


def _failed(case: Case, seed: int, sc: Scenario, err: Exception, run_s: float) -> FaultRun:
    nan3 = (math.nan, math.nan, math.nan)
    tb = traceback.extract_tb(err.__traceback__)
    where = next((f"{Path(fr.filename).name}:{fr.lineno}" for fr in reversed(tb)
                  if "/seqat/" in fr.filename or "/pipeline/" in fr.filename), "")
    return FaultRun(case=case.name, seed=seed, fault=sc.fault, variant=sc.variant, n_images=0,
                    n_points=0, pos_rmse_m=nan3, att_rmse_deg=nan3, gp_rmse_m=nan3,
                    gp_outliers=0, sigma0=math.nan, update_ms_median=math.nan,
                    update_ms_p95=math.nan, update_ms_max=math.nan, rejected=0,
                    nav_downweighted=(), detection=None, detection_testable=None,
                    jump_flagged=None, jump_error_m=math.nan, dropout_position=None,
                    dropout_attitude=None, skipped=0, run_s=run_s,
                    error=f"{type(err).__name__} ({where}): {' '.join(str(err).split())}"[:300])


# ---------------------------------------------------------------------------- injection
def fault_label(kind: str, options: FaultBenchOptions, fraction: float = 0.0) -> str:
    """Row label of a fault: ``clean``, ``blunders 5 %``, ``jump 5 m``, ``dropout 30 s``."""
    if kind == "blunders":
        return f"blunders {100 * fraction:g} %"
    if kind == "jump":
        return f"jump {options.jump_m:g} m"
    if kind == "dropout":
        return f"dropout {options.dropout_s:g} s"
    return "clean"


def scenarios(case: Case, seed: int, options: FaultBenchOptions,
              first: int) -> tuple[FaultSetup, list[Scenario]]:
    """The faults of one case and seed and the runs that measure them.

    Each fault has its own random stream (``SeedSequence([seed, case, fault])``), so adding a
    fault or a case leaves the others unchanged.
    """
    k = case.obs_uv.shape[0]
    n = len(case.image_ids)
    ci = CASES.index(case.name) if case.name in CASES else len(CASES)

    def rng(fault: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([seed, ci, fault]))

    all_rows = np.ones(k, dtype=bool)
    out = [Scenario(fault="clean", variant=v, uv_px=case.obs_uv, keep=all_rows,
                     injected=frozenset(), snooping=s) for v, s in ((OFF, False), (ON, True))]
    counts = []
    for f_i, frac in enumerate(options.blunder_fractions):
        b = inject_blunders(case.obs_uv, case.width_px, case.height_px, frac, rng(10 + f_i),
                            min_px=options.blunder_min_px, max_px=options.blunder_max_px)
        counts.append(int(b.index.size))
        bad = frozenset(zip(case.obs_image[b.index].tolist(), case.obs_point[b.index].tolist(),
                            strict=True))
        clean = all_rows.copy()
        clean[b.index] = False
        label = fault_label("blunders", options, frac)
        out += [Scenario(fault=label, variant=ORACLE, uv_px=case.obs_uv, keep=clean,
                          injected=frozenset()),
                Scenario(fault=label, variant=ON, uv_px=b.uv_px, keep=all_rows, injected=bad,
                          snooping=True),
                Scenario(fault=label, variant=OFF, uv_px=b.uv_px, keep=all_rows, injected=bad)]
    j, offset = pick_jump(n, first + 1, rng(1), options.jump_m,
                          last_margin=max(1, min(5, n // 10)))
    gap = pick_dropout(case.times_s, first, options.dropout_s, rng(2))
    for kind, extra in (("jump", {"jump": (j, offset)}), ("dropout", {"gap": gap})):
        for v, s in ((ON, True), (OFF, False), (SIM, False)) if kind == "dropout" else (
                (ON, True), (OFF, False)):
            out.append(Scenario(fault=fault_label(kind, options), variant=v,
                                 uv_px=case.obs_uv, keep=all_rows, injected=frozenset(),
                                 snooping=s, **extra))  # type: ignore[arg-type]
    setup = FaultSetup(case=case.name, seed=seed, n_images=n, n_observations=k,
                       blunders=tuple(counts), jump_image=case.image_ids[j],
                       jump_offset_m=(float(offset[0]), float(offset[1]), float(offset[2])),
                       dropout_images=tuple(case.image_ids[i] for i in gap),
                       dropout_span_s=float(case.times_s[gap[-1]] - case.times_s[gap[0]])
                       if gap.size else 0.0)
    return setup, out


# ---------------------------------------------------------------------------- driver
def _strip_config(path: Path, options: FaultBenchOptions) -> StripSimConfig:
    cfg = load_sim_config(path)
    if options.strip_images is not None:
        cfg = dataclasses.replace(cfg, n_images=options.strip_images,
                                  n_points=max(2, round(cfg.n_points * options.strip_images
                                                        / cfg.n_images)))
    return cfg


def run_fault_bench(out_dir: Path, *, seeds: Sequence[int] = (1, 2, 3),
                    cases: Sequence[str] = CASES,
                    strip_config: Path = Path("configs/paper_sim.yaml"),
                    rendered_flight: Path = Path("sample_data/autzen_rendered"),
                    options: FaultBenchOptions = FaultBenchOptions(),  # noqa: B008 - frozen
                    progress: bool = True,
                    block_config: StripSimConfig = BLOCK) -> FaultBenchReport:
    """Run the fault benchmark; write ``faults.json`` and ``faults.md`` to ``out_dir``.

    Parameters
    ----------
    out_dir : Path
        Output folder (the rendered case also keeps its run folders in ``out_dir/rendered``).
    seeds : sequence of int
    cases : sequence of str
        Subset of :data:`CASES`.
    strip_config : Path
        ``kind: observations`` config of the strip case.
    rendered_flight : Path
        Image flight folder with ``truth/`` for the rendered case.
    options : FaultBenchOptions
    progress : bool
        Rich progress bars.
    block_config : StripSimConfig
        The block case's simulation.

    Raises
    ------
    ConfigError
        No seed, an unknown case, a bad strip config or a missing flight folder.
    """
    if not seeds:
        raise ConfigError("bench faults: at least one --seed is needed")
    unknown = [c for c in cases if c not in CASES]
    if unknown or not cases:
        raise ConfigError(f"bench faults: --case: expected some of {', '.join(CASES)}, got "
                          f"{', '.join(unknown) or 'none'}")
    out_dir = Path(out_dir)
    strip_cfg = _strip_config(Path(strip_config), options) if "strip" in cases else None
    if "rendered" in cases and not (Path(rendered_flight) / "truth").is_dir():
        what = ("not a flight folder with truth/" if Path(rendered_flight).is_dir()
                else "no such folder (relative paths are from the working directory)")
        raise ConfigError(f"bench faults: {rendered_flight}: {what} (--rendered)")
    t_start, load_start = time.perf_counter(), load_average()
    setups: list[FaultSetup] = []
    runs: list[FaultRun] = []
    folder_case: FolderCase | None = None
    with progress_bars(progress) as bar:
        for name in [c for c in CASES if c in cases]:
            for seed in seeds:
                case: Case
                if name == "rendered":
                    if folder_case is None:
                        folder_case = FolderCase(Path(rendered_flight), out_dir / "rendered")
                    case = folder_case
                    first = options.rendered_initial_images
                else:
                    cfg = strip_cfg if name == "strip" else block_config
                    assert cfg is not None
                    case = _SimCase(name, simulate_strip(cfg, seed))
                    first = case.first_sequential
                setup, scs = scenarios(case, seed, options, first)
                setups.append(setup)
                task = bar.add_task(f"{name} seed {seed}", total=len(scs) * len(case.image_ids))
                for sc in scs:
                    t0 = time.perf_counter()
                    tick = (lambda t=task: bar.advance(t))  # noqa: E731
                    try:
                        outcome = case.run(sc, options, tick)
                    except (SeqatError, np.linalg.LinAlgError) as err:  # a singular system
                        runs.append(_failed(case, seed, sc, err, time.perf_counter() - t0))
                        continue
                    finally:
                        bar.update(task, completed=(scs.index(sc) + 1) * len(case.image_ids))
                    min_rays = options.min_rays if sc.snooping else SequentialOptions().min_rays
                    runs.append(_score(case, seed, sc, outcome, options, min_rays,
                                       time.perf_counter() - t0))
    report = FaultBenchReport(
        date=datetime.datetime.now(datetime.UTC).date().isoformat(),
        runtime_s=time.perf_counter() - t_start, machine=machine(load_start), options=options,
        strip_config=str(strip_config), rendered_flight=str(rendered_flight),
        cases=tuple(c for c in CASES if c in cases), seeds=tuple(seeds),
        setups=tuple(setups), runs=tuple(runs))
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "faults.json").write_text(
        json.dumps(to_jsonable(report), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    (out_dir / "faults.md").write_text(render_fault_markdown(report), encoding="utf-8")
    return report
