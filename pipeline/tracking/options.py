"""``tracking:`` section of ``flight.yaml``: the options of the streaming tracker."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from seqat.errors import ConfigError

#: Smallest working width accepted (SIFT needs some octaves), pixels.
MIN_WORKING_WIDTH_PX = 64
#: Fewest point correspondences of the geometric model (8-point fundamental matrix).
MIN_MODEL_POINTS = 8


@dataclass(frozen=True, kw_only=True)
class TrackerOptions:
    """``tracking:`` section of ``flight.yaml`` (all keys optional).

    Attributes
    ----------
    detector : {"sift", "orb"}
    working_width_px : int
        Images are downscaled to this width for detection (never upscaled).
    max_features : int
        Features detected per image (SIFT/ORB ``nfeatures``).
    neighbours : int
        At most this many earlier images are matched with each new image.
    min_overlap : float
        Predicted footprint overlap, as a fraction of the new image's footprint, for a held
        image to be a candidate, in ``[0, 1)``.
    ratio : float
        Lowe's ratio test, in ``(0, 1]``.
    ransac_threshold_px : float
        USAC_MAGSAC threshold at working resolution (pixels).
    min_inliers : int
        Pairs with fewer verified matches are rejected (>= 8).
    geometry : {"fundamental", "homography"}
        Model of the verification. The fundamental matrix accepts any rigid scene (buildings,
        trees); a homography only a plane, but constrains matches in 2D instead of 1D.
    matcher : {"auto", "brute_force", "flann"}
        Descriptor matcher for SIFT (ORB always uses brute-force Hamming): ``brute_force``
        finds the exact nearest neighbours (one BLAS product per pair of images,
        :mod:`pipeline.tracking.matching`), ``flann`` approximate ones (kd-trees, cheaper at
        ~4000 features per image), ``auto`` the first up to 2500 x 2500 descriptors per pair
        and FLANN above.
    sift_contrast_threshold : float
        SIFT ``contrastThreshold``. OpenCV's default 0.04 finds only 5-20 features on the
        low-contrast fields of the Seneca flight (gray std ~13); 0.01 finds 4000 there (the
        ``max_features`` strongest are kept, so textured images are unaffected).
    max_held_images : int
        At most this many images are held for matching (>= ``neighbours``).
    stale_after_images : int
        A held image is dropped once its footprint has not overlapped any of this many
        consecutive new images.
    default_height_above_ground_m : float
        Ground plane for the footprints before a ground height is known:
        ``Z_camera - default_height_above_ground_m``.
    opencv_threads : int
        ``cv2.setNumThreads`` applied by the tracker (process-wide); 0 leaves OpenCV's setting.
    max_relief_fraction : float or None
        Plane gate after the fundamental matrix: terrain relief tolerated off the pair's
        dominant plane, as a fraction of the height above ground (:meth:`Tracker._plane_gate`);
        ``None`` switches the gate off (steep terrain, oblique views).
    emit_per_image : int or None
        At most this many features of an image become observations (and can start or continue
        tracks): every continuation of an emitted track, then new features spread over
        ``emit_grid`` cells (strongest first, round robin over the cells). The estimator's
        cost grows with the tie points in its window, so the default keeps tens of points
        per image, as aerial triangulation does; ``None`` emits every feature.
    emit_grid : (int, int)
        Columns and rows of the grid new features are spread over.
    late_per_pair : int
        Late observations (docs/algorithm.md, *Late observations*): when a verified match
        links a feature of the new image to a feature a held image did not emit, the held
        image's feature is emitted now, as a late observation of that image: per pair as many
        as top its ties (verified matches through emitted features) up to this number
        (smallest descriptor distance first; a pair tied this well gets none); 0: never.
    late_untied_per_pair : int
        The cap instead when the pair has no tie through emitted features, or the held
        image has no tie with any image yet (the new image, or the held one, would otherwise
        have no tie point): >= ``late_per_pair``.
    resection_threshold_deg : float
        RANSAC threshold (angle between an image ray and the direction from the GPS position
        to its point) of the resection that gives each new image its initial attitude
        (:mod:`pipeline.run.resection`).
    """

    detector: Literal["sift", "orb"] = "sift"
    working_width_px: int = 1000
    max_features: int = 4000
    neighbours: int = 5
    min_overlap: float = 0.15
    ratio: float = 0.8
    ransac_threshold_px: float = 1.0
    min_inliers: int = 15
    geometry: Literal["fundamental", "homography"] = "fundamental"
    matcher: Literal["auto", "brute_force", "flann"] = "auto"
    sift_contrast_threshold: float = 0.01
    max_held_images: int = 60
    stale_after_images: int = 40
    default_height_above_ground_m: float = 100.0
    opencv_threads: int = 2
    max_relief_fraction: float | None = 0.15
    emit_per_image: int | None = 200
    resection_threshold_deg: float = 3.0
    emit_grid: tuple[int, int] = (8, 6)
    late_per_pair: int = 20
    late_untied_per_pair: int = 50

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, expected: str) -> None:
            if not ok:
                raise ConfigError(f"{name}: expected {expected}, got {getattr(self, name)!r}")

        need(self.detector in ("sift", "orb"), "detector", "'sift' or 'orb'")
        need(self.working_width_px >= MIN_WORKING_WIDTH_PX, "working_width_px",
             f"an integer >= {MIN_WORKING_WIDTH_PX}")
        need(self.max_features >= MIN_MODEL_POINTS, "max_features",
             f"an integer >= {MIN_MODEL_POINTS}")
        need(self.neighbours >= 1, "neighbours", "an integer >= 1")
        need(0.0 <= self.min_overlap < 1.0, "min_overlap", "a number in [0, 1)")
        need(0.0 < self.ratio <= 1.0, "ratio", "a number in (0, 1]")
        need(self.ransac_threshold_px > 0.0, "ransac_threshold_px", "a positive number")
        need(self.min_inliers >= MIN_MODEL_POINTS, "min_inliers",
             f"an integer >= {MIN_MODEL_POINTS}")
        need(self.geometry in ("fundamental", "homography"), "geometry",
             "'fundamental' or 'homography'")
        need(self.matcher in ("auto", "brute_force", "flann"), "matcher",
             "'auto', 'brute_force' or 'flann'")
        need(self.sift_contrast_threshold > 0.0, "sift_contrast_threshold", "a positive number")
        need(self.max_held_images >= self.neighbours, "max_held_images",
             f"an integer >= neighbours ({self.neighbours})")
        need(self.stale_after_images >= 1, "stale_after_images", "an integer >= 1")
        need(self.default_height_above_ground_m > 0.0, "default_height_above_ground_m",
             "a positive number")
        need(self.opencv_threads >= 0, "opencv_threads", "an integer >= 0")
        need(0.0 < self.resection_threshold_deg < 90.0, "resection_threshold_deg",
             "a number in (0, 90)")
        need(self.emit_per_image is None or self.emit_per_image >= 1, "emit_per_image",
             "a positive integer or null")
        need(len(self.emit_grid) == 2 and min(self.emit_grid) >= 1, "emit_grid",
             "two positive integers [columns, rows]")
        need(self.late_per_pair >= 0, "late_per_pair", "an integer >= 0")
        need(self.late_untied_per_pair >= self.late_per_pair, "late_untied_per_pair",
             f"an integer >= late_per_pair ({self.late_per_pair})")
        need(self.max_relief_fraction is None or self.max_relief_fraction > 0.0,
             "max_relief_fraction", "a positive number or null")

