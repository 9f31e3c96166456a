"""Value objects shared by the estimators: camera, frame (one image's input), solutions.

Conventions (docs/conventions.md): world frame east-north-up in metres; EOP vector
``[X0_m, Y0_m, Z0_m, omega_rad, phi_rad, kappa_rad]`` with the camera->world rotation
``R = Rx(omega) Ry(phi) Rz(kappa)``; image points in OpenCV pixels (u right, v down, origin
at the centre of the top-left pixel) of a central-projection camera with square pixels and,
optionally, OpenCV (Brown) lens distortion (:class:`PinholeCamera`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from seqat.errors import InputDataError

FloatArray = NDArray[np.float64]

#: Number of exterior orientation parameters per image.
EOP_SIZE = 6
#: Number of coordinates per ground point.
GP_SIZE = 3
#: The camera's interior parameters, in the order of :attr:`PinholeCamera.intrinsics`
#: (COLMAP's OPENCV model with ``fx = fy = f``; docs/conventions.md, *Camera*).
INTRINSICS = ("f_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True, kw_only=True)
class PinholeCamera:
    """Central-projection camera in pixels: square pixels, OpenCV lens distortion.

    With every distortion coefficient 0 (the default) it is the ideal pinhole camera. With
    coefficients (a flight's lens, fixed or self-calibrated: its image points reach seqat as
    observed) it is COLMAP's ``OPENCV`` model with ``fx = fy = f_px``: normalised camera
    coordinates ``(xn, yn)`` (OpenCV frame), ``r2 = xn^2 + yn^2``,
    ``xd = xn (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 xn yn + p2 (r2 + 2 xn^2)``,
    ``yd = yn (1 + ...) + p1 (r2 + 2 yn^2) + 2 p2 xn yn``, ``u = cx + f xd``, ``v = cy + f yd``.
    """

    f_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @property
    def intrinsics(self) -> FloatArray:
        """(8,) ``[f_px, cx_px, cy_px, k1, k2, p1, p2, k3]`` (:data:`INTRINSICS`)."""
        return np.array([float(getattr(self, n)) for n in INTRINSICS])

    @property
    def has_distortion(self) -> bool:
        # written out: every projection asks (a generator of getattr cost more than the check)
        return (self.k1 != 0.0 or self.k2 != 0.0 or self.p1 != 0.0 or self.p2 != 0.0
                or self.k3 != 0.0)

    def with_intrinsics(self, values: FloatArray) -> PinholeCamera:
        """The same camera with the :data:`INTRINSICS` ``values`` (8,)."""
        v = np.asarray(values, dtype=np.float64).reshape(len(INTRINSICS))
        return dataclasses.replace(self, **{n: float(x) for n, x in zip(INTRINSICS, v,
                                                                        strict=True)})

    def __post_init__(self) -> None:
        if not (np.isfinite(self.f_px) and self.f_px > 0):
            raise InputDataError(f"camera f_px must be a positive number, got {self.f_px!r}")
        if self.width_px <= 0 or self.height_px <= 0:
            raise InputDataError(
                f"camera size must be positive, got {self.width_px} x {self.height_px} px"
            )
        for name in ("cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3"):
            if not np.isfinite(getattr(self, name)):
                raise InputDataError(f"camera {name} must be finite, got {getattr(self, name)!r}")


@dataclass(frozen=True, kw_only=True, eq=False)
class Frame:
    """Everything the estimator receives for one image, in acquisition order.

    Attributes
    ----------
    image_id : str
    nav_eop : (6,) float
        GPS/INS exterior orientation in the world frame, ``[X, Y, Z]`` metres and
        ``[omega, phi, kappa]`` radians.
    nav_sigma : (6,) float
        Standard deviation of each ``nav_eop`` component (metres, radians), all > 0; ``inf``
        leaves that component unconstrained (a GNSS dropout: ``nav_eop`` is then only the
        starting value, the image is resected on the window's GPs).
    point_ids : tuple[str, ...]
        Ground point (track) id of each observation, unique within the frame.
    uv_px : (k, 2) float
        Observed pixel coordinates of the ``k`` observations (ideal pinhole pixels).
    sigma_px : float
        Standard deviation of an image coordinate, pixels.
    initial_eop : (6,) float or None
        Initial value of the image's EOP for the estimator's linearisation (e.g. a space
        resection on known ground points), world frame; not an observation. ``None``: the
        nav is the initial value.
    late_image_ids, late_point_ids : tuple[str, ...]
        *Late observations* arriving with this frame: observations of *earlier* images
        (ids of images the estimator already has) that the tracker emitted only now, when
        this image matched a feature those images held without emitting it
        (docs/algorithm.md, *Late observations*). One entry per observation; an
        (image, point) pair appears once, never for this frame's own image.
    late_uv_px : (m, 2) float
        Their ideal pinhole pixels in the earlier image, with ``sigma_px``.
    """

    image_id: str
    nav_eop: FloatArray
    nav_sigma: FloatArray
    point_ids: tuple[str, ...]
    uv_px: FloatArray
    sigma_px: float = 1.0
    initial_eop: FloatArray | None = None
    late_image_ids: tuple[str, ...] = ()
    late_point_ids: tuple[str, ...] = ()
    late_uv_px: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def n_late(self) -> int:
        """Number of late observations of earlier images this frame carries."""
        return len(self.late_point_ids)

    def _check_late(self, where: str) -> FloatArray:
        late_uv = np.asarray(self.late_uv_px, dtype=np.float64).reshape(-1, 2)
        n = len(self.late_point_ids)
        if len(self.late_image_ids) != n or late_uv.shape[0] != n:
            raise InputDataError(
                f"{where}: {len(self.late_image_ids)} late image ids, {n} late point ids and "
                f"{late_uv.shape[0]} late image points: expected one of each per late "
                "observation")
        if not np.all(np.isfinite(late_uv)):
            raise InputDataError(f"{where}: late image coordinates must be finite")
        if self.image_id in self.late_image_ids:
            raise InputDataError(f"{where}: a late observation names the frame's own image "
                                 "(late observations are of earlier images)")
        pairs = set(zip(self.late_image_ids, self.late_point_ids, strict=True))
        if len(pairs) != n:
            raise InputDataError(f"{where}: a late observation (image, point) appears twice")
        return late_uv

    def __post_init__(self) -> None:
        nav = np.asarray(self.nav_eop, dtype=np.float64).reshape(-1)
        sig = np.asarray(self.nav_sigma, dtype=np.float64).reshape(-1)
        uv = np.asarray(self.uv_px, dtype=np.float64).reshape(-1, 2)
        where = f"image {self.image_id!r}"
        if nav.shape != (EOP_SIZE,) or not np.all(np.isfinite(nav)):
            raise InputDataError(f"{where}: nav_eop must be 6 finite numbers, got {nav!r}")
        if sig.shape != (EOP_SIZE,) or np.any(np.isnan(sig)) or np.any(sig <= 0):
            raise InputDataError(f"{where}: nav_sigma must be 6 positive numbers (inf: no "
                                 f"constraint), got {sig!r}")
        if uv.shape[0] != len(self.point_ids):
            raise InputDataError(
                f"{where}: {len(self.point_ids)} point ids but {uv.shape[0]} image points"
            )
        if not np.all(np.isfinite(uv)):
            raise InputDataError(f"{where}: image coordinates must be finite")
        if len(set(self.point_ids)) != len(self.point_ids):
            raise InputDataError(f"{where}: a point id appears twice in one image")
        if not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise InputDataError(f"{where}: sigma_px must be positive, got {self.sigma_px!r}")
        if self.initial_eop is not None:
            init = np.asarray(self.initial_eop, dtype=np.float64).reshape(-1)
            if init.shape != (EOP_SIZE,) or not np.all(np.isfinite(init)):
                raise InputDataError(f"{where}: initial_eop must be 6 finite numbers, "
                                     f"got {init!r}")
            object.__setattr__(self, "initial_eop", init)
        late_uv = self._check_late(where)
        object.__setattr__(self, "late_uv_px", late_uv)
        object.__setattr__(self, "late_image_ids", tuple(self.late_image_ids))
        object.__setattr__(self, "late_point_ids", tuple(self.late_point_ids))
        object.__setattr__(self, "nav_eop", nav)
        object.__setattr__(self, "nav_sigma", sig)
        object.__setattr__(self, "uv_px", uv)
        object.__setattr__(self, "point_ids", tuple(self.point_ids))


@dataclass(frozen=True, kw_only=True, eq=False)
class ControlPoint:
    """A ground control point: a ground point whose coordinates were surveyed.

    Its image observations arrive in the frames like a tie point's (``Frame.point_ids``,
    under ``point_id``); the estimators adjust it with ``xyz_m`` as a weighted observation of
    its coordinates (docs/algorithm.md, *Ground control*). One ray is enough for it to be
    adjusted.

    Attributes
    ----------
    point_id : str
    xyz_m : (3,) float
        Surveyed coordinates in the world frame of the run (the frame of ``Frame.nav_eop``).
    sigma_m : (3,) float
        Standard deviation of each coordinate, > 0; ``inf`` leaves that coordinate free (a
        planimetric or a height-only control point).
    """

    point_id: str
    xyz_m: FloatArray
    sigma_m: FloatArray

    def __post_init__(self) -> None:
        xyz = np.asarray(self.xyz_m, dtype=np.float64).reshape(-1)
        sig = np.asarray(self.sigma_m, dtype=np.float64).reshape(-1)
        where = f"control point {self.point_id!r}"
        if xyz.shape != (GP_SIZE,) or not np.all(np.isfinite(xyz)):
            raise InputDataError(f"{where}: xyz_m must be 3 finite numbers, got {xyz!r}")
        if sig.shape != (GP_SIZE,) or np.any(np.isnan(sig)) or np.any(sig <= 0):
            raise InputDataError(f"{where}: sigma_m must be 3 positive numbers (inf: free), "
                                 f"got {sig!r}")
        if not np.any(np.isfinite(sig)):
            raise InputDataError(f"{where}: at least one coordinate needs a finite sigma_m")
        object.__setattr__(self, "xyz_m", xyz)
        object.__setattr__(self, "sigma_m", sig)

    @property
    def weight(self) -> FloatArray:
        """(3,) ``1 / sigma^2`` (0 for a free coordinate)."""
        return 1.0 / self.sigma_m**2


@dataclass(frozen=True, kw_only=True, eq=False)
class EopEstimate:
    """Estimated exterior orientation of one image with its standard deviations."""

    image_id: str
    eop: FloatArray  # (6,) world metres / radians
    sigma: FloatArray  # (6,) metres / radians (scaled by the a posteriori sigma0)


@dataclass(frozen=True, kw_only=True, eq=False)
class PointEstimate:
    """Estimated ground point with standard deviations and the number of image observations."""

    point_id: str
    xyz_m: FloatArray  # (3,) world metres
    sigma_m: FloatArray  # (3,)
    n_obs: int


@dataclass(frozen=True, kw_only=True, eq=False)
class CameraEstimate:
    """The estimated camera with the standard deviations and correlations of its free
    parameters (scaled by the a posteriori sigma0).

    ``held``: parameters set free that the block did not determine, fixed at their prior
    (Sim). ``undetermined``: free parameters the data determine no better than the
    prior does (sequential: they stay estimated, constrained by their prior, since later
    images may determine them); ``seqat.calibration.HOLD_RATIO``."""

    camera: PinholeCamera
    prior: PinholeCamera
    free: tuple[str, ...]
    sigma: FloatArray  # (len(free),)
    correlation: FloatArray  # (len(free), len(free))
    held: tuple[str, ...] = ()
    undetermined: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (docs/formats.md, run.json ``camera``)."""
        values = {n: float(getattr(self.camera, n)) for n in INTRINSICS}
        prior = {n: float(getattr(self.prior, n)) for n in INTRINSICS}
        return {
            "values": values,
            "prior": prior,
            "free": list(self.free),
            "held": list(self.held),
            "undetermined": list(self.undetermined),
            "sigma": {n: float(s) for n, s in zip(self.free, self.sigma, strict=True)},
            "correlation": np.round(self.correlation, 4).tolist(),
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class Solution:
    """All parameters known so far (window and frozen), in first-seen order."""

    eops: tuple[EopEstimate, ...]
    points: tuple[PointEstimate, ...]
    sigma0: float
    redundancy: int
    #: The self-calibrated camera (None: the camera was fixed).
    camera: CameraEstimate | None = None
    #: Ids of estimated points left out of ``points``: their rays disagree, meet elsewhere
    #: in more rays or barely spread (seqat.robust.withheld_points, narrow_points), or they
    #: lie off the surface (seqat.surface).
    withheld: tuple[str, ...] = ()


@dataclass(frozen=True, kw_only=True)
class ImageUpdate:
    """What the estimator reports after each image (seed 000 Figs 8-11, seed 003 §4.4).

    ``inverse_sizes`` are the orders of the two matrices inverted in the update:
    ``[I + P2bar A21 N11^-1 A21^T]`` and ``(M22 + L22)`` (0, 0 in the initial Sim stage,
    where ``sim_reduced_size`` gives the order of the reduced EOP normal matrix instead).
    """

    image_id: str
    index: int
    stage: str  # "initial-sim" | "sequential" | "sim"
    update_ms: float
    window_images: int
    window_first_image: str
    window_params: int
    window_eop_params: int
    window_gp_params: int
    inverse_sizes: tuple[int, int]
    sim_reduced_size: int
    sigma0: float
    redundancy: int
    rms_gp_sigma_m: tuple[float, float, float]
    n_points_total: int
    new_points: int
    observations_used: int
    observations_skipped: int
    iterations: int
    eop: EopEstimate
    images_left_window: int = 0  # Seq-R: images that left the window before this update
    #: Seq-R: departed images and GPs re-opened in this update (docs/algorithm.md).
    reopened: int = 0
    #: Largest gap (px) between the window's linearised rows and the collinearity equations
    #: after this update (nan: not checked); above relinearise_px the window is re-adjusted.
    #: The check and the re-adjustment run once the update's estimate is out
    #: (``SequentialAT.refine``; their time is ``refine_ms``, not in ``update_ms``).
    drift_px: float = float("nan")
    #: When the window was re-adjusted after this update (drift check or re-linearisation):
    #: the largest change of a window camera's position (m) and attitude (deg); else nan.
    drift_m: float = float("nan")
    drift_deg: float = float("nan")
    #: Data snooping: observations removed in this update, (image id, point id, w).
    rejected: tuple[tuple[str, str, float], ...] = ()
    #: Data snooping: GPS/INS groups ("position", "attitude") down-weighted in this update.
    nav_downweighted: tuple[str, ...] = ()
    #: Late observations of earlier images the frame carried that the estimator used (as
    #: pending rays or rows); those it could not use are in ``observations_skipped``.
    late_used: int = 0
    #: A second start tried after this update (seqat/second_start.py), once the update was
    #: out: "kept" or "not kept" ("" none), and its time (ms; not in ``update_ms``).
    second_start: str = ""
    second_start_ms: float = float("nan")
    #: The refinement after this update (``SequentialAT.refine``: drift check,
    #: re-linearisation, housekeeping and a second start), ms; nan: none run. Its image's
    #: estimate was out before it: ``update_ms`` is that latency, ``update_ms + refine_ms``
    #: the image's processing.
    refine_ms: float = float("nan")

    @property
    def processing_ms(self) -> float:
        """The image's AT processing: ``update_ms`` and ``refine_ms`` (when one ran)."""
        refine = self.refine_ms
        return self.update_ms + (refine if math.isfinite(refine) else 0.0)
