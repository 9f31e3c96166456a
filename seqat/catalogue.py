"""The growing store of observations behind the simultaneous adjustment (Sim).

:class:`Catalogue` keeps every frame's nav and image points, and the *late observations* a
frame carries (observations of earlier images the tracker emitted only with this frame,
docs/algorithm.md, *Late observations*): Sim takes them as ordinary observations of their
image, so a late observation changes nothing but the moment it becomes known. Also
:func:`control_by_id`, the ground control by point id (Sim and the sequential estimators).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from seqat.errors import InputDataError
from seqat.types import ControlPoint, FloatArray, Frame

#: Sigma given to free GPS/INS components (Frame.nav_sigma inf): metres and radians.
FREE_NAV_SIGMA = np.array([1e3, 1e3, 1e3, 1.0, 1.0, 1.0])


def free_nav_sigma(sigma: FloatArray) -> FloatArray:
    """GPS/INS sigmas with the free components (inf, a dropout) replaced by a weak constraint
    (:data:`FREE_NAV_SIGMA`): an image the tie points do not determine keeps its starting
    value with a sigma that says so, instead of a singular system."""
    return np.where(np.isinf(sigma), FREE_NAV_SIGMA, sigma)


@dataclass(eq=False)
class Catalogue:
    """Growing store of the frames seen so far (used by the simultaneous baseline)."""

    image_ids: list[str] = field(default_factory=list)
    image_index: dict[str, int] = field(default_factory=dict)
    nav_eop: list[FloatArray] = field(default_factory=list)
    nav_sigma: list[FloatArray] = field(default_factory=list)
    point_index: dict[str, int] = field(default_factory=dict)
    point_ids: list[str] = field(default_factory=list)
    obs_image: list[int] = field(default_factory=list)
    obs_point: list[int] = field(default_factory=list)
    obs_uv: list[FloatArray] = field(default_factory=list)
    obs_sigma: list[float] = field(default_factory=list)
    #: (image index, point index) of every observation, to refuse a repeated one.
    pairs: set[tuple[int, int]] = field(default_factory=set)

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Image and point index (int64 arrays) of every observation, in order."""
        return (np.asarray(self.obs_image, dtype=np.int64),
                np.asarray(self.obs_point, dtype=np.int64))

    def point(self, pid: str) -> int:
        """Index of point ``pid`` (a new one is numbered)."""
        j = self.point_index.get(pid)
        if j is None:
            j = self.point_index[pid] = len(self.point_ids)
            self.point_ids.append(pid)
        return j

    def add_frame(self, frame: Frame, nav: FloatArray, nav_sigma: FloatArray) -> int:
        """Add a frame (local ``nav``): its late observations first, then its own image
        points. Returns the image index.

        Raises
        ------
        InputDataError
            A late observation of an image not added before, or of an (image, point) pair
            already observed.
        """
        for iid in frame.late_image_ids:
            if iid not in self.image_index:
                raise InputDataError(
                    f"image {frame.image_id!r}: late observation of image {iid!r}, which the "
                    "estimator has not received (late observations are of earlier images)")
        i = len(self.image_ids)
        self.image_index[frame.image_id] = i
        self.image_ids.append(frame.image_id)
        self.nav_eop.append(nav)
        self.nav_sigma.append(nav_sigma)
        late = [(self.image_index[iid], self.point(pid), uv) for iid, pid, uv
                in zip(frame.late_image_ids, frame.late_point_ids, frame.late_uv_px,
                       strict=True)]
        own = [(i, self.point(pid), uv) for pid, uv in zip(frame.point_ids, frame.uv_px,
                                                          strict=True)]
        for img, j, uv in late + own:
            if (img, j) in self.pairs:
                raise InputDataError(
                    f"image {frame.image_id!r}: point {self.point_ids[j]!r} is observed twice "
                    f"in image {self.image_ids[img]!r} (a late observation repeats one)")
            self.pairs.add((img, j))
            self.obs_image.append(img)
            self.obs_point.append(j)
            self.obs_uv.append(uv)
            self.obs_sigma.append(frame.sigma_px)
        return i


def control_by_id(control: Sequence[ControlPoint]) -> dict[str, ControlPoint]:
    """The control points by point id; an id given twice is an input error."""
    out: dict[str, ControlPoint] = {}
    for cp in control:
        if cp.point_id in out:
            raise InputDataError(f"control point {cp.point_id!r} is given twice")
        out[cp.point_id] = cp
    return out
