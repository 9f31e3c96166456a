"""``seqat report OUT``: the flight report a surveyor reads, ``report.html`` and ``report.json``.

Sources (docs/formats.md, *Report*): the run folder ``OUT`` (``read_run``), other runs of the
same flight given with ``--compare`` (one method each), the COLMAP reference
``OUT/reference/`` when present, the nav (direct georeferencing), the flight's ``truth/``
(simulated and rendered flights) and its check points (``checkpoints.csv`` +
``checkpoint_obs.csv``, never used in the adjustment).

Accuracy is measured against ``truth/`` when the flight has it, else against the COLMAP
reference. Check points are intersected from their observed pixels with each method's EOPs
(:func:`seqat.geometry.intersect_rays`) and summarised as in the ASPRS Positional Accuracy
Standards, Edition 2 (2023): ``RMSE_H = sqrt(RMSE_x^2 + RMSE_y^2)``, ``RMSE_V = RMSE_z``, at
least 30 check points.
"""

from __future__ import annotations

import datetime
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.common.columns import (
    CHECKPOINT_OBS_FILE,
    CHECKPOINTS_FILE,
    EOP_FILE,
    FLIGHT_YAML,
    POINTS_FILE,
    REFERENCE_DIR,
)
from pipeline.common.paths import exists_as_anything, file_problem
from pipeline.common.rmse import Triple, rmse
from pipeline.common.tables import EopTable, PointTable
from pipeline.flight.camera import PixelCorrector, pinhole_camera
from pipeline.flight.folder import read_truth
from pipeline.flight.nav_files import read_ground_points
from pipeline.flight.schema import load_flight_config
from pipeline.reference.stage import REFERENCE_JSON, read_observations
from pipeline.report.asprs import (
    AsprsTable,
    PointResidual,
    asprs_table,
    verdict_lines,
)
from pipeline.report.control_section import (
    ControlReport,
    control_json,
    control_reports,
    control_verdict,
    read_run_control,
)
from pipeline.report.sfm_section import read_sfm_agreement
from pipeline.report.stage_warnings import StageWarning, collect_warnings
from pipeline.run.accuracy import eop_differences, point_differences
from pipeline.run.latency import LatencyTable, latency_table, read_ortho_json
from pipeline.run.robustness import RobustnessSummary, summarise
from pipeline.run.store import (
    JSON_INDENT,
    RunFolder,
    read_eop_csv,
    read_points_csv,
    read_run,
    to_jsonable,
)
from seqat.errors import InputDataError
from seqat.geometry import intersect_rays, project, rotation_matrix
from seqat.types import FloatArray

#: Output files.
REPORT_HTML = "report.html"
REPORT_JSON = "report.json"
REPORT_VERSION = 1
#: Method label of direct georeferencing (the nav) and of the COLMAP reference.
DIRECT = "direct"
REFERENCE = "colmap"
#: Precision plateau: the first image after which the rms GP sigma stays within this
#: fraction of its final level (median of the last quarter of the images).
PLATEAU_TOLERANCE = 0.05
PLATEAU_TAIL_FRACTION = 0.25


@dataclass(frozen=True, kw_only=True)
class MethodAccuracy:
    """RMSE of one method's EOPs and ground points against truth or the reference."""

    method: str
    against: str  # "truth" | "reference"
    n_images: int
    n_points: int
    pos_rmse_m: Triple
    pos_rmse_h_m: float
    pos_rmse_3d_m: float
    att_rmse_deg: Triple
    gp_rmse_m: Triple
    gp_rmse_h_m: float
    gp_rmse_3d_m: float


@dataclass(frozen=True, kw_only=True)
class FlightSummary:
    images: int
    duration_s: float
    gsd_m: float  # median camera height above the median tie point height, over f
    forward_overlap: float  # median over consecutive images, 0..1
    crs_name: str
    camera_model: str
    camera_approximate: bool
    #: Self-calibration (run.json ``camera_estimate``): each free parameter with its sigma
    #: and prior, and those held at the prior; empty: the camera was fixed.
    camera_estimate: str = ""


def camera_estimate_text(run: RunFolder) -> str:
    """One line on the self-calibrated camera of a run ("" when the camera was fixed)."""
    est = run.record.get("camera_estimate")
    if not isinstance(est, dict):
        return ""
    v, sg, prior = est["values"], est["sigma"], est["prior"]
    parts = [f"{n} {v[n]:.5g} ± {sg[n]:.2g} (prior {prior[n]:.5g})" for n in est["free"]]
    held = est.get("held") or []
    because = "not determined, or not significant"
    if not parts:  # every free parameter held: the camera as given
        return f"self-calibration: every parameter held at the prior ({because}): " + (
            ", ".join(held))
    text = "self-calibrated: " + ", ".join(parts)
    return text + (f"; held at the prior ({because}): {', '.join(held)}" if held else "")


@dataclass(frozen=True, kw_only=True)
class TiePointSummary:
    count: int
    observations: int
    track_length_mean: float
    track_length_median: float
    track_length_max: int
    image_residual_rms_px: float  # of the run's solution, observed pixels


@dataclass(frozen=True, kw_only=True)
class RealTime:
    """Per-image behaviour of one run (from ``run.json`` ``images[]``)."""

    method: str
    update_ms_median: float
    update_ms_p95: float
    update_ms_max: float
    window_images_median: float
    window_images_max: int
    inverse_sizes_max: tuple[int, int]
    final_sigma0: float
    final_rms_gp_sigma_m: float
    precision_plateau_index: int | None  # 0-based image index
    precision_plateau_image: str | None


@dataclass(frozen=True, kw_only=True)
class LiveOperation:
    """How the main run kept up (``run.json`` ``mode``, ``images[].live``, ``latency_budget``).

    ``processing_ms_*``: tracking + update + the refinement after it (re-linearisation, a
    second start) per image;
    ``latency_ms_*``: input complete -> estimate (watch mode only, else None);
    ``budget_mode``: ``fixed``, ``keep-up`` or None (no budget); ``threshold_changes``: the
    latency budget's events (image, old and new threshold and features, measured ms, reason).
    """

    mode: str
    replayed_images: int
    processing_ms_median: float
    processing_ms_p95: float
    processing_ms_max: float
    latency_ms_median: float | None
    latency_ms_p95: float | None
    latency_ms_max: float | None
    budget_mode: str | None
    budget_ms: float | None
    images_over_budget: int | None
    final_threshold: float | None
    final_features: int | None
    threshold_changes: tuple[Mapping[str, object], ...]


@dataclass(frozen=True, kw_only=True)
class CheckpointReport:
    method: str
    table: AsprsTable
    residuals: tuple[PointResidual, ...]
    not_intersected: tuple[str, ...]  # fewer than two rays
    #: Check points that are also ground control points of the run: left out (control).
    excluded_control: tuple[str, ...] = ()


@dataclass(frozen=True, kw_only=True)
class ReportTitle:
    """What the report's title says: the flight's name (its folder's), a date and the method.

    ``date_kind``: ``flown`` (the first image's time, when the nav holds absolute times) or
    ``processed`` (when ``run.json`` was written).
    """

    flight_name: str
    date: str  # ISO 8601 day, UTC
    date_kind: str
    method: str


@dataclass(frozen=True, kw_only=True)
class Report:
    """Everything ``report.json`` holds (``accuracy`` and ``checkpoints`` keyed as DESIGN.md)."""

    version: int
    title: ReportTitle
    #: The first box in sentences (:func:`pipeline.report.asprs.verdict_lines`).
    verdict: tuple[str, ...]
    #: Every stage's warnings (:func:`pipeline.report.stage_warnings.collect_warnings`).
    warnings: tuple[StageWarning, ...]
    run: str
    flight: str
    methods: tuple[str, ...]
    flight_summary: FlightSummary
    tie_points: TiePointSummary
    sigma0: float
    processing_ms_per_image_median: float
    processing_total_s: float
    reference: Mapping[str, object] | None
    accuracy_against: str | None
    accuracy: Mapping[str, MethodAccuracy]
    realtime: tuple[RealTime, ...]
    live: LiveOperation | None
    latency: LatencyTable
    checkpoints: Mapping[str, float | int | None] | None
    checkpoint_reports: tuple[CheckpointReport, ...]
    notes: tuple[str, ...]
    robustness: RobustnessSummary | None = None  # data snooping, GNSS dropouts
    sfm_agreement: Mapping[str, object] | None = None  # report/sfm_section.py
    #: Ground control (report/control_section.py): the run in OUT, and per method.
    control: Mapping[str, object] | None = None
    control_reports: tuple[ControlReport, ...] = ()


# --------------------------------------------------------------------------------------------
# Numbers
# --------------------------------------------------------------------------------------------


def _h(t: Triple) -> float:
    return float(math.hypot(t[0], t[1]))


def _3d(t: Triple) -> float:
    return float(math.sqrt(t[0] ** 2 + t[1] ** 2 + t[2] ** 2))


def method_accuracy(method: str, against: str, eop_ids: tuple[str, ...], eop_values: FloatArray,
                    point_ids: tuple[str, ...], xyz: FloatArray,
                    ref_eop_ids: tuple[str, ...], ref_eop: FloatArray,
                    ref_point_ids: tuple[str, ...], ref_xyz: FloatArray) -> MethodAccuracy:
    """RMSEs of one method against truth or the reference (matched by id)."""
    rows, d_pos, d_att = eop_differences(eop_ids, eop_values, ref_eop_ids, ref_eop)
    d_gp = point_differences(point_ids, xyz, ref_point_ids, ref_xyz)
    pos, att, gp = rmse(d_pos), rmse(d_att), rmse(d_gp)
    return MethodAccuracy(method=method, against=against, n_images=int(rows.size),
                          n_points=int(d_gp.shape[0]), pos_rmse_m=pos, pos_rmse_h_m=_h(pos),
                          pos_rmse_3d_m=_3d(pos), att_rmse_deg=att, gp_rmse_m=gp,
                          gp_rmse_h_m=_h(gp), gp_rmse_3d_m=_3d(gp))


def precision_plateau(rms_gp_sigma_m: FloatArray) -> int | None:
    """First image after which the rms GP sigma stays within 5 % of its final level.

    Parameters
    ----------
    rms_gp_sigma_m : (n,) float
        r.m.s. GP sigma after each image (NaN where none).

    Returns
    -------
    int or None
        0-based index; None without finite values.
    """
    g = np.asarray(rms_gp_sigma_m, dtype=np.float64)
    finite = np.flatnonzero(np.isfinite(g))
    if finite.size == 0:
        return None
    tail = g[finite[int(finite.size * (1 - PLATEAU_TAIL_FRACTION)):]]
    level = float(np.median(tail))
    outside = np.flatnonzero(np.isfinite(g) & (g > level * (1 + PLATEAU_TOLERANCE)))
    return int(finite[0]) if outside.size == 0 else min(int(outside[-1]) + 1, g.size - 1)


@dataclass(frozen=True, kw_only=True, eq=False)
class _Method:
    """One set of estimates to compare."""

    label: str
    eop: EopTable
    points: PointTable | None
    record: Mapping[str, object] | None  # run.json of a run


def _direct_points(run: RunFolder, obs: tuple[np.ndarray, tuple[str, ...], np.ndarray,
                                               FloatArray]) -> PointTable:
    """Tie points intersected with the nav EOPs (what direct georeferencing gives)."""
    obs_image, point_ids, obs_point, uv = obs
    fix = np.all(np.isfinite(run.nav.eop[obs_image]), axis=1)  # not the GNSS dropouts
    obs_image, obs_point, uv = obs_image[fix], obs_point[fix], uv[fix]
    ideal = PixelCorrector(camera=run.camera).ideal_pixels(uv)
    X, _ = intersect_rays(run.nav.eop[obs_image], ideal, obs_point, len(point_ids),
                          pinhole_camera(run.camera))
    ok = np.all(np.isfinite(X), axis=1)
    m = int(np.count_nonzero(ok))
    return PointTable(point_ids=tuple(p for p, k in zip(point_ids, ok, strict=True) if k),
                      xyz_m=X[ok], sigma_m=np.full((m, 3), np.nan),
                      n_obs=np.bincount(obs_point, minlength=len(point_ids))[ok])


#: Nav times above this (s) are absolute (Unix time, after 1973): the flight's date is known.
ABSOLUTE_TIME_S = 1e8


def report_title(run: RunFolder) -> ReportTitle:
    """The flight's name, date and method (:class:`ReportTitle`)."""
    folder = Path(str(run.record.get("flight") or run.flight_dir))
    name = folder.name or folder.resolve().name  # "." names the folder it stands for
    t0 = float(run.nav.times_s[0]) if len(run.nav) else float("nan")
    if math.isfinite(t0) and t0 > ABSOLUTE_TIME_S:
        when, kind = datetime.datetime.fromtimestamp(t0, tz=datetime.UTC), "flown"
    else:
        mtime = (run.path / "run.json").stat().st_mtime
        when, kind = datetime.datetime.fromtimestamp(mtime, tz=datetime.UTC), "processed"
    return ReportTitle(flight_name=name or str(folder), date=when.date().isoformat(),
                       date_kind=kind, method=run.method)


def _same_flight(main: RunFolder, other: RunFolder) -> None:
    if main.nav.image_ids != other.nav.image_ids:
        raise InputDataError(f"{other.path}: --compare run is not of the same flight as "
                             f"{main.path} (different images)")


def image_residuals_px(run: RunFolder, obs: tuple[np.ndarray, tuple[str, ...], np.ndarray,
                                                   FloatArray] | None = None) -> FloatArray:
    """Image residuals (observed pixels, ``(k, 2)``: the pixels the features were measured
    in, as the adjustment weighs them) of the observations of ``observations.csv`` whose
    image and point the run estimated, at the run's estimates.

    A sequential run may leave some observations out (rays of images that left its window
    before a second ray came, observations of points that had left it); they are counted
    here all the same.
    """
    if obs is None:
        obs = read_observations(run.observations_path, run.nav.index())
    obs_image, point_ids, obs_point, uv = obs
    est = run.points.index()
    sel = np.array([point_ids[j] in est for j in obs_point], dtype=bool)
    eop_index = run.eop.index()
    img_rows = np.array([eop_index.get(run.nav.image_ids[i], -1) for i in obs_image],
                        dtype=np.int64)
    sel &= img_rows >= 0
    if not np.any(sel):
        return np.zeros((0, 2))
    xyz = run.points.xyz_m[[est[point_ids[j]] for j in obs_point[sel]]]
    ideal = project(run.eop.eop[img_rows[sel]], xyz, pinhole_camera(run.camera))
    return uv[sel] - PixelCorrector(camera=run.camera).observed_pixels(ideal)


def _tie_points(run: RunFolder, obs: tuple[np.ndarray, tuple[str, ...], np.ndarray,
                                           FloatArray]) -> TiePointSummary:
    obs_image = obs[0]
    n_obs = run.points.n_obs
    res = image_residuals_px(run, obs)
    rms_px = float(np.sqrt(np.mean(res**2))) if res.size else float("nan")
    return TiePointSummary(count=len(run.points), observations=int(obs_image.size),
                           track_length_mean=float(np.mean(n_obs)) if n_obs.size else 0.0,
                           track_length_median=float(np.median(n_obs)) if n_obs.size else 0.0,
                           track_length_max=int(n_obs.max(initial=0)),
                           image_residual_rms_px=rms_px)


def _flight_summary(run: RunFolder) -> FlightSummary:
    nav = run.nav
    cam = run.camera
    z_ground = float(np.median(run.points.xyz_m[:, 2])) if len(run.points) else float("nan")
    height = float(np.nanmedian(nav.eop[:, 2])) - z_ground
    gsd = height / cam.fx_px
    overlaps = []
    for i in range(len(nav) - 1):
        base = nav.eop[i + 1, :3] - nav.eop[i, :3]
        b = float(np.linalg.norm(base[:2]))
        if b == 0.0 or not np.all(np.isfinite(nav.eop[i])) or not np.isfinite(b):
            continue
        R = rotation_matrix(*nav.eop[i, 3:])
        d_cam = R.T @ np.array([base[0], base[1], 0.0]) / b
        footprint = gsd * (abs(d_cam[0]) * cam.width_px + abs(d_cam[1]) * cam.height_px)
        overlaps.append(1.0 - b / footprint)
    return FlightSummary(images=len(nav), duration_s=float(nav.times_s[-1] - nav.times_s[0]),
                         gsd_m=gsd, forward_overlap=float(np.median(overlaps)) if overlaps
                         else float("nan"), crs_name=run.crs.name, camera_model=cam.model,
                         camera_approximate=run.inputs.camera_approximate,
                         camera_estimate=camera_estimate_text(run))


def _realtime(label: str, record: Mapping[str, object]) -> RealTime:
    images = record.get("images", [])
    assert isinstance(images, list)

    def series(key: str) -> FloatArray:
        return np.array([np.nan if im.get(key) is None else float(im[key]) for im in images])

    ms = series("update_ms")
    win = series("window_images")
    g = np.array([np.nan if any(v is None for v in im["rms_gp_sigma_m"])
                  else float(np.sqrt(np.mean(np.square(im["rms_gp_sigma_m"]))))
                  for im in images])
    inv = np.array([im.get("inverse_sizes", [0, 0]) for im in images]).reshape(-1, 2)
    plateau = precision_plateau(g)
    s0 = series("sigma0")
    return RealTime(
        method=label, update_ms_median=float(np.nanmedian(ms)),
        update_ms_p95=float(np.nanpercentile(ms, 95)), update_ms_max=float(np.nanmax(ms)),
        window_images_median=float(np.nanmedian(win)), window_images_max=int(np.nanmax(win)),
        inverse_sizes_max=(int(inv[:, 0].max(initial=0)), int(inv[:, 1].max(initial=0))),
        final_sigma0=float(s0[-1]), final_rms_gp_sigma_m=float(g[-1]),
        precision_plateau_index=plateau,
        precision_plateau_image=None if plateau is None else str(images[plateau]["image_id"]))


def live_operation(record: Mapping[str, object]) -> LiveOperation | None:
    """The live section of a run (None for runs written before per-image timings existed)."""
    images = record.get("images", [])
    assert isinstance(images, list)
    with_live = [im for im in images if isinstance(im.get("live"), dict)]
    live = [im["live"] for im in with_live]
    if not live:
        return None
    # reading and tracking, the update and the refinement after it (the next image waits)
    proc = np.array([float(x["prep_ms"]) + float(x["update_ms"]) + float(im.get("refine_ms") or 0.0)
                     for x, im in zip(live, with_live, strict=True)])
    lat = np.array([float(x["latency_ms"]) for x in live if x.get("latency_ms") is not None])
    budget = record.get("latency_budget")

    def stat(values: FloatArray, q: float | None) -> float | None:
        if values.size == 0:
            return None
        return float(np.max(values) if q is None else np.percentile(values, q))

    return LiveOperation(
        mode=str(record.get("mode", "run")), replayed_images=int(record.get("replayed", 0)),  # type: ignore[call-overload]
        processing_ms_median=float(np.median(proc)),
        processing_ms_p95=float(np.percentile(proc, 95)), processing_ms_max=float(proc.max()),
        latency_ms_median=stat(lat, 50), latency_ms_p95=stat(lat, 95),
        latency_ms_max=stat(lat, None),
        budget_mode=str(budget.get("mode", "fixed")) if isinstance(budget, dict) else None,
        budget_ms=budget["budget_ms"] if isinstance(budget, dict) else None,
        final_features=budget.get("final_features") if isinstance(budget, dict) else None,
        images_over_budget=budget["images_over_budget"] if isinstance(budget, dict) else None,
        final_threshold=budget["final_threshold"] if isinstance(budget, dict) else None,
        threshold_changes=tuple(budget["events"]) if isinstance(budget, dict) else ())


#: A check point's observation farther than this many image sigmas outside the frame is an
#: error of the check point file (it cannot have been measured in the image).
CHECKPOINT_FRAME_SIGMAS = 5.0


def find_checkpoints(flight_dir: Path) -> tuple[Path, Path] | None:
    """``checkpoints.csv`` and ``checkpoint_obs.csv`` of a flight, or None.

    ``checkpoints:`` in ``flight.yaml`` names the check point file; ``checkpoint_obs.csv``
    lies beside it.

    Raises
    ------
    InputDataError
        Check points without their observations file.
    """
    name = CHECKPOINTS_FILE
    yaml_path = flight_dir / FLIGHT_YAML
    if yaml_path.is_file():
        configured = load_flight_config(yaml_path).checkpoints
        name = configured if configured is not None else name
    path = Path(name) if Path(name).is_absolute() else flight_dir / name
    if not path.is_file():
        if name != CHECKPOINTS_FILE or exists_as_anything(path):
            raise InputDataError(f"{path}: {file_problem(path)} (checkpoints in {yaml_path})")
        return None
    obs = path.parent / CHECKPOINT_OBS_FILE
    if not obs.is_file():
        raise InputDataError(f"{obs}: {file_problem(obs)} (observations of the check points "
                             f"in {path})")
    return path, obs


def checkpoint_report(method: str, eop: EopTable, run: RunFolder, known_path: Path,
                      obs_path: Path, exclude: frozenset[str] = frozenset()) -> CheckpointReport:
    """Intersect every check point from its observations with ``eop``; residuals and ASPRS.

    Check points named in ``exclude`` (ground control points of the run) are left out.

    Raises
    ------
    InputDataError
        An observed check point missing from the check point file.
    """
    known = read_ground_points(known_path)
    obs_image, point_ids, obs_point, uv = read_observations(obs_path, run.nav.index())
    kindex = known.index()
    for pid in point_ids:
        if pid not in kindex:
            raise InputDataError(f"{obs_path}: check point {pid!r} is not in {known_path}")
    cam = run.camera
    margin = CHECKPOINT_FRAME_SIGMAS * run.inputs.sigma_image_px
    outside = ~((uv[:, 0] >= -0.5 - margin) & (uv[:, 0] <= cam.width_px - 0.5 + margin)
                & (uv[:, 1] >= -0.5 - margin) & (uv[:, 1] <= cam.height_px - 0.5 + margin))
    if outside.any():
        q = int(np.flatnonzero(outside)[0])
        raise InputDataError(
            f"{obs_path}: check point {point_ids[obs_point[q]]!r} in image "
            f"{run.nav.image_ids[obs_image[q]]!r}: pixel ({uv[q, 0]:.4g}, {uv[q, 1]:.4g}) lies "
            f"outside the {cam.width_px} x {cam.height_px} px image "
            f"({int(outside.sum())} such observation(s))")
    eindex = eop.index()
    eop_rows = np.array([eindex.get(run.nav.image_ids[i], -1) for i in obs_image],
                        dtype=np.int64)
    sel = eop_rows >= 0
    ideal = PixelCorrector(camera=run.camera).ideal_pixels(uv[sel])
    X, _ = intersect_rays(eop.eop[eop_rows[sel]], ideal, obs_point[sel], len(point_ids),
                          pinhole_camera(run.camera))
    counts = np.bincount(obs_point[sel], minlength=len(point_ids))
    ok = np.all(np.isfinite(X), axis=1)
    residuals = tuple(
        PointResidual(point=pid, n_images=int(counts[j]),
                      x_m=float(known.xyz_m[kindex[pid], 0]),
                      y_m=float(known.xyz_m[kindex[pid], 1]),
                      z_m=float(known.xyz_m[kindex[pid], 2]),
                      dx_m=float(X[j, 0] - known.xyz_m[kindex[pid], 0]),
                      dy_m=float(X[j, 1] - known.xyz_m[kindex[pid], 1]),
                      dz_m=float(X[j, 2] - known.xyz_m[kindex[pid], 2]))
        for j, pid in enumerate(point_ids) if ok[j] and pid not in exclude)
    # largest first (3D length), ties by name: the table a surveyor reads top down
    residuals = tuple(sorted(residuals, key=lambda r: (-math.sqrt(
        r.dx_m**2 + r.dy_m**2 + r.dz_m**2), r.point)))
    d = np.array([[r.dx_m, r.dy_m, r.dz_m] for r in residuals]).reshape(-1, 3)
    return CheckpointReport(method=method, table=asprs_table(d), residuals=residuals,
                            not_intersected=tuple(p for p, k in zip(point_ids, ok, strict=True)
                                                  if not k and p not in exclude),
                            excluded_control=tuple(sorted(p for p in point_ids
                                                          if p in exclude)))


def build_report(out_dir: Path | str, compare: Sequence[Path | str] = ()) -> tuple[
        Report, dict[str, object]]:
    """Gather the numbers of the report (no file is written).

    Returns
    -------
    Report
    dict
        Per-image series for the figures (``errors``: method -> (pos_m, att_deg) per image;
        ``series``: method -> run.json ``images``; ``checkpoints``).
    """
    run = read_run(out_dir)
    notes: list[str] = []
    obs = read_observations(run.observations_path, run.nav.index())
    runs = [run]
    for other_dir in compare:
        other = read_run(other_dir)
        _same_flight(run, other)
        runs.append(other)
    fix = np.all(np.isfinite(run.nav.eop), axis=1)  # GNSS dropouts have no direct EOP
    methods = [_Method(label=DIRECT, eop=EopTable(
        image_ids=tuple(np.asarray(run.nav.image_ids)[fix]), eop=run.nav.eop[fix],
        sigma=np.full_like(run.nav.eop[fix], np.nan)), points=_direct_points(run, obs),
        record=None)]
    labels = {DIRECT}
    for r in runs:
        label = r.method if r.method not in labels else f"{r.method} ({r.path.name})"
        labels.add(label)
        methods.append(_Method(label=label, eop=r.eop, points=r.points, record=r.record))
    ref_dir = run.path / REFERENCE_DIR
    reference_record: dict[str, object] | None = None
    if (ref_dir / REFERENCE_JSON).is_file():
        reference_record = json.loads((ref_dir / REFERENCE_JSON).read_text(encoding="utf-8"))
        methods.append(_Method(label=REFERENCE, eop=read_eop_csv(ref_dir / EOP_FILE),
                               points=read_points_csv(ref_dir / POINTS_FILE), record=None))
    else:
        notes.append(f"no COLMAP reference ({ref_dir}); run `seqat reference {run.path}`")

    truth = read_truth(run.flight_dir) if run.flight_dir.is_dir() else None
    against: str | None = None
    accuracy: dict[str, MethodAccuracy] = {}
    errors: dict[str, tuple[FloatArray, FloatArray]] = {}
    if truth is not None:
        against, ref_eop_ids, ref_eop = "truth", truth.eop.image_ids, truth.eop.eop
        ref_pt_ids, ref_xyz = truth.points.point_ids, truth.points.xyz_m
    elif reference_record is not None:
        ref = next(m for m in methods if m.label == REFERENCE)
        against, ref_eop_ids, ref_eop = "reference", ref.eop.image_ids, ref.eop.eop
        assert ref.points is not None
        ref_pt_ids, ref_xyz = ref.points.point_ids, ref.points.xyz_m
        notes.append("the flight has no truth/: the orientations are compared with the "
                     "COLMAP reference (agreement on the same tie points, not accuracy)")
    else:
        notes.append("neither truth/ nor a COLMAP reference: no accuracy figures")
    if against is not None:
        for m in methods:
            if against == "reference" and m.label == REFERENCE:
                continue
            pts = m.points
            pid = pts.point_ids if pts is not None else ()
            xyz = pts.xyz_m if pts is not None else np.zeros((0, 3))
            accuracy[m.label] = method_accuracy(m.label, against, m.eop.image_ids,
                                                m.eop.eop, pid, xyz, ref_eop_ids, ref_eop,
                                                ref_pt_ids, ref_xyz)
            _, d_pos, d_att = eop_differences(m.eop.image_ids, m.eop.eop, ref_eop_ids, ref_eop)
            errors[m.label] = (np.linalg.norm(d_pos, axis=1), np.abs(d_att).max(axis=1))

    control = read_run_control(run.path)
    ctrl = control_reports(control, [(m.label, m.points) for m in methods
                                     if m.label != DIRECT])
    main_ctrl = next((c for c in ctrl if c.method == methods[1].label), None)
    exclude = frozenset(control.names) if control is not None else frozenset()
    cps: list[CheckpointReport] = []
    found = find_checkpoints(run.flight_dir) if run.flight_dir.is_dir() else None
    if found is None:
        notes.append("the flight has no check points (checkpoints.csv + checkpoint_obs.csv)")
    else:
        cps = [checkpoint_report(m.label, m.eop, run, *found, exclude=exclude)
               for m in methods]
    main_cp = next((c for c in cps if c.method == methods[1].label), None)
    checkpoints = None if main_cp is None else {
        "method": main_cp.method, "count": main_cp.table.count, **main_cp.table.figures(),
        "horizontal_class_cm": main_cp.table.horizontal_class_cm,
        "vertical_class_cm": main_cp.table.vertical_class_cm,
        "excluded_as_control": list(main_cp.excluded_control)}
    if main_cp is not None and main_cp.excluded_control:
        notes.append(f"check point(s) {', '.join(main_cp.excluded_control)} are ground control "
                     "points of the run: left out of the check statistics")
    realtime = tuple(_realtime(m.label, m.record) for m in methods if m.record is not None)
    totals = run.record.get("totals", {})
    assert isinstance(totals, dict)
    sfm = read_sfm_agreement(run.path)
    ortho = read_ortho_json(run.path)
    report = Report(
        version=REPORT_VERSION, title=report_title(run),
        verdict=(*verdict_lines(None if main_cp is None else main_cp.table,
                                methods[1].label, truth is not None),
                 *control_verdict(main_ctrl, () if main_cp is None
                                  else main_cp.excluded_control)),
        warnings=collect_warnings(run.record, ortho, reference_record, sfm,
                                  () if main_cp is None else main_cp.not_intersected, notes),
        run=str(run.path), flight=str(run.flight_dir),
        methods=tuple(m.label for m in methods), flight_summary=_flight_summary(run),
        tie_points=_tie_points(run, obs), sigma0=float(totals.get("sigma0") or float("nan")),
        processing_ms_per_image_median=realtime[0].update_ms_median,
        processing_total_s=float(totals.get("wall_s") or float("nan")),
        reference=reference_record, accuracy_against=against, accuracy=accuracy,
        realtime=realtime, live=live_operation(run.record),
        latency=latency_table(run.record, ortho),
        checkpoints=checkpoints, checkpoint_reports=tuple(cps),
        notes=tuple(notes), robustness=summarise(run.record),
        sfm_agreement=sfm, control=control_json(main_ctrl, control), control_reports=ctrl)
    extras: dict[str, object] = {
        "run_path": run.path, "crs": run.crs,
        "cameras_xyz_m": run.eop.eop[:, :3], "points_xyz_m": run.points.xyz_m,
        "errors": errors,
        "control_xyz_m": control.xyz_m if control is not None else np.zeros((0, 3)),
        "control_names": control.names if control is not None else (),
        "series": {m.label: m.record.get("images", []) for m in methods if m.record is not None},
    }
    return report, extras


def main_checkpoints(report: Report) -> CheckpointReport | None:
    """The check points of the run in OUT (the first method after ``direct``), or None."""
    return next((c for c in report.checkpoint_reports if c.method == report.methods[1]), None)


def format_report_json(report: Report) -> str:
    """Text of ``report.json`` (strict JSON, non-finite numbers as ``null``)."""
    return json.dumps(to_jsonable(report), indent=JSON_INDENT, allow_nan=False) + "\n"
