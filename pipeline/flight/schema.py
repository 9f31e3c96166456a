"""``flight.yaml`` of a flight folder: the camera, navigation and flight config classes.

Loaded with the strict loader of :mod:`pipeline.common.strict_yaml`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.common.strict_yaml import build_dataclass, load_yaml
from pipeline.flight.navigation import BoresightConfig
from pipeline.tracking.options import TrackerOptions
from seqat.calibration import DEFAULT_FREE, SelfCalibration
from seqat.errors import ConfigError
from seqat.geometry import distort_normalized, inverse_distortion
from seqat.types import FloatArray, PinholeCamera

#: Number of components of a position or attitude sigma given as a list.
AXES = 3

SigmaTriple = float | tuple[float, float, float]

#: Plausible ranges of the numbers of ``flight.yaml`` (docs/formats.md): a finite value
#: outside them is a typo or a corrupt file, refused naming the key before it makes the
#: adjustment singular or its results absurd.
MAX_IMAGE_SIDE_PX = 100_000
MAX_FOCAL_PX = 1e6
MAX_DISTORTION = 100.0
#: The lens distortion is checked invertible over the image (:meth:`CameraConfig.fold`) along
#: this many directions from the principal point, in steps of this normalised radius, out to
#: this radius (tan 80°: no OPENCV lens sees wider).
FOLD_DIRECTIONS = 48
FOLD_STEP = 0.005
FOLD_MAX_RADIUS = 5.7
#: ... and every pixel of this many per image edge (corners included) checked to have a ray
#: on the principal point's side of any fold (:func:`seqat.geometry.inverse_distortion`):
#: with tangential terms the unfolded part can stop short of a corner.
FOLD_BORDER_SAMPLES = 256
MAX_SIGMA_IMAGE_PX = 1000.0
MAX_SIGMA_POSITION_M = 1e5
MAX_SIGMA_ATTITUDE_DEG = 180.0
#: Smallest sigmas: below them the weights (1 / sigma^2) overflow the adjustment's algebra
#: (sigma_image_px 1e-300 ended in a LinAlgError).
MIN_SIGMA_IMAGE_PX = 1e-3
MIN_SIGMA_POSITION_M = 1e-4
MIN_SIGMA_ATTITUDE_DEG = 1e-5
MAX_LEVER_ARM_M = 100.0
MAX_BORESIGHT_DEG = 360.0


def check_range(value: float, name: str, low: float, high: float, *,
                low_open: bool = False) -> None:
    """Refuse a value outside ``[low, high]`` (``(low, high]`` with ``low_open``)."""
    ok = (value > low if low_open else value >= low) and value <= high
    if not (math.isfinite(value) and ok):
        bracket = "(" if low_open else "["
        raise ConfigError(f"{name}: expected a number in {bracket}{low:g}, {high:g}], "
                          f"got {value!r}")


def _triple(value: SigmaTriple, name: str, high: float = math.inf,
            low: float = 0.0) -> tuple[float, float, float]:
    """Expand a scalar-or-3-list sigma and check every component is positive, finite and in
    ``[low, high]``."""
    trip = (value,) * AXES if isinstance(value, int | float) else tuple(value)
    if len(trip) != AXES or not all(math.isfinite(v) and v > 0 for v in trip):
        raise ConfigError(f"{name}: expected a positive number or a list of {AXES} positive "
                          f"numbers, got {value!r}")
    if any(v > high or v < low for v in trip):
        raise ConfigError(f"{name}: expected sigmas in [{low:g}, {high:g}], got {value!r}")
    return (float(trip[0]), float(trip[1]), float(trip[2]))


@dataclass(frozen=True, kw_only=True)
class CameraConfig:
    """``camera:`` section of ``flight.yaml`` (OpenCV pixel convention, docs/conventions.md).

    ``model: PINHOLE`` is an ideal camera with square pixels (``fx_px == fy_px``) and no
    distortion; ``model: OPENCV`` adds the OpenCV distortion ``k1 k2 p1 p2 k3``, which
    seqat's camera models (:mod:`pipeline.flight.camera`).
    """

    model: Literal["PINHOLE", "OPENCV"]
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name}: expected a positive integer, got {getattr(self, name)}")
            if getattr(self, name) > MAX_IMAGE_SIDE_PX:
                raise ConfigError(f"{name}: expected at most {MAX_IMAGE_SIDE_PX} px, got "
                                  f"{getattr(self, name)}")
        for name in ("fx_px", "fy_px"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: expected a positive number, got {getattr(self, name)}")
            check_range(getattr(self, name), name, 0.0, MAX_FOCAL_PX, low_open=True)
        # the principal point lies near the image (within 10 image sizes: crops, typos in
        # the size are left to the observation checks)
        check_range(self.cx_px, "cx_px", -10.0 * self.width_px, 11.0 * self.width_px)
        check_range(self.cy_px, "cy_px", -10.0 * self.height_px, 11.0 * self.height_px)
        for name in ("k1", "k2", "p1", "p2", "k3"):
            check_range(getattr(self, name), name, -MAX_DISTORTION, MAX_DISTORTION)
        if self.model == "PINHOLE":
            if self.fx_px != self.fy_px:
                raise ConfigError(
                    f"fy_px: a PINHOLE camera has square pixels, fx_px = fy_px, got "
                    f"{self.fx_px!r} and {self.fy_px!r} (use model: OPENCV)")
            if self.has_distortion:
                raise ConfigError("a PINHOLE camera has no distortion, got non-zero "
                                  "k1 k2 p1 p2 k3 (use model: OPENCV)")

    @property
    def distortion(self) -> FloatArray:
        """(5,) OpenCV distortion coefficients ``[k1, k2, p1, p2, k3]``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0.0))

    @property
    def model_camera(self) -> PinholeCamera:
        """seqat's camera of these pixels with their aspect made square: ``f_px = fx_px``,
        the distortion in the model (:func:`pipeline.flight.camera.seqat_camera`)."""
        return PinholeCamera(f_px=self.fx_px, cx_px=self.cx_px, cy_px=self.cy_px,
                             width_px=self.width_px, height_px=self.height_px, k1=self.k1,
                             k2=self.k2, p1=self.p1, p2=self.p2, k3=self.k3)

    def ideal_normalized(self, u_px: FloatArray, v_px: FloatArray
                         ) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """Ideal normalised coordinates of observed pixels ``(u, v)``: the distortion of
        :attr:`model_camera` inverted (:func:`seqat.geometry.inverse_distortion`), and
        whether each pixel has a ray (on the principal point's side of any fold)."""
        return inverse_distortion((np.asarray(u_px) - self.cx_px) / self.fx_px,
                                  (np.asarray(v_px) - self.cy_px) / self.fy_px,
                                  self.model_camera)

    def fold(self) -> str | None:
        """Why the distortion is no lens over this image, or None: going out from the
        principal point, the OpenCV polynomial must map the ideal image plane onto the image
        one to one (its Jacobian determinant > 0) until it reaches the image border. A
        polynomial that folds back first (k1 -0.9 where -0.09 was meant: the corners'
        pixels then have two rays, or none) leaves the adjustment singular; so does one
        whose unfolded part stops short of a border pixel (tangential terms can leave a
        corner without a ray). Not checked with the principal point outside the image."""
        w, h = self.width_px, self.height_px
        if not self.has_distortion or not (-0.5 <= self.cx_px <= w - 0.5
                                           and -0.5 <= self.cy_px <= h - 0.5):
            return None
        angle = np.linspace(0.0, 2.0 * np.pi, FOLD_DIRECTIONS, endpoint=False)[:, None]
        r = np.arange(1, int(FOLD_MAX_RADIUS / FOLD_STEP) + 1)[None, :] * FOLD_STEP
        xd, yd, D, _ = distort_normalized((r * np.cos(angle)).ravel(),
                                          (r * np.sin(angle)).ravel(), self.model_camera,
                                          jacobians=True)
        u = (self.fx_px * xd + self.cx_px).reshape(angle.size, -1)
        v = (self.fy_px * yd + self.cy_px).reshape(angle.size, -1)
        det = (D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]).reshape(angle.size, -1)
        inside = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
        # each direction up to its first sample outside the image (all of it if none)
        reach = np.where(inside.all(axis=1), r.size, np.argmin(inside, axis=1))
        before = np.arange(r.size)[None, :] <= np.minimum(reach, r.size - 1)[:, None]
        folded = before & ~(det > 0.0)
        coeffs = ", ".join(f"{n} {getattr(self, n):g}" for n in ("k1", "k2", "p1", "p2", "k3"))
        if folded.any():
            d, k = np.unravel_index(np.argmax(folded), folded.shape)
            return (f"the distortion ({coeffs}) folds back inside the {w} x {h} px image, "
                    f"{float(np.hypot(u[d, k] - self.cx_px, v[d, k] - self.cy_px)):.0f} px "
                    "from the principal point: no lens maps so (check the coefficients' "
                    "signs and that they are OpenCV's, on normalised coordinates)")
        if (reach == r.size).any():
            return (f"the distortion ({coeffs}) keeps rays 80 degrees off the axis inside the "
                    f"{w} x {h} px image: no OPENCV lens sees so wide (check the "
                    "coefficients' signs and that they are OpenCV's)")
        t = np.linspace(0.0, 1.0, FOLD_BORDER_SAMPLES)
        u = np.concatenate([t * (w - 1), t * (w - 1), np.zeros_like(t), np.full_like(t, w - 1)])
        v = np.concatenate([np.zeros_like(t), np.full_like(t, h - 1), t * (h - 1), t * (h - 1)])
        _, _, found = self.ideal_normalized(u, v)
        if not found.all():
            k = int(np.argmin(found))
            return (f"the distortion ({coeffs}) folds back before the border of the {w} x {h} "
                    f"px image: no ray reaches the pixel ({u[k]:.0f}, {v[k]:.0f}) (check the "
                    "coefficients' signs and that they are OpenCV's, on normalised "
                    "coordinates)")
        return None


#: Default a priori σ of GPS positions (x, y, z), metres: a consumer GNSS receiver.
DEFAULT_SIGMA_POSITION_M = (3.0, 3.0, 5.0)
#: Default a priori σ of INS attitudes (omega, phi, kappa), degrees: a low-grade autopilot
#: IMU whose "heading" may be the GPS course (on Seneca the adjusted kappa differs from it by
#: +12 deg on one heading and -20 deg on the reverse one: the wind's crab angle; roll and
#: pitch differ by 4-5 deg rms).
DEFAULT_SIGMA_ATTITUDE_DEG = (5.0, 5.0, 15.0)


@dataclass(frozen=True, kw_only=True)
class NavConfig:
    """``nav:`` section of ``flight.yaml``: where the GPS/INS comes from and its precision.

    ``source: file`` reads ``file`` (``frame: projected`` or ``geodetic``); ``source: images``
    reads each image's EXIF/XMP (docs/formats.md). ``height`` is the height kind of a
    geodetic ``nav.csv`` (``ellipsoidal`` WGS 84 or ``egm96`` orthometric). ``boresight`` and
    ``lever_arm_m`` (GPS antenna -> camera, body axes x forward, y right, z down, metres) apply
    to geodetic attitudes and positions only. ``dropout`` is what becomes of an image
    without a GNSS fix (empty or ``nan`` position fields, no ``nav.csv`` row, no GPS in its
    EXIF): ``bridge`` (default) sends it to the estimator without a position constraint,
    resected on the known ground points; ``skip`` leaves it out (docs/formats.md).
    """

    source: Literal["file", "images"] = "file"
    file: str = "nav.csv"
    frame: Literal["projected", "geodetic"] = "projected"
    height: Literal["ellipsoidal", "egm96"] = "ellipsoidal"
    sigma_position_m: SigmaTriple = DEFAULT_SIGMA_POSITION_M
    sigma_attitude_deg: SigmaTriple = DEFAULT_SIGMA_ATTITUDE_DEG
    boresight: BoresightConfig = BoresightConfig()
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dropout: Literal["bridge", "skip"] = "bridge"

    def __post_init__(self) -> None:
        _triple(self.sigma_position_m, "sigma_position_m", MAX_SIGMA_POSITION_M,
                MIN_SIGMA_POSITION_M)
        _triple(self.sigma_attitude_deg, "sigma_attitude_deg", MAX_SIGMA_ATTITUDE_DEG,
                MIN_SIGMA_ATTITUDE_DEG)
        for v in self.lever_arm_m:
            check_range(v, "lever_arm_m", -MAX_LEVER_ARM_M, MAX_LEVER_ARM_M)
        for name in ("roll_deg", "pitch_deg", "yaw_deg"):
            check_range(getattr(self.boresight, name), "boresight",
                        -MAX_BORESIGHT_DEG, MAX_BORESIGHT_DEG)

    @property
    def sigma_eop(self) -> FloatArray:
        """(6,) standard deviations of ``[X, Y, Z]`` (metres) and ``[omega, phi, kappa]`` (rad)."""
        pos = _triple(self.sigma_position_m, "sigma_position_m")
        att = _triple(self.sigma_attitude_deg, "sigma_attitude_deg")
        return np.concatenate([np.asarray(pos), np.radians(att)])


@dataclass(frozen=True, kw_only=True)
class SelfCalibrationConfig:
    """``self_calibration:`` section of ``flight.yaml`` (docs/formats.md, docs/algorithm.md).

    ``enabled``: ``null`` (default, "auto") self-calibrates a camera taken from EXIF (a
    nominal focal length, no distortion known) and keeps a ``flight.yaml`` camera fixed (it
    is a calibration); ``true`` / ``false`` force it. ``free`` lists the interior parameters
    estimated (``f_px cx_px cy_px k1 k2 p1 p2 k3``), ``sigma`` their prior standard
    deviations (pixels; normalised units for the distortion) where not the defaults.
    """

    enabled: bool | None = None
    free: tuple[str, ...] = DEFAULT_FREE
    sigma: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.calibration()  # checks the names and sigmas

    def calibration(self) -> SelfCalibration:
        return SelfCalibration(free=self.free, sigma=tuple(self.sigma.items()))

    def resolve(self, camera_from_exif: bool) -> SelfCalibration | None:
        """The self-calibration of a flight whose camera is (not) from EXIF; None: fixed."""
        on = camera_from_exif if self.enabled is None else self.enabled
        return self.calibration() if on and self.free else None


#: Default a priori σ of a ground control point's surveyed coordinates (RTK GNSS on a
#: target): horizontal (x, y) and vertical (z), metres.
DEFAULT_GCP_SIGMA_HORIZONTAL_M = 0.02
DEFAULT_GCP_SIGMA_VERTICAL_M = 0.03


@dataclass(frozen=True, kw_only=True)
class GcpConfig:
    """``gcp:`` section of ``flight.yaml``: ground control points (docs/formats.md, *Ground
    control*).

    ``file`` is an ODM ``gcp_list.txt`` or a Metashape markers export (``.xml``);
    ``reference`` optionally a Metashape reference CSV (label, X, Y, Z[, accuracy]) whose
    coordinates replace the XML's; ``crs`` the CRS of a file that names none (a Metashape
    export in a local frame, the reference CSV). The sigmas apply to points without an
    accuracy of their own.
    """

    file: str = "gcp_list.txt"
    reference: str | None = None
    crs: str | None = None
    sigma_horizontal_m: float = DEFAULT_GCP_SIGMA_HORIZONTAL_M
    sigma_vertical_m: float = DEFAULT_GCP_SIGMA_VERTICAL_M

    def __post_init__(self) -> None:
        for name in ("sigma_horizontal_m", "sigma_vertical_m"):
            check_range(getattr(self, name), name, MIN_SIGMA_POSITION_M, MAX_SIGMA_POSITION_M)


@dataclass(frozen=True, kw_only=True)
class FlightConfig:
    """``flight.yaml`` of a flight folder (docs/formats.md).

    File names are relative to the flight folder (absolute paths are allowed).
    """

    crs: str = "auto"
    camera: CameraConfig | None = None
    nav: NavConfig = NavConfig()
    sigma_image_px: float = 1.0
    observations: str | None = None
    images: str | None = None
    checkpoints: str | None = None
    gcp: GcpConfig | None = None
    lidar: str | tuple[str, ...] | None = None
    tracking: TrackerOptions = TrackerOptions()
    self_calibration: SelfCalibrationConfig = SelfCalibrationConfig()

    def __post_init__(self) -> None:
        if not self.sigma_image_px > 0:
            raise ConfigError(f"sigma_image_px: expected a positive number, "
                              f"got {self.sigma_image_px!r}")
        check_range(self.sigma_image_px, "sigma_image_px", MIN_SIGMA_IMAGE_PX,
                    MAX_SIGMA_IMAGE_PX)
        if not self.crs.strip():
            raise ConfigError("crs: expected a CRS such as 'EPSG:32652', got an empty string")
        fold = self.camera.fold() if self.camera is not None else None
        if fold is not None:
            raise ConfigError(f"camera: {fold}")


def load_flight_config(path: Path | str) -> FlightConfig:
    """Read and validate a ``flight.yaml`` (structure and types; CRS:
    :mod:`pipeline.flight.folder`)."""
    return build_dataclass(FlightConfig, load_yaml(path), str(path))


