"""Self-calibration: the camera's interior parameters as unknowns shared by all images.

Seed 003 §3.3: the additional parameters of self-calibration "should be included" in the
sequential estimation. The interior parameters (:data:`seqat.types.INTRINSICS`: focal length,
principal point, radial ``k1 k2 k3`` and decentring ``p1 p2`` distortion of COLMAP's OPENCV
model) that :class:`SelfCalibration` sets free are estimated with every image's EOPs, with
a prior (the EXIF or ``flight.yaml`` value, a standard deviation each) as a stochastic
constraint. The prior keeps the normal equations regular; a parameter the block cannot
determine is *held*: fixed at its prior and reported as such (:func:`undetermined`), as
Metashape and COLMAP warn of over-parameterisation. docs/algorithm.md, *Self-calibration*.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqat.errors import ConfigError
from seqat.geometry import project, project_with_jacobians
from seqat.types import EOP_SIZE, INTRINSICS, FloatArray, PinholeCamera

#: Parameters estimated by default: focal length, principal point, k1, k2, p1, p2 (k3 is
#: rarely determinable from an aerial block and correlates with k1/k2).
DEFAULT_FREE = ("f_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2")

#: Default prior standard deviations: f as a fraction of f (EXIF focal lengths are nominal,
#: a few per cent off), the principal point as a fraction of the larger image side, the
#: distortion coefficients in their own (normalised) units.
PRIOR_F_FRACTION = 0.05
PRIOR_C_FRACTION = 0.02
PRIOR_K = 0.2
PRIOR_P = 0.01

#: A free parameter is undetermined (held at its prior) when the block's data shrink its
#: prior standard deviation by less than this factor: they add less than ``1/r^2 - 1 = 10``
#: times the prior's information (a single strip's k2 against its heights: 0.46).
HOLD_RATIO = 0.3


#: A free parameter whose estimate differs from its prior value by less than this many
#: a-posteriori sigmas is not significant (two-sided alpha = 0.05) and is held at its prior,
#: as additional parameters are tested in a self-calibrating bundle adjustment: estimated
#: but indistinguishable from the prior, it only trades with the EOPs and heights (on the
#: paper's strip: k1 0.0019 +- 0.0025 doubled the GPs' height error).
SIGNIFICANCE = 1.96


@dataclass(frozen=True, kw_only=True)
class SelfCalibration:
    """Which interior parameters are estimated, and their prior standard deviations.

    Parameters
    ----------
    free : tuple of str
        Names from :data:`seqat.types.INTRINSICS`, estimated in the order of that tuple.
    sigma : dict of str to float, optional
        Prior standard deviation per parameter (pixels for ``f_px cx_px cy_px``, normalised
        units for the distortion); missing ones get the defaults (:meth:`prior_sigma`).
    hold_undetermined : bool
        Hold parameters the block does not determine at their prior (:data:`HOLD_RATIO`)
        and, with ``significance``, those not significantly different from it.
    significance : float or None
        The significance test of :func:`to_hold` (:data:`SIGNIFICANCE` sigmas); None: off.
    """

    free: tuple[str, ...] = DEFAULT_FREE
    sigma: tuple[tuple[str, float], ...] = ()
    hold_undetermined: bool = True
    significance: float | None = SIGNIFICANCE

    def __post_init__(self) -> None:
        object.__setattr__(self, "free", tuple(self.free))
        sig = dict(self.sigma) if not isinstance(self.sigma, dict) else self.sigma
        object.__setattr__(self, "sigma", tuple(sorted(sig.items())))
        unknown = [n for n in (*self.free, *sig) if n not in INTRINSICS]
        if unknown:
            raise ConfigError(f"self-calibration: unknown parameter {unknown[0]!r}, expected "
                              f"one of {', '.join(INTRINSICS)}")
        if len(set(self.free)) != len(self.free):
            raise ConfigError("self-calibration: a parameter is listed twice")
        if self.significance is not None and not self.significance > 0:
            raise ConfigError(f"self-calibration: significance must be a positive number of "
                              f"sigmas or null, got {self.significance!r}")
        for name, s in sig.items():
            if not (np.isfinite(s) and s > 0):
                raise ConfigError(f"self-calibration: sigma of {name} must be a positive "
                                  f"number, got {s!r}")

    @property
    def index(self) -> np.ndarray:
        """Positions of the free parameters in :data:`INTRINSICS`, in INTRINSICS order."""
        return np.array([i for i, n in enumerate(INTRINSICS) if n in self.free],
                        dtype=np.int64)

    @property
    def names(self) -> tuple[str, ...]:
        """The free parameters in :data:`INTRINSICS` order (the estimator's column order)."""
        return tuple(n for n in INTRINSICS if n in self.free)

    def prior_sigma(self, camera: PinholeCamera) -> FloatArray:
        """(8,) prior standard deviation of every :data:`INTRINSICS` parameter."""
        side = float(max(camera.width_px, camera.height_px))
        default = {"f_px": PRIOR_F_FRACTION * camera.f_px, "cx_px": PRIOR_C_FRACTION * side,
                   "cy_px": PRIOR_C_FRACTION * side, "k1": PRIOR_K, "k2": PRIOR_K,
                   "k3": PRIOR_K, "p1": PRIOR_P, "p2": PRIOR_P}
        default.update(dict(self.sigma))
        return np.array([default[n] for n in INTRINSICS])

    def holding(self, names: tuple[str, ...]) -> SelfCalibration:
        """The same calibration with ``names`` no longer free."""
        return SelfCalibration(free=tuple(n for n in self.free if n not in names),
                               sigma=self.sigma, hold_undetermined=self.hold_undetermined,
                               significance=self.significance)


def to_hold(calibration: SelfCalibration, cofactor: FloatArray, prior_sigma: FloatArray,
            values: FloatArray, prior: FloatArray, scale: float) -> np.ndarray:
    """Free parameters to hold at their prior: undetermined, or (with
    ``calibration.significance``) not significantly different from the prior, their sigma
    the cofactor's square root times ``scale`` (the a posteriori sigma0)."""
    bad = undetermined(cofactor, prior_sigma)
    if calibration.significance is not None:
        sigma = np.sqrt(np.maximum(np.diagonal(cofactor), 0.0)) * scale
        bad |= np.abs(values - prior) < calibration.significance * sigma
    return bad


def undetermined(cofactor: FloatArray, prior_sigma: FloatArray) -> np.ndarray:
    """Free parameters the data do not determine: a posteriori sigma (a priori units, the
    cofactor's square root) above :data:`HOLD_RATIO` times the prior sigma.

    Parameters
    ----------
    cofactor : (c, c) float
        Cofactor block of the free parameters.
    prior_sigma : (c,) float

    Returns
    -------
    (c,) bool
    """
    return np.sqrt(np.maximum(np.diagonal(cofactor), 0.0)) > HOLD_RATIO * prior_sigma


def correlation(cofactor: FloatArray) -> FloatArray:
    """Correlation matrix of a cofactor block."""
    sd = np.sqrt(np.maximum(np.diagonal(cofactor), 1e-300))
    return cofactor / np.outer(sd, sd)


@dataclass(frozen=True, eq=False)
class FreeCamera:
    """A camera whose free interior parameters ride along with each observation's EOP.

    The sequential estimator addresses an image point's parameters as an *image block*
    ``[EOP (6), free interior parameters (c)]`` and its GP (3): the camera's columns are
    appended to every observation's EOP columns, so every factor, Jacobian and scatter
    of the fixed-camera code applies unchanged (``c = 0`` is the fixed camera).

    Parameters
    ----------
    base : PinholeCamera
        The camera (its values of the parameters that are not free are used).
    index : (c,) int
        Positions of the free parameters in :data:`seqat.types.INTRINSICS`.
    """

    base: PinholeCamera
    index: np.ndarray

    @property
    def size(self) -> int:
        return int(self.index.size)

    def at(self, values: FloatArray) -> PinholeCamera:
        """The camera with the free parameters at ``values`` (c,)."""
        if not self.size:
            return self.base
        intr = self.base.intrinsics
        intr[self.index] = values
        return self.base.with_intrinsics(intr)

    def admissible(self, values: FloatArray) -> bool:
        """The free parameters at ``values`` (c,) make a camera (finite, focal length > 0):
        an iterate that leaves this domain is not a camera to project with."""
        if not np.all(np.isfinite(values)):
            return False
        f = values[self.index == INTRINSICS.index("f_px")]
        return bool(np.all(f > 0.0))

    def _camera_of(self, e_ext: FloatArray) -> PinholeCamera:
        if not self.size or e_ext.shape[0] == 0:
            return self.base
        return self.at(e_ext[0, EOP_SIZE:])  # one camera: every row holds the same values

    def project(self, e_ext: FloatArray, X: FloatArray) -> FloatArray:
        """Pixels of ``X`` (k, 3) from image blocks ``e_ext`` (k, 6 + c)."""
        return project(e_ext[:, :EOP_SIZE], X, self._camera_of(e_ext))

    def project_with_jacobians(self, e_ext: FloatArray,
                               X: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Pixels and Jacobians ``d uv / d e_ext`` (k, 2, 6 + c) and ``d uv / d X``."""
        cam = self._camera_of(e_ext)
        if not self.size:
            uv, Je, Jp = project_with_jacobians(e_ext, X, cam)
            return uv, Je, Jp
        uv, Je, Jp, Jc = project_with_jacobians(e_ext[:, :EOP_SIZE], X, cam, intrinsics=True)
        return uv, np.concatenate([Je, Jc[:, :, self.index]], axis=2), Jp
