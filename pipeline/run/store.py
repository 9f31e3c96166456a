"""Result files of a run: ``eop.csv``, ``points.csv``, ``run.json``, ``nav.csv``,
``observations.csv`` (docs/formats.md), and :func:`read_run` for the later stages.

A run folder is self-contained: besides the estimates it holds the navigation input in the
working CRS (``nav.csv``), the image observations the estimator received
(``observations.csv``, observed pixels of the full-resolution images) and, in ``run.json``,
the CRS, the camera and the a priori sigmas, so the reference, ortho and report stages need
nothing else.

Every file is written atomically: a temporary file in the same folder, ``fsync``, then
``os.replace`` (and an ``fsync`` of the folder), so a reader never sees a half-written file and
a failed run leaves the previous results untouched (:mod:`pipeline.common.atomic`;
:func:`~pipeline.common.atomic.write_files_atomically` publishes a set of files together and
removes the output folder again if it created it and failed). Column schemas and file names:
:mod:`pipeline.common.columns`.

Numbers are written with Python's shortest round-trip representation (``repr``): reading a
file back gives the written float64 values exactly (angles pass through degrees, so they
round-trip to about 1e-15 relative).
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj
from pyproj.exceptions import CRSError

from pipeline.common import jsonio
from pipeline.common.atomic import atomic_write_text, write_files_atomically
from pipeline.common.columns import (
    EOP_COLUMNS,
    EOP_FILE,
    NAV_COLUMNS,
    NAV_FILE,
    OBSERVATIONS_FILE,
    POINT_COLUMNS,
    POINTS_FILE,
    RUN_FILE,
    RUN_OBS_COLUMNS,
)
from pipeline.common.csvio import format_csv_line, read_csv
from pipeline.common.strict_yaml import build_dataclass
from pipeline.common.tables import EopTable, NavTable, PointTable
from pipeline.flight.camera import estimated_camera
from pipeline.flight.inputs import RunInputs, SkippedImage
from pipeline.flight.schema import CameraConfig
from pipeline.run.accuracy import Accuracy
from pipeline.run.control import CONTROL_FILE
from pipeline.run.exports import export_files
from pipeline.run.robustness import RobustnessRecord
from seqat.errors import ConfigError, InputDataError
from seqat.types import CameraEstimate, EopEstimate, ImageUpdate, PointEstimate, Solution

#: Version of the ``run.json`` layout (bumped on incompatible changes).
RUN_JSON_VERSION = 1
#: Percentiles of the per-image update time reported in ``run.json``.
TIMING_PERCENTILES = (95.0, 99.0)
#: Indentation of ``run.json``.
JSON_INDENT = 1
#: Number of position (metres) and angle (radians) components of an EOP vector.
XYZ = 3


def fmt(value: float) -> str:
    """Shortest decimal text that reads back as the same float64 (``nan`` for NaN)."""
    return repr(float(value))


# --------------------------------------------------------------------------------------------
# eop.csv / points.csv
# --------------------------------------------------------------------------------------------


def _eop_fields(eop: np.ndarray, sigma: np.ndarray) -> list[str]:
    """Position, angles (deg) and their sigmas of one image as formatted fields."""
    values = np.concatenate([eop[:XYZ], np.degrees(eop[XYZ:]), sigma[:XYZ],
                             np.degrees(sigma[XYZ:])])
    return [fmt(v) for v in values]


def format_eop_csv(eops: Sequence[EopEstimate]) -> str:
    """Text of an ``eop.csv`` (angles converted to degrees)."""
    lines = [format_csv_line(EOP_COLUMNS)]
    lines += [format_csv_line([e.image_id, *_eop_fields(e.eop, e.sigma)]) for e in eops]
    return "".join(lines)


def format_points_csv(points: Sequence[PointEstimate]) -> str:
    """Text of a ``points.csv``."""
    lines = [format_csv_line(POINT_COLUMNS)]
    lines += [format_csv_line([p.point_id, *(fmt(v) for v in p.xyz_m),
                               *(fmt(v) for v in p.sigma_m), str(int(p.n_obs))])
              for p in points]
    return "".join(lines)


def write_eop_csv(path: Path | str, eops: Sequence[EopEstimate]) -> None:
    """Write ``eop.csv`` atomically."""
    atomic_write_text(path, format_eop_csv(eops))


def write_points_csv(path: Path | str, points: Sequence[PointEstimate]) -> None:
    """Write ``points.csv`` atomically."""
    atomic_write_text(path, format_points_csv(points))


def read_eop_csv(path: Path | str) -> EopTable:
    """Read an output ``eop.csv``; sigmas may be ``nan``, ids must be unique.

    Returns
    -------
    EopTable
        Metres and radians.
    """
    ids: list[str] = []
    values: list[list[float]] = []
    first: dict[str, int] = {}
    for row in read_csv(path, EOP_COLUMNS):
        image = row.ident("image")
        if image in first:
            raise row.error(f"duplicate image {image!r} (first at line {first[image]})")
        first[image] = row.line
        ids.append(image)
        values.append([row.number(c) for c in EOP_COLUMNS[1:7]]
                      + [row.number(c, allow_nan=True) for c in EOP_COLUMNS[7:]])
    arr = np.asarray(values, dtype=np.float64).reshape(-1, 12)
    eop, sigma = arr[:, :6].copy(), arr[:, 6:].copy()
    eop[:, XYZ:] = np.radians(eop[:, XYZ:])
    sigma[:, XYZ:] = np.radians(sigma[:, XYZ:])
    return EopTable(image_ids=tuple(ids), eop=eop, sigma=sigma)


def read_points_csv(path: Path | str) -> PointTable:
    """Read an output ``points.csv``; sigmas may be ``nan``, ids must be unique."""
    ids: list[str] = []
    xyz: list[list[float]] = []
    sig: list[list[float]] = []
    n_obs: list[int] = []
    first: dict[str, int] = {}
    for row in read_csv(path, POINT_COLUMNS):
        point = row.ident("point")
        if point in first:
            raise row.error(f"duplicate point {point!r} (first at line {first[point]})")
        first[point] = row.line
        ids.append(point)
        xyz.append([row.number(c) for c in ("x_m", "y_m", "z_m")])
        sig.append([row.number(c, allow_nan=True) for c in ("sx_m", "sy_m", "sz_m")])
        n_obs.append(row.integer("n_obs"))
    return PointTable(point_ids=tuple(ids), xyz_m=np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
                      sigma_m=np.asarray(sig, dtype=np.float64).reshape(-1, 3),
                      n_obs=np.asarray(n_obs, dtype=np.int64))


def format_nav_csv(ids: Sequence[str], times_s: np.ndarray, eop: np.ndarray) -> str:
    """Text of a projected ``nav.csv`` (or ``truth/eop.csv``); angles in radians -> degrees."""
    lines = [format_csv_line(NAV_COLUMNS)]
    for iid, t, e in zip(ids, times_s, eop, strict=True):
        lines.append(format_csv_line([iid, fmt(t), *(fmt(v) for v in e[:XYZ]),
                                      *(fmt(v) for v in np.degrees(e[XYZ:]))]))
    return "".join(lines)


def format_observation_lines(image_id: str | Sequence[str], point_ids: Sequence[str],
                             uv_px: np.ndarray, frame_id: str | None = None) -> str:
    """Rows of one image for ``observations.csv`` (no header); with ``frame_id`` the
    ``frame`` column too (the image update the rows arrived with). ``image_id`` may give
    one image per row (the late observations a frame carries)."""
    images = [image_id] * len(point_ids) if isinstance(image_id, str) else list(image_id)
    tail = [] if frame_id is None else [frame_id]
    return "".join(format_csv_line([iid, pid, fmt(u), fmt(v), *tail])
                   for iid, pid, (u, v) in zip(images, point_ids,
                                               np.asarray(uv_px).reshape(-1, 2), strict=True))


def eop_table(eops: Sequence[EopEstimate]) -> EopTable:
    """Stack estimates into an :class:`EopTable`."""
    return EopTable(image_ids=tuple(e.image_id for e in eops),
                    eop=np.asarray([e.eop for e in eops], dtype=np.float64).reshape(-1, 6),
                    sigma=np.asarray([e.sigma for e in eops], dtype=np.float64).reshape(-1, 6))


def point_table(points: Sequence[PointEstimate]) -> PointTable:
    """Stack estimates into a :class:`PointTable`."""
    return PointTable(point_ids=tuple(p.point_id for p in points),
                      xyz_m=np.asarray([p.xyz_m for p in points], dtype=np.float64).reshape(-1, 3),
                      sigma_m=np.asarray([p.sigma_m for p in points],
                                         dtype=np.float64).reshape(-1, 3),
                      n_obs=np.asarray([p.n_obs for p in points], dtype=np.int64))


# --------------------------------------------------------------------------------------------
# run.json
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class TimingStats:
    """Statistics of the per-image update times, milliseconds (NaN when there are none)."""

    median_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float
    total_ms: float

    @classmethod
    def from_samples(cls, samples_ms: Sequence[float] | np.ndarray) -> TimingStats:
        """Summarise update times (milliseconds)."""
        t = np.asarray(samples_ms, dtype=np.float64)
        if t.size == 0:
            nan = float("nan")
            return cls(median_ms=nan, p95_ms=nan, p99_ms=nan, max_ms=nan, total_ms=0.0)
        p95, p99 = np.percentile(t, TIMING_PERCENTILES)
        return cls(median_ms=float(np.median(t)), p95_ms=float(p95), p99_ms=float(p99),
                   max_ms=float(t.max()), total_ms=float(t.sum()))


@dataclass(frozen=True, kw_only=True)
class RunTotals:
    """Totals of a run (``run.json`` ``totals``)."""

    images: int
    points: int
    observations: int
    update_ms: TimingStats  # every image, initial simultaneous stage included
    sequential_update_ms: TimingStats  # images of the sequential stage only (Seq-R / Seq-F)
    wall_s: float
    sigma0: float
    redundancy: int
    accuracy: Accuracy | None = None
    latency_ms: TimingStats | None = None  # end to end per image (watch mode)
    journal_ms: TimingStats | None = None  # journaling each new image (state file + record)
    #: late observations: ``observations``, ``images`` (that got some),
    #: ``images_tied_only_by_late`` (RunSession.late_summary)
    late: Mapping[str, object] | None = None
    #: second starts tried after updates (``images[].second_start_ms``); None: none
    second_start_ms: TimingStats | None = None
    #: refinements after the sequential updates (``images[].refine_ms``: drift check,
    #: re-linearisation, second start; not in ``update_ms``); None: none run
    sequential_refine_ms: TimingStats | None = None


@dataclass(frozen=True, kw_only=True, eq=False)
class RunRecord:
    """Everything ``run.json`` holds.

    Attributes
    ----------
    method : str
        ``seq-r``, ``seq-f`` or ``sim``.
    flight : str
        The flight folder.
    inputs : RunInputs
        CRS, camera, sigmas, skipped images and warnings (``nav`` goes to ``nav.csv``).
    options : object
        The estimator options (a dataclass such as ``SequentialOptions``), serialised field
        by field.
    final_only : bool
    images : tuple[ImageUpdate, ...]
        One record per image, in acquisition order.
    totals : RunTotals
    tracking_options : object or None
        Tie-point tracker options (image flights).
    tracking : tuple[object, ...]
        Per-image tracker statistics (image flights; empty otherwise), stored in
        ``images[i].tracking``.
    live : tuple[object, ...]
        Per-image timings and counts (:class:`pipeline.run.session.ImageLive`), stored in
        ``images[i].live``.
    latency_budget : object or None
        ``--budget-ms``: the budget and its threshold changes
        (:class:`pipeline.run.budget.BudgetReport`).
    mode : str
        ``run`` or ``watch``.
    replayed : int
        Images replayed from the journal (``--resume``).
    robustness : RobustnessRecord or None
        Data snooping and GNSS dropouts (:mod:`pipeline.run.robustness`).
    camera_estimate : CameraEstimate or None
        The self-calibrated camera.
    control : Mapping or None
        Ground control: ``run.json`` ``control`` (:func:`pipeline.run.control.control_record`).
    control_csv : str or None
        Text of ``control.csv`` (:func:`pipeline.run.control.format_control_csv`).
    """

    method: str
    flight: str
    inputs: RunInputs
    options: object
    final_only: bool
    images: tuple[ImageUpdate, ...]
    totals: RunTotals
    tracking_options: object | None = None
    tracking: tuple[object, ...] = ()
    live: tuple[object, ...] = ()
    latency_budget: object | None = None
    mode: str = "run"
    replayed: int = 0
    robustness: RobustnessRecord | None = None
    #: The self-calibrated camera (None: the camera was fixed).
    camera_estimate: CameraEstimate | None = None
    control: Mapping[str, object] | None = None
    control_csv: str | None = None


def camera_estimate_json(inputs: RunInputs, est: CameraEstimate) -> dict[str, object]:
    """run.json ``camera_estimate``: the estimate with its sigmas and correlations, and the
    camera in ``flight.yaml`` form that later stages use (docs/formats.md)."""
    camera = to_jsonable(estimated_camera(inputs.camera, est.camera))
    return {**est.as_dict(), "camera": camera}


def eop_json(eop: EopEstimate) -> dict[str, object]:
    """An EOP estimate with the units and names of ``eop.csv`` (JSON-ready)."""
    return {"image": eop.image_id,
            **{c: _finite_or_none(float(v))
               for c, v in zip(EOP_COLUMNS[1:], np.concatenate(
                   [eop.eop[:XYZ], np.degrees(eop.eop[XYZ:]), eop.sigma[:XYZ],
                    np.degrees(eop.sigma[XYZ:])]), strict=True)}}


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def to_jsonable(value: object) -> object:
    """Convert dataclasses, numpy values, enums and paths to JSON types (NaN/inf -> null)."""
    if isinstance(value, EopEstimate):
        return eop_json(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return to_jsonable(value.value)
    if isinstance(value, bool | str) or value is None:
        return value
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return _finite_or_none(float(value))
    if isinstance(value, np.ndarray):
        return [to_jsonable(v) for v in value.tolist()]
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot serialise {type(value).__name__} to JSON")


def _inputs_json(inputs: RunInputs) -> dict[str, object]:
    sigma = np.asarray(inputs.nav_sigma, dtype=np.float64)
    camera = to_jsonable(inputs.camera)
    assert isinstance(camera, dict)
    return {
        "crs": inputs.crs.to_wkt(),
        "crs_name": inputs.crs.name,
        "camera": {**camera, "approximate": inputs.camera_approximate},
        "nav_sigma": {"position_m": to_jsonable(sigma[:XYZ]),
                      "attitude_deg": to_jsonable(np.degrees(sigma[XYZ:]))},
        "sigma_image_px": inputs.sigma_image_px,
        "images_dir": None if inputs.images_dir is None else str(inputs.images_dir),
        "skipped": to_jsonable(inputs.skipped),
        "warnings": list(inputs.warnings),
    }


def format_run_json(record: RunRecord) -> str:
    """Text of ``run.json`` (strict JSON: non-finite numbers become ``null``)."""
    images = to_jsonable(record.images)
    assert isinstance(images, list)
    for image, stats in zip(images, record.tracking, strict=False):
        image["tracking"] = to_jsonable(stats)
    for image, live in zip(images, record.live, strict=False):
        image["live"] = to_jsonable(live)
    doc = {"version": RUN_JSON_VERSION, "method": record.method, "flight": record.flight,
           "mode": record.mode, "replayed": record.replayed,
           **_inputs_json(record.inputs),
           "options": to_jsonable(record.options), "final_only": record.final_only,
           "tracking_options": to_jsonable(record.tracking_options),
           "latency_budget": to_jsonable(record.latency_budget),
           "images": images, "totals": to_jsonable(record.totals),
           "robustness": to_jsonable(record.robustness),
           "control": to_jsonable(record.control)}
    if record.camera_estimate is not None:
        doc["camera_estimate"] = camera_estimate_json(record.inputs, record.camera_estimate)
    return json.dumps(doc, indent=JSON_INDENT, allow_nan=False) + "\n"


def write_run_json(path: Path | str, record: RunRecord) -> None:
    """Write ``run.json`` atomically."""
    atomic_write_text(path, format_run_json(record))


def write_run_outputs(out_dir: Path | str, solution: Solution, record: RunRecord,
                      observations_text: str) -> tuple[Path, ...]:
    """Publish the files of a run together (atomically, all or none).

    Parameters
    ----------
    out_dir : Path or str
    solution : Solution
    record : RunRecord
    observations_text : str
        Rows of ``observations.csv`` without the header (:func:`format_observation_lines`).

    Returns
    -------
    tuple[Path, ...]
        ``eop.csv``, ``points.csv``, ``run.json``, ``nav.csv``, ``observations.csv``, then
        the exports for other tools (:func:`pipeline.run.exports.export_files`).
    """
    nav = record.inputs.nav
    inputs = record.inputs
    exports = export_files(eop_table(solution.eops), point_table(solution.points), inputs.crs,
                           inputs.camera, inputs.images_dir)
    return write_files_atomically(out_dir, {
        EOP_FILE: format_eop_csv(solution.eops),
        POINTS_FILE: format_points_csv(solution.points),
        RUN_FILE: format_run_json(record),
        NAV_FILE: format_nav_csv(nav.image_ids, nav.times_s, nav.eop),
        OBSERVATIONS_FILE: format_csv_line(RUN_OBS_COLUMNS) + observations_text,
        **({CONTROL_FILE: record.control_csv} if record.control_csv is not None else {}),
        **exports,
    })


# --------------------------------------------------------------------------------------------
# Reading a run folder (later stages)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class RunFolder:
    """A finished run's output folder, read back (:func:`read_run`).

    Attributes
    ----------
    path : Path
    method : str
    flight_dir : Path
    inputs : RunInputs
    eop : EopTable
        The estimates of ``eop.csv``.
    points : PointTable
        The estimates of ``points.csv``.
    observations_path : Path
        ``observations.csv`` of the run (observed pixels, full resolution).
    record : dict
        ``run.json`` as parsed JSON.
    """

    path: Path
    method: str
    flight_dir: Path
    inputs: RunInputs
    eop: EopTable
    points: PointTable
    observations_path: Path
    record: Mapping[str, object]
    estimated_camera: CameraConfig | None = None

    @property
    def crs(self) -> pyproj.CRS:
        return self.inputs.crs

    @property
    def camera(self) -> CameraConfig:
        """The camera of the results: the self-calibrated one when the run estimated it
        (run.json ``camera_estimate``), else the input camera."""
        return self.estimated_camera if self.estimated_camera is not None else self.inputs.camera

    @property
    def camera_prior(self) -> CameraConfig:
        """The input camera (EXIF or ``flight.yaml``)."""
        return self.inputs.camera

    @property
    def nav(self) -> NavTable:
        return self.inputs.nav

    @property
    def nav_sigma(self) -> np.ndarray:
        return self.inputs.nav_sigma

    @property
    def sigma_image_px(self) -> float:
        return self.inputs.sigma_image_px

    @property
    def images_dir(self) -> Path | None:
        return self.inputs.images_dir


def _json_field(doc: Mapping[str, object], key: str, source: Path) -> object:
    if key not in doc:
        raise InputDataError(f"{source}: missing key {key!r} (written by an older seqat? run "
                             "`seqat run` again)")
    return doc[key]


def _triple(value: object, key: str, source: Path) -> list[float]:
    if not (isinstance(value, list) and len(value) == XYZ
            and all(isinstance(v, int | float) for v in value)):
        raise InputDataError(f"{source}: {key}: expected a list of 3 numbers, got {value!r}")
    return [float(v) for v in value]


def read_json_object(path: Path) -> dict[str, object]:
    """A JSON file holding an object (``run.json``, ``ortho.json``).

    Raises
    ------
    InputDataError
        Unreadable, not JSON, or not an object.
    """
    try:
        doc = jsonio.loads(path.read_bytes())
    except (OSError, jsonio.JSONDecodeError) as err:
        raise InputDataError(f"{path}: cannot read {path.name}: {err}") from err
    if not isinstance(doc, dict):
        raise InputDataError(f"{path}: expected a JSON object")
    return doc


def read_run(out_dir: Path | str) -> RunFolder:
    """Read a run folder written by ``seqat run`` (docs/formats.md, *Output folder*).

    Raises
    ------
    InputDataError
        Missing folder or file, malformed ``run.json``, CSV or camera.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise InputDataError(f"{out}: no such run folder")
    run_path = out / RUN_FILE
    if not run_path.is_file():
        raise InputDataError(f"{run_path}: no such file (is {out} the output of `seqat run`?)")
    doc = read_json_object(run_path)
    try:
        crs = pyproj.CRS.from_wkt(str(_json_field(doc, "crs", run_path)))
    except CRSError as err:
        raise InputDataError(f"{run_path}: crs: not a valid WKT CRS: {err}") from err
    camera_doc = _json_field(doc, "camera", run_path)
    if not isinstance(camera_doc, dict):
        raise InputDataError(f"{run_path}: camera: expected an object")
    camera_doc = dict(camera_doc)
    approximate = bool(camera_doc.pop("approximate", False))
    try:
        camera = build_dataclass(CameraConfig, camera_doc, str(run_path), key="camera")
    except ConfigError as err:
        raise InputDataError(str(err)) from err
    sig = _json_field(doc, "nav_sigma", run_path)
    if not isinstance(sig, dict):
        raise InputDataError(f"{run_path}: nav_sigma: expected an object")
    nav_sigma = np.concatenate([
        _triple(sig.get("position_m"), "nav_sigma.position_m", run_path),
        np.radians(_triple(sig.get("attitude_deg"), "nav_sigma.attitude_deg", run_path))])
    images_dir = doc.get("images_dir")
    from pipeline.flight.nav_files import (
        read_nav_projected,  # flight imports store: no cycle at load
    )
    inputs = RunInputs(
        crs=crs, camera=camera, camera_approximate=approximate,
        nav=read_nav_projected(out / NAV_FILE, allow_missing=True), nav_sigma=nav_sigma,
        sigma_image_px=float(_json_field(doc, "sigma_image_px", run_path)),  # type: ignore[arg-type]
        images_dir=None if images_dir is None else Path(str(images_dir)),
        skipped=tuple(SkippedImage(**s) for s in doc.get("skipped", [])),
        warnings=tuple(doc.get("warnings", [])))
    obs_path = out / OBSERVATIONS_FILE
    if not obs_path.is_file():
        raise InputDataError(f"{obs_path}: no such file")
    estimated = None
    est_doc = doc.get("camera_estimate")
    if est_doc is not None:
        if not isinstance(est_doc, dict) or not isinstance(est_doc.get("camera"), dict):
            raise InputDataError(f"{run_path}: camera_estimate: expected an object with a "
                                 f"'camera' object")
        try:
            estimated = build_dataclass(CameraConfig, est_doc["camera"], str(run_path),
                                        key="camera_estimate.camera")
        except ConfigError as err:
            raise InputDataError(str(err)) from err
    return RunFolder(path=out, method=str(_json_field(doc, "method", run_path)),
                     flight_dir=Path(str(_json_field(doc, "flight", run_path))), inputs=inputs,
                     eop=read_eop_csv(out / EOP_FILE), points=read_points_csv(out / POINTS_FILE),
                     observations_path=obs_path, record=doc, estimated_camera=estimated)
