"""Typed tables read from and written to the pipeline's CSV files (docs/formats.md).

Arrays are in the units used inside seqat: world metres and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqat.types import EOP_SIZE, GP_SIZE, FloatArray


def _check_shape(name: str, array: np.ndarray, shape: tuple[int, ...]) -> None:
    if array.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {array.shape}")


@dataclass(frozen=True, kw_only=True, eq=False)
class NavTable:
    """Exterior orientations with times: a projected ``nav.csv`` or a ``truth/eop.csv``.

    Attributes
    ----------
    image_ids : tuple[str, ...]
        In acquisition order (file order).
    times_s : (n,) float
        Acquisition times, seconds, strictly increasing.
    eop : (n, 6) float
        ``[X_m, Y_m, Z_m, omega_rad, phi_rad, kappa_rad]`` in the flight CRS.
    """

    image_ids: tuple[str, ...]
    times_s: FloatArray
    eop: FloatArray

    def __post_init__(self) -> None:
        n = len(self.image_ids)
        _check_shape("times_s", self.times_s, (n,))
        _check_shape("eop", self.eop, (n, EOP_SIZE))

    def __len__(self) -> int:
        return len(self.image_ids)

    def index(self) -> dict[str, int]:
        """Row of each image id."""
        return {iid: i for i, iid in enumerate(self.image_ids)}


@dataclass(frozen=True, kw_only=True, eq=False)
class EopTable:
    """Estimated exterior orientations with standard deviations (output ``eop.csv``).

    Attributes
    ----------
    image_ids : tuple[str, ...]
    eop : (n, 6) float
        Metres and radians.
    sigma : (n, 6) float
        Standard deviations, metres and radians; NaN where the estimator gave none.
    """

    image_ids: tuple[str, ...]
    eop: FloatArray
    sigma: FloatArray

    def __post_init__(self) -> None:
        n = len(self.image_ids)
        _check_shape("eop", self.eop, (n, EOP_SIZE))
        _check_shape("sigma", self.sigma, (n, EOP_SIZE))

    def __len__(self) -> int:
        return len(self.image_ids)

    def index(self) -> dict[str, int]:
        """Row of each image id."""
        return {iid: i for i, iid in enumerate(self.image_ids)}


@dataclass(frozen=True, kw_only=True, eq=False)
class PointTable:
    """Estimated ground points (output ``points.csv``).

    Attributes
    ----------
    point_ids : tuple[str, ...]
    xyz_m : (m, 3) float
    sigma_m : (m, 3) float
        NaN where the estimator gave none.
    n_obs : (m,) int
        Number of image observations used for each point.
    """

    point_ids: tuple[str, ...]
    xyz_m: FloatArray
    sigma_m: FloatArray
    n_obs: np.ndarray

    def __post_init__(self) -> None:
        m = len(self.point_ids)
        _check_shape("xyz_m", self.xyz_m, (m, GP_SIZE))
        _check_shape("sigma_m", self.sigma_m, (m, GP_SIZE))
        _check_shape("n_obs", self.n_obs, (m,))

    def __len__(self) -> int:
        return len(self.point_ids)

    def index(self) -> dict[str, int]:
        """Row of each point id."""
        return {pid: j for j, pid in enumerate(self.point_ids)}


@dataclass(frozen=True, kw_only=True, eq=False)
class GroundPoints:
    """Ground points without precision (``truth/points.csv``, ``checkpoints.csv``).

    Attributes
    ----------
    point_ids : tuple[str, ...]
    xyz_m : (m, 3) float
    """

    point_ids: tuple[str, ...]
    xyz_m: FloatArray

    def __post_init__(self) -> None:
        _check_shape("xyz_m", self.xyz_m, (len(self.point_ids), GP_SIZE))

    def __len__(self) -> int:
        return len(self.point_ids)

    def index(self) -> dict[str, int]:
        """Row of each point id."""
        return {pid: j for j, pid in enumerate(self.point_ids)}
