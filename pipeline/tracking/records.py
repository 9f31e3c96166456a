"""What the streaming tracker (:mod:`pipeline.tracking.tracker`) hands out and keeps: the
observations of an image, its statistics, the held images and the tracker's state."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from seqat.types import FloatArray


@dataclass(frozen=True, kw_only=True)
class TrackStats:
    """What the tracker did for one image (serialised into ``run.json``).

    Attributes
    ----------
    features : int
        Features detected (all are used to match).
    emitted : int
        Features that became observations (``TrackerOptions.emit_per_image``).
    candidates : tuple[str, ...]
        Held images matched, best predicted overlap first.
    pairs_matched : int
        Candidate pairs that passed geometric verification.
    matches : int
        Ratio-test matches over all candidate pairs.
    inliers : int
        Verified matches over the accepted pairs.
    new_tracks : int
        Tracks that got their second image now.
    extended_tracks : int
        Tracks that got a third or later image now.
    split_conflicts : int
        Features whose verified matches pointed to more than one track, plus features that
        lost a track to another feature of the same image.
    late : int
        Late observations of held images emitted with this image.
    detect_ms, match_ms, total_ms : float
        Wall times: gray conversion, downscale and detection; candidate selection, matching,
        verification and linking; the whole call.
    """

    features: int
    emitted: int
    candidates: tuple[str, ...]
    pairs_matched: int
    matches: int
    inliers: int
    new_tracks: int
    extended_tracks: int
    split_conflicts: int
    detect_ms: float
    match_ms: float
    total_ms: float
    late: int = 0


@dataclass(frozen=True, kw_only=True, eq=False)
class TrackedImage:
    """The observations of one image, as emitted to the estimator.

    Attributes
    ----------
    image_id : str
    point_ids : tuple[str, ...]
        Track id of every emitted feature, unique within the image.
    uv_px : (k, 2) float
        Observed pixels of the full-resolution image (OpenCV convention; lens distortion not
        removed: :class:`pipeline.flight.camera.PixelCorrector` does that).
    stats : TrackStats
    late_image_ids, late_point_ids : tuple[str, ...]
        Late observations of held (earlier) images emitted with this image (module
        docstring): image and track id of each.
    late_uv_px : (m, 2) float
        Their observed full-resolution pixels in the earlier image.
    """

    image_id: str
    point_ids: tuple[str, ...]
    uv_px: FloatArray
    stats: TrackStats
    late_image_ids: tuple[str, ...] = ()
    late_point_ids: tuple[str, ...] = ()
    late_uv_px: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(kw_only=True, eq=False)
class HeldImage:
    """What the tracker keeps of an earlier image (no pixels). Arrays never change in place
    once held: a late emission replaces ``point_nums`` and ``late`` by new arrays."""

    image_id: str
    seq: int  # acquisition index
    nav_eop: FloatArray  # (6,)
    kp_work: NDArray[np.float32]  # (n, 2) working-resolution keypoints
    desc: NDArray[np.uint8]  # (n, d) descriptors
    point_nums: NDArray[np.int64]  # (n,) point number of each keypoint's pixel, -1: not emitted
    last_overlap_seq: int = field(default=0)
    #: (m, 2) [keypoint index, point number] of every late emission (``point_nums`` includes
    #: them): what changed since the image was added.
    late: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    #: (n, 2) ``kp_work`` with the lens distortion removed, where the pairs are verified
    #: (:meth:`Tracker.geometric_keypoints`); None: not formed (the state files do not keep
    #: it, :meth:`Tracker.restore` forms it again).
    kp_geo: NDArray[np.float32] | None = None


@dataclass(frozen=True, kw_only=True, eq=False)
class TrackerState:
    """Everything a :class:`Tracker` holds between images (:meth:`Tracker.state`).

    A fresh tracker of the same options and camera given this state (:meth:`Tracker.restore`)
    tracks the next images exactly as the tracker it was taken from. ``held`` are copies whose
    arrays are shared with the tracker (they never change once an image is held).

    Attributes
    ----------
    seq : int
        Images added so far.
    next_point : int
        Number of the next fresh track id.
    origin_xy : (2,) float or None
        Local origin of the footprints.
    held : tuple[HeldImage, ...]
        Held images, oldest first, with their ``last_overlap_seq`` at the time of the state.
    tracks : (m, 3) int64
        Point number, images in the track, held images holding it.
    """

    seq: int
    next_point: int
    origin_xy: FloatArray | None
    held: tuple[HeldImage, ...]
    tracks: NDArray[np.int64]
