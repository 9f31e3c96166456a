"""``seqat reference OUT``: the COLMAP reference of a run, written to ``OUT/reference/``.

Reads the run folder (nav = priors, observed pixels, the run's estimates as initial values),
adjusts with :func:`pipeline.reference.colmap_ba.adjust_reference` (COLMAP's Ceres bundle adjuster
under Sim's stochastic model) and publishes ``OUT/reference/`` whole: ``colmap/`` (the COLMAP
model, binary and text, world coordinates), ``eop.csv`` and ``points.csv`` (our formats) and
``reference.json`` (docs/formats.md). An SfM check already there (``sfm/``, written by
``seqat reference OUT --sfm``) is kept.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.common.atomic import atomic_write_text, building_folder
from pipeline.common.columns import (
    EOP_FILE,
    OBS_FRAME_COLUMN,
    POINTS_FILE,
    REFERENCE_DIR,
    SFM_DIR,
)
from pipeline.common.csvio import read_csv
from pipeline.flight.camera import PixelCorrector, pinhole_camera
from pipeline.flight.nav_files import OBSERVATION_COLUMNS
from pipeline.flight.schema import CameraConfig
from pipeline.reference.colmap_ba import (
    CAMERA_ID,
    PriorKind,
    ReferenceInput,
    ReferenceOptions,
    ReferenceResult,
    adjust_reference,
    loss_of_run,
    run_loss_scale,
)
from pipeline.run.control import CONTROL_FILE, read_control_csv
from pipeline.run.exports import image_file_names
from pipeline.run.store import (
    JSON_INDENT,
    RunFolder,
    format_eop_csv,
    format_points_csv,
    read_run,
    to_jsonable,
)
from seqat.errors import EstimationError
from seqat.geometry import intersect_rays
from seqat.types import EopEstimate, FloatArray, PointEstimate

#: COLMAP model inside it (binary and text files side by side).
COLMAP_MODEL_DIR = "colmap"
#: The reference's own record.
REFERENCE_JSON = "reference.json"
#: Camera centres whose second singular value is below this fraction of the first are
#: (nearly) collinear: position-only priors then leave the roll about the line (almost) free.
#: A straight strip with metre-level wander over a kilometre is ~1e-3.
COLLINEAR_RATIO = 0.05


def read_observations(path: Path, image_index: dict[str, int]) -> tuple[
        np.ndarray, tuple[str, ...], np.ndarray, FloatArray]:
    """Read ``image,point,x_px,y_px`` (observed pixels) into index arrays.

    Returns
    -------
    obs_image : (k,) int
        Row of the image in ``image_index``.
    point_ids : tuple[str, ...]
        In order of first sight.
    obs_point : (k,) int
    uv_px : (k, 2) float

    Raises
    ------
    InputDataError
        Unknown image, duplicate (image, point), malformed row.
    """
    images: list[int] = []
    points: list[int] = []
    uv: list[tuple[float, float]] = []
    point_index: dict[str, int] = {}
    seen: dict[tuple[int, int], int] = {}
    for row in read_csv(path, OBSERVATION_COLUMNS, (OBS_FRAME_COLUMN,)):  # frame unused
        image = row.ident("image")
        i = image_index.get(image)
        if i is None:
            raise row.error(f"field 'image': unknown image {image!r} (not in the run's nav)")
        j = point_index.setdefault(row.ident("point"), len(point_index))
        if (i, j) in seen:
            raise row.error(f"duplicate observation of point {row.values['point']!r} in image "
                            f"{image!r} (first at line {seen[(i, j)]})")
        seen[(i, j)] = row.line
        images.append(i)
        points.append(j)
        uv.append((row.number("x_px"), row.number("y_px")))
    return (np.asarray(images, dtype=np.int64), tuple(point_index),
            np.asarray(points, dtype=np.int64), np.asarray(uv, dtype=np.float64).reshape(-1, 2))


def reference_input(run: RunFolder) -> tuple[ReferenceInput, int]:
    """Observations and initial values of the reference from a run.

    Initial EOPs are the run's estimates (nav where it has none); initial points the run's
    estimates, else a multi-ray intersection at those EOPs (ideal pixels). Points that
    cannot be intersected are left out, and so are images with no position from either
    (a GNSS dropout the run skipped).

    Returns
    -------
    ReferenceInput
    int
        Observations left out (points without an initial value, images without a position).
    """
    nav = run.nav
    index = nav.index()
    obs_image, point_ids, obs_point, uv = read_observations(run.observations_path, index)
    eop0 = nav.eop.copy()
    est = run.eop.index()
    for i, iid in enumerate(nav.image_ids):
        if iid in est and np.all(np.isfinite(run.eop.eop[est[iid]])):
            eop0[i] = run.eop.eop[est[iid]]
    # An image neither the run nor the GPS placed (a GNSS dropout the run skipped) has no
    # position to start from or to hold: the reference leaves it out, as the run did.
    placed = np.all(np.isfinite(eop0[:, :3]), axis=1)
    image_ids, nav_eop, n_unplaced = nav.image_ids, nav.eop, 0
    if not placed.all():
        image_ids = tuple(iid for iid, ok in zip(image_ids, placed, strict=True) if ok)
        nav_eop, eop0 = nav_eop[placed], eop0[placed]
        on = placed[obs_image]
        n_unplaced = int(np.count_nonzero(~on))
        obs_image, obs_point, uv = (np.cumsum(placed) - 1)[obs_image[on]], obs_point[on], uv[on]
    xyz0 = np.full((len(point_ids), 3), np.nan)
    pts = run.points.index()
    for j, pid in enumerate(point_ids):
        if pid in pts:
            xyz0[j] = run.points.xyz_m[pts[pid]]
    missing = ~np.all(np.isfinite(xyz0), axis=1)
    if np.any(missing):
        sel = missing[obs_point]
        ideal = PixelCorrector(camera=run.camera).ideal_pixels(uv[sel])
        X, _ = intersect_rays(eop0[obs_image[sel]], ideal, obs_point[sel], len(point_ids),
                              pinhole_camera(run.camera))
        xyz0[missing] = X[missing]
    ok = np.all(np.isfinite(xyz0), axis=1)
    keep = ok[obs_point]
    remap = np.cumsum(ok) - 1
    kept_ids = tuple(p for p, k in zip(point_ids, ok, strict=True) if k)
    control = read_control_csv(run.path / CONTROL_FILE)
    in_run = set(kept_ids)
    sel = ([k for k, p in enumerate(control.point_ids) if p in in_run]
           if control is not None else [])
    data = ReferenceInput(camera=run.camera, image_ids=image_ids, nav_eop=nav_eop,
                          nav_sigma=np.asarray(run.nav_sigma, dtype=np.float64),
                          sigma_px=run.sigma_image_px, point_ids=kept_ids,
                          obs_image=obs_image[keep], obs_point=remap[obs_point[keep]],
                          obs_uv_px=uv[keep], eop0=eop0, xyz0=xyz0[ok],
                          control_ids=tuple(control.point_ids[k] for k in sel)
                          if control is not None else (),
                          control_xyz=control.xyz_m[sel] if control is not None
                          else np.zeros((0, 3)),
                          control_sigma=control.sigma_m[sel] if control is not None
                          else np.zeros((0, 3)))
    return data, int(np.count_nonzero(~keep)) + n_unplaced


def check_prior_geometry(data: ReferenceInput, prior: PriorKind) -> None:
    """Position-only priors need camera centres that are not on one line.

    Raises
    ------
    EstimationError
        With the singular values of the centred positions.
    """
    if prior is not PriorKind.POSITION:
        return
    c = data.nav_eop[:, :3] - data.nav_eop[:, :3].mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[1] < COLLINEAR_RATIO * s[0]:
        raise EstimationError(
            f"position-only priors: the camera centres lie (nearly) on a line (singular values "
            f"{s[0]:.3g}, {s[1]:.3g} m), which leaves the roll about it free; use the "
            "6-DoF pose prior")


@dataclass(frozen=True, kw_only=True)
class ReferenceRecord:
    """``reference/reference.json``."""

    version: int
    run: str
    method_of_run: str
    options: ReferenceOptions
    camera_model: str
    camera: CameraConfig
    n_images: int
    n_images_adjusted: int
    n_points: int
    n_observations: int
    n_observations_left_out: int
    n_residuals: int
    n_prior_residuals: int
    converged: bool
    termination: str
    iterations: int
    sigma0: float
    redundancy: int
    rms_px: float
    ba_s: float
    linear_solver: str
    covariance: str
    origin_m: tuple[float, float, float]
    pycolmap_version: str
    n_control_points: int = 0  # ground control points adjusted with their surveyed prior
    n_control_residuals: int = 0


@dataclass(frozen=True, kw_only=True)
class ReferenceSummary:
    """Typed result of :func:`run_reference` (what ``seqat reference`` prints)."""

    out_dir: Path
    reference_dir: Path
    record: ReferenceRecord


def _eop_estimates(result: ReferenceResult) -> list[EopEstimate]:
    return [EopEstimate(image_id=iid, eop=result.eop[i], sigma=result.eop_sigma[i])
            for i, iid in enumerate(result.image_ids)]


def _point_estimates(result: ReferenceResult) -> list[PointEstimate]:
    return [PointEstimate(point_id=pid, xyz_m=result.xyz[j], sigma_m=result.xyz_sigma[j],
                          n_obs=int(result.n_obs[j])) for j, pid in enumerate(result.point_ids)]


def name_images(reconstruction: object, names: Mapping[str, str]) -> None:
    """Give the model's images the file names of the images folder (``img_0001.jpg``, not the
    image id ``img_0001``): COLMAP tools find the pixels by ``image_path / name``
    (``pycolmap.undistort_images``, dense reconstruction). Ids without a file keep the id."""
    for image in reconstruction.images.values():  # type: ignore[attr-defined]
        image.name = names.get(image.name, image.name)


def write_reference(out_dir: Path, result: ReferenceResult, record: ReferenceRecord,
                    image_names: Mapping[str, str] | None = None) -> Path:
    """Publish ``out_dir/reference/`` whole: built in a temporary sibling, then renamed.

    ``image_names``: image id -> file name of the model's images (:func:`name_images`).

    Returns
    -------
    Path
        The reference folder.
    """
    target = out_dir / REFERENCE_DIR
    with building_folder(target) as tmp:
        if (target / SFM_DIR).is_dir():  # the SfM check (seqat reference --sfm) stays
            shutil.copytree(target / SFM_DIR, tmp / SFM_DIR)
        model = tmp / COLMAP_MODEL_DIR
        model.mkdir()
        if image_names:
            name_images(result.reconstruction, image_names)
        result.reconstruction.write_binary(str(model))
        result.reconstruction.write_text(str(model))
        atomic_write_text(tmp / EOP_FILE, format_eop_csv(_eop_estimates(result)))
        atomic_write_text(tmp / POINTS_FILE, format_points_csv(_point_estimates(result)))
        doc = to_jsonable(record)
        atomic_write_text(tmp / REFERENCE_JSON,
                          json.dumps(doc, indent=JSON_INDENT, allow_nan=False) + "\n")
    return target


def run_reference(out_dir: Path | str,
                  options: ReferenceOptions | None = None) -> ReferenceSummary:
    """Adjust a run's observations with COLMAP and write ``OUT/reference/``.

    Parameters
    ----------
    out_dir : Path or str
        A run folder (``seqat run ... --out OUT``).
    options : ReferenceOptions

    Returns
    -------
    ReferenceSummary

    Raises
    ------
    InputDataError
        Not a run folder, or malformed inputs (nothing is written).
    EstimationError
        The adjustment failed (nothing is written).
    """
    import pycolmap

    options = options if options is not None else ReferenceOptions()
    out = Path(out_dir)
    run = read_run(out)
    if options.robust_loss is None:  # the run's own loss
        loss, k = loss_of_run(run_loss_scale(run.record))
        options = dataclasses.replace(options, robust_loss=loss, loss_scale_sigmas=k)
    data, left_out = reference_input(run)
    check_prior_geometry(data, options.prior)
    result = adjust_reference(data, options)
    cam = result.reconstruction.camera(CAMERA_ID)
    record = ReferenceRecord(
        version=1, run=str(out), method_of_run=run.method, options=options,
        camera_model=cam.model.name, camera=result.camera, n_images=len(result.image_ids),
        n_images_adjusted=int(np.count_nonzero(result.in_adjustment)),
        n_points=len(result.point_ids), n_observations=int(np.sum(result.n_obs)),
        n_observations_left_out=left_out, n_residuals=result.n_residuals,
        n_prior_residuals=result.n_prior_residuals, converged=result.converged,
        termination=result.termination, iterations=result.iterations, sigma0=result.sigma0,
        redundancy=result.redundancy, rms_px=result.rms_px, ba_s=result.ba_s,
        linear_solver=result.linear_solver,
        covariance=result.covariance_status,
        origin_m=(float(result.origin[0]), float(result.origin[1]), float(result.origin[2])),
        pycolmap_version=str(pycolmap.__version__),
        n_control_points=result.n_control_points,
        n_control_residuals=result.n_control_residuals)
    names = image_file_names(run.images_dir, result.image_ids)
    folder = write_reference(out, result, record, names)
    return ReferenceSummary(out_dir=out, reference_dir=folder, record=record)
