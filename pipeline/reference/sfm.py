"""COLMAP's own structure from motion on a flight's images (pycolmap), for the independent check.

The algorithm of ``seqat reference OUT --sfm`` (:mod:`pipeline.reference.sfm_stage`). Nothing
of the run's tie points or estimates goes in: COLMAP detects its own SIFT features, matches
them, registers the images incrementally and self-calibrates its camera. Only the nav
positions are used, to choose which image pairs to match (spatial matching), and the run's
camera as the *starting value* of the self-calibration (COLMAP's EXIF focal length guess is
not scaled to the image's resolution: 2775 px for the 1000 px wide Seneca sample, whose focal
length is 694 px).

* **Images** of another size than the camera's (same aspect ratio) are resampled to it
  (``cv2.INTER_AREA``, as the run reads them: flight/folder.py ``check_image_size``) into the
  work folder, so one camera, in the run's pixel frame, fits every image; the others are
  linked there unchanged.
* **Features**: SIFT (``pycolmap.extract_features``, first octave 0 by default, not COLMAP's
  upsampling -1: a quarter of the CPU time on 2 shared cores) on a copy at most
  ``max_image_size_px`` wide (keypoints are returned at full resolution), one ``OPENCV``
  camera shared by every image (``CameraMode.SINGLE``). Extracted in batches so the stage can
  show progress.
* **Pairs**: spatial (``pycolmap.match_spatial``) on the nav positions, written to the
  database as Cartesian pose priors in local coordinates of the working CRS (the EXIF GPS the
  extractor reads is WGS 84 and absent for a ``nav.csv`` flight). Neighbours within
  ``spatial_max_distance_m`` (default: the image footprint's diagonal at the median height
  above the ground), at most ``spatial_neighbours``. ``sequential`` and ``exhaustive`` are
  there for flights without positions or with bad ones.
* **Mapping**: ``pycolmap.incremental_mapping`` with two thresholds lowered for weakly
  textured ground (15 pose inliers, two-view tracks triangulated); focal length and
  distortion (k1, k2, p1, p2) refined in its bundle adjustments, the principal point too
  with ``refine_principal_point``. The largest model is kept.

CPU only; every thread count is ``num_threads``. Seeds are fixed, but COLMAP's multi-threaded
parts may still make runs differ slightly (not measured).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.flight.schema import CameraConfig
from pipeline.reference.colmap_ba import COLMAP_PIXEL_OFFSET, camera_config_from_colmap
from seqat.errors import ConfigError, EstimationError
from seqat.types import FloatArray

if TYPE_CHECKING:
    import pycolmap

#: Images per feature-extraction call (progress granularity).
EXTRACT_BATCH = 4
#: Database and mapper output inside the work folder.
DATABASE_FILE = "database.db"
SPARSE_DIR = "sparse"
IMAGES_DIR = "images"
#: JPEG quality of an image resampled to the camera's size.
RESAMPLED_JPEG_QUALITY = 95

#: ``progress(stage, done, total)``; stage is ``features``, ``matching`` or ``mapping``.
Progress = Callable[[str, int, int], None]


class Matching(enum.StrEnum):
    """How image pairs are chosen for matching."""

    SPATIAL = "spatial"  # nav positions: neighbours within a distance
    SEQUENTIAL = "sequential"  # acquisition order: the next `sequential_overlap` images
    EXHAUSTIVE = "exhaustive"  # every pair (small flights only)


@dataclass(frozen=True, kw_only=True)
class SfmOptions:
    """Options of the independent SfM.

    Attributes
    ----------
    max_image_size_px : int
        SIFT runs on a copy whose larger side is at most this (COLMAP's default 3200).
    max_num_features : int
        SIFT features per image (COLMAP's default 8192).
    sift_first_octave : int
        0: SIFT on the (downscaled) image as it is; COLMAP's default -1 doubles it first
        (more, finer features for ~4x the CPU time: ~7 s per 1600 px image on one core).
    matching : Matching
    spatial_neighbours : int
        Spatial matching: at most this many neighbours per image.
    spatial_max_distance_m : float or None
        Spatial matching: neighbours within this distance; None: the footprint's diagonal.
    sequential_overlap : int
        Sequential matching: images matched after each image.
    min_pose_inliers : int
        Inliers an image needs to be registered (``abs_pose_min_num_inliers``; COLMAP's
        default is 30).
    two_view_tracks : bool
        Also triangulate points seen in two images only (COLMAP's default ignores them while
        mapping). With 15 and this, 67 of the 70 Seneca images register instead of 56 (the
        others are over weakly textured fields), with the same agreement
        (docs/benchmarks.md).
    refine_principal_point : bool
        Also self-calibrate cx, cy (COLMAP's default: off; a nadir block hardly fixes them).
    min_registered_fraction : float
        Fewer images registered than this fraction of the flight's (and than 5) is an error.
    num_threads : int
    seed : int
        COLMAP's random seeds (RANSAC, mapper).
    """

    max_image_size_px: int = 1600
    max_num_features: int = 8192
    sift_first_octave: int = 0
    sift_peak_threshold: float = 0.02 / 3
    matching: Matching = Matching.SPATIAL
    spatial_neighbours: int = 20
    spatial_max_distance_m: float | None = None
    sequential_overlap: int = 10
    min_pose_inliers: int = 15
    two_view_tracks: bool = True
    refine_principal_point: bool = False
    min_registered_fraction: float = 0.5
    num_threads: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("max_image_size_px", "max_num_features", "spatial_neighbours",
                     "sequential_overlap", "num_threads"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.spatial_max_distance_m is not None and not self.spatial_max_distance_m > 0:
            raise ConfigError("spatial_max_distance_m: expected > 0, got "
                              f"{self.spatial_max_distance_m}")
        if not 0.0 < self.min_registered_fraction <= 1.0:
            raise ConfigError("min_registered_fraction: expected in (0, 1], got "
                              f"{self.min_registered_fraction}")


@dataclass(frozen=True, kw_only=True, eq=False)
class SfmInput:
    """The images and what is used besides their pixels.

    Attributes
    ----------
    image_dir : Path
    image_ids : tuple[str, ...]
        Our ids, acquisition order.
    file_names : tuple[str, ...]
        File of each image inside ``image_dir``.
    positions : (n, 3) float
        Nav positions (working CRS, metres; NaN rows: no position), for spatial matching.
    camera : CameraConfig
        Starting value of the self-calibration.
    ground_z_m : float
        Median ground height (for the footprint; NaN: unknown).
    """

    image_dir: Path
    image_ids: tuple[str, ...]
    file_names: tuple[str, ...]
    positions: FloatArray
    camera: CameraConfig
    ground_z_m: float


@dataclass(frozen=True, kw_only=True, eq=False)
class SfmModel:
    """The largest model of the SfM.

    Attributes
    ----------
    image_ids : tuple[str, ...]
        Registered images, acquisition order.
    centres : (r, 3) float
        Projection centres in the model's own (arbitrary) frame.
    R_cam_from_world : (r, 3, 3) float
        COLMAP ``cam_from_world`` rotations.
    camera : CameraConfig
        The self-calibrated camera (our pixel convention).
    n_images : int
        Images given.
    n_models : int
        Models the mapper made (1 when every registered image is connected).
    n_points, n_observations : int
    mean_reprojection_px, mean_track_length : float
    n_matched_pairs : int
        Image pairs with geometrically verified matches.
    spatial_max_distance_m : float or None
        The distance used (spatial matching).
    seconds : dict[str, float]
        Wall time of features, matching and mapping.
    reconstruction : pycolmap.Reconstruction
    """

    image_ids: tuple[str, ...]
    centres: FloatArray
    R_cam_from_world: FloatArray
    camera: CameraConfig
    n_images: int
    n_models: int
    n_points: int
    n_observations: int
    mean_reprojection_px: float
    mean_track_length: float
    n_matched_pairs: int
    spatial_max_distance_m: float | None
    seconds: dict[str, float]
    reconstruction: pycolmap.Reconstruction


def footprint_diagonal_m(data: SfmInput) -> float:
    """The image footprint's diagonal at the median height above the ground (nadir view)."""
    z = data.positions[:, 2]
    z = z[np.isfinite(z)]
    height = float(np.median(z)) - data.ground_z_m if z.size else math.nan
    if not (math.isfinite(height) and height > 0):
        raise EstimationError("spatial matching needs the height above the ground (no ground "
                              "points or nav heights in the run); use --matching sequential")
    cam = data.camera
    return height * math.hypot(cam.width_px, cam.height_px) / cam.fx_px


def _no_progress(stage: str, done: int, total: int) -> None:
    del stage, done, total


def prepare_images(data: SfmInput, work: Path) -> Path:
    """``work/images/``: every image at the camera's size (linked, or resampled if needed)."""
    import cv2
    from PIL import Image

    folder = work / IMAGES_DIR
    folder.mkdir()
    size = (data.camera.width_px, data.camera.height_px)
    for name in data.file_names:
        src = data.image_dir / name
        with Image.open(src) as im:
            this = im.size
        if this == size:
            (folder / name).symlink_to(src.resolve())
            continue
        image = cv2.imread(str(src), cv2.IMREAD_COLOR)
        if image is None:
            raise EstimationError(f"{src}: cannot decode")
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if not cv2.imwrite(str(folder / name), image,
                           [cv2.IMWRITE_JPEG_QUALITY, RESAMPLED_JPEG_QUALITY]):
            raise EstimationError(f"{folder / name}: cannot write the resampled image")
    return folder


def _extract(pycolmap: object, db: Path, data: SfmInput, options: SfmOptions,
             progress: Progress) -> None:
    cam = data.camera
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV"
    reader.camera_params = ",".join(repr(float(v)) for v in (
        cam.fx_px, cam.fy_px, cam.cx_px + COLMAP_PIXEL_OFFSET, cam.cy_px + COLMAP_PIXEL_OFFSET,
        0.0, 0.0, 0.0, 0.0))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = options.max_image_size_px
    extraction.num_threads = options.num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = options.max_num_features
    extraction.sift.first_octave = options.sift_first_octave
    extraction.sift.peak_threshold = options.sift_peak_threshold
    names = list(data.file_names)
    progress("features", 0, len(names))
    for start in range(0, len(names), EXTRACT_BATCH):
        batch = names[start:start + EXTRACT_BATCH]
        pycolmap.extract_features(db, data.image_dir, image_names=batch,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        reader.existing_camera_id = 1  # the batches after the first share its camera
        progress("features", min(start + EXTRACT_BATCH, len(names)), len(names))


def _write_pose_priors(pycolmap: object, db: Path, data: SfmInput) -> None:
    """The nav positions as Cartesian priors (local coordinates), replacing the EXIF ones."""
    by_name = dict(zip(data.file_names, data.positions, strict=True))
    finite = data.positions[np.all(np.isfinite(data.positions), axis=1)]
    origin = np.round(finite[0]) if finite.size else np.zeros(3)
    database = pycolmap.Database.open(str(db))
    try:
        database.clear_pose_priors()
        for image in database.read_all_images():
            position = by_name[image.name]
            if not np.all(np.isfinite(position)):
                continue
            prior = pycolmap.PosePrior(
                position=position - origin,
                coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
                corr_data_id=image.data_id)
            database.write_pose_prior(prior)
    finally:
        database.close()


def _match(pycolmap: object, db: Path, data: SfmInput, options: SfmOptions,
           progress: Progress) -> float | None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    common = {"matching_options": matching, "verification_options": verification,
              "device": pycolmap.Device.cpu}
    progress("matching", 0, 1)
    distance: float | None = None
    if options.matching is Matching.SPATIAL:
        distance = (options.spatial_max_distance_m if options.spatial_max_distance_m is not None
                    else footprint_diagonal_m(data))
        _write_pose_priors(pycolmap, db, data)
        pairing = pycolmap.SpatialPairingOptions()
        pairing.ignore_z = False
        pairing.max_distance = distance
        pairing.max_num_neighbors = options.spatial_neighbours
        pairing.num_threads = options.num_threads
        pycolmap.match_spatial(db, pairing_options=pairing, **common)
    elif options.matching is Matching.SEQUENTIAL:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_overlap
        pairing.quadratic_overlap = False
        pairing.num_threads = options.num_threads
        pycolmap.match_sequential(db, pairing_options=pairing, **common)
    else:
        pycolmap.match_exhaustive(db, **common)
    progress("matching", 1, 1)
    return distance


def _n_verified_pairs(pycolmap: object, db: Path) -> int:
    database = pycolmap.Database.open(str(db))
    try:
        return int(database.num_verified_image_pairs())
    finally:
        database.close()


def _map(pycolmap: object, db: Path, data: SfmInput, work: Path, options: SfmOptions,
         progress: Progress) -> dict[int, pycolmap.Reconstruction]:
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = options.num_threads
    pipeline.random_seed = options.seed
    pipeline.ba_refine_focal_length = True
    pipeline.ba_refine_extra_params = True
    pipeline.ba_refine_principal_point = options.refine_principal_point
    pipeline.extract_colors = False
    pipeline.mapper.abs_pose_min_num_inliers = options.min_pose_inliers
    pipeline.triangulation.ignore_two_view_tracks = not options.two_view_tracks
    n = len(data.file_names)
    registered = [0]

    def next_image() -> None:
        registered[0] += 1
        progress("mapping", min(registered[0], n), n)

    def initial_pair() -> None:
        registered[0] = 2
        progress("mapping", min(registered[0], n), n)

    progress("mapping", 0, n)
    out = work / SPARSE_DIR
    out.mkdir()
    models = pycolmap.incremental_mapping(db, data.image_dir, out, pipeline,
                                          initial_image_pair_callback=initial_pair,
                                          next_image_callback=next_image)
    progress("mapping", max((r.num_reg_images() for r in models.values()), default=0), n)
    return models


def run_sfm(data: SfmInput, work: Path, options: SfmOptions | None = None,
            progress: Progress | None = None) -> SfmModel:
    """Structure from motion of ``data``'s images; scratch files go to ``work`` (a folder).

    Raises
    ------
    EstimationError
        No model, or fewer images registered than ``min_registered_fraction`` (and 5).
    """
    import pycolmap

    options = options if options is not None else SfmOptions()
    report = progress if progress is not None else _no_progress
    db = work / DATABASE_FILE
    image_dir = data.image_dir
    seconds: dict[str, float] = {}
    with quiet_colmap(pycolmap):
        t0 = time.perf_counter()
        data = dataclasses.replace(data, image_dir=prepare_images(data, work))
        _extract(pycolmap, db, data, options, report)
        t1 = time.perf_counter()
        distance = _match(pycolmap, db, data, options, report)
        n_pairs = _n_verified_pairs(pycolmap, db)
        t2 = time.perf_counter()
        models = _map(pycolmap, db, data, work, options, report)
        t3 = time.perf_counter()
    seconds.update(features=t1 - t0, matching=t2 - t1, mapping=t3 - t2)
    n = len(data.image_ids)
    needed = max(5, math.ceil(options.min_registered_fraction * n))
    if not models:
        raise EstimationError(f"SfM of {image_dir}: no model ({n_pairs} image pairs "
                              f"matched of {n} images)")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    if rec.num_reg_images() < needed:
        raise EstimationError(
            f"SfM of {image_dir}: registered {rec.num_reg_images()} of {n} images "
            f"(needs >= {needed}; {len(models)} models, {n_pairs} image pairs matched)")
    return model_from_reconstruction(rec, data, n_models=len(models), n_pairs=n_pairs,
                                     distance=distance, seconds=seconds)


@contextmanager
def quiet_colmap(pycolmap: object) -> Iterator[None]:
    """COLMAP's log off while it works, errors included: its normal course logs warnings
    ("Discarding reconstruction due to insufficient size") and an error when no model forms,
    which :func:`run_sfm` reports itself, in one line. ``SEQAT_DEBUG=1`` keeps the log."""
    logging = pycolmap.logging
    previous = logging.minloglevel
    if os.environ.get("SEQAT_DEBUG", "") in ("", "0"):
        logging.minloglevel = int(logging.FATAL)
    try:
        yield
    finally:
        logging.minloglevel = previous


def model_from_reconstruction(rec: pycolmap.Reconstruction, data: SfmInput, *, n_models: int,
                              n_pairs: int, distance: float | None,
                              seconds: dict[str, float]) -> SfmModel:
    """The :class:`SfmModel` of a reconstruction of ``data``'s images (images by file name).

    Raises
    ------
    EstimationError
        Not one camera, or an image that is not one of ``data``'s.
    """
    id_of_file = dict(zip(data.file_names, data.image_ids, strict=True))
    order = {iid: i for i, iid in enumerate(data.image_ids)}
    poses: dict[str, tuple[FloatArray, FloatArray]] = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        if image.name not in id_of_file:
            raise EstimationError(f"SfM model: image {image.name!r} is not one of the run's")
        pose = image.cam_from_world()
        poses[id_of_file[image.name]] = (
            np.asarray(pose.rotation.matrix(), dtype=np.float64),
            np.asarray(image.projection_center(), dtype=np.float64))
    ids = tuple(sorted(poses, key=order.__getitem__))
    cams = list(rec.cameras.values())
    if len(cams) != 1:
        raise EstimationError(f"SfM: expected one shared camera, the model has {len(cams)}")
    return SfmModel(
        image_ids=ids, centres=np.array([poses[i][1] for i in ids]).reshape(-1, 3),
        R_cam_from_world=np.array([poses[i][0] for i in ids]).reshape(-1, 3, 3),
        camera=camera_config_from_colmap(cams[0], data.camera), n_images=len(data.image_ids),
        n_models=n_models, n_points=int(rec.num_points3D()),
        n_observations=int(rec.compute_num_observations()),
        mean_reprojection_px=float(rec.compute_mean_reprojection_error()),
        mean_track_length=float(rec.compute_mean_track_length()), n_matched_pairs=n_pairs,
        spatial_max_distance_m=distance, seconds=seconds, reconstruction=rec)

