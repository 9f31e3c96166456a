"""Streaming tie points: features of each new image matched to earlier images, grown to tracks.

When image ``i`` arrives (:meth:`Tracker.add_image`) the tracker

1. converts it to gray and downscales it to a *working copy* ``working_width_px`` wide (never
   upscaled, ``cv2.INTER_AREA``), detects SIFT (default) or ORB features there;
2. predicts the ground footprint of ``i`` and of every held image from the nav EOPs (the four
   image corners intersected with the plane ``Z = ground_z_m``, ideal pinhole from
   ``fx_px, cx_px, cy_px``) and picks as candidates the up-to-``neighbours`` held images whose
   footprint covers at least ``min_overlap`` of the footprint of ``i``, best overlap first
   (none: the most recent images near in plan, :mod:`pipeline.tracking.footprint`);
3. matches ``i`` against each candidate (FLANN kd-tree or brute force for SIFT, brute-force
   Hamming for ORB; ``knnMatch`` k = 2 and Lowe's ratio test; one match per feature of ``i``)
   and verifies the pair with ``USAC_MAGSAC`` on the fundamental matrix (or a homography) at
   working resolution, on the keypoints with the lens distortion removed (the epipolar
   geometry holds for ideal pixels, not for a wide lens's observed ones); pairs with fewer
   than ``min_inliers`` inliers are rejected;
4. gives each feature of ``i`` a point id: the id of the track its verified matches point to,
   or a fresh id (``t`` + 7-digit counter, unique over the flight); features at one pixel
   (SIFT's orientations of one blob, :func:`feature_sites`) are one observation.

Up to ``emit_per_image`` features of ``i`` are emitted (:class:`TrackedImage`), matched or
not: every continuation of a track, then features matched to non-emitted features of held
images (below), then new features over a grid. A track born later between ``i`` and a later
image then has ``i``'s observation in the estimator already (the estimator keeps single-ray
points pending). Nothing is looked ahead.

**Late observations.** A held image keeps all its features for matching but emitted only
some. When a verified match links a feature of ``i`` to a feature of a held image ``j`` that
``j`` did not emit, ``j``'s feature is emitted *now*, as a late observation of ``j`` carried
by ``i``'s :class:`TrackedImage` (``late_*``): it joins the track of ``i``'s feature (a
continued or a fresh one) unless that track already holds a feature of ``j``. Per pair
as many as top its ties through emitted features up to ``late_per_pair``
(``late_untied_per_pair`` when it has none, or when none of ``j``'s tracks has a second
image yet), smallest descriptor distance first; one per pixel of ``j``. This is the
only thing emitted about an earlier image later; without it, an image whose matches all
fell on features its neighbour did not emit would have no tie point. The held image's point
numbers are replaced, never changed in place (:meth:`Tracker.state` snapshots share them),
and its late emissions are kept apart (``HeldImage.late``) for the journal.

Tracks are never merged. If a feature of ``i`` matches features of several different tracks
(through different candidate images), it joins the one with the most verified matches (ties:
the candidate with the larger predicted overlap, then the smaller descriptor distance); if two
features of ``i`` claim the same track, the one with the smaller descriptor distance gets it
and the other starts a fresh track. Both count as ``split_conflicts``. Hence a track never
holds two features of one image.

Memory: the tracker holds per image only the working-resolution keypoints (float32), the
descriptors (uint8), the point id number of each
keypoint and the nav EOP, never pixels. An image is dropped once its footprint has not
overlapped (``>= min_overlap``) any of the last ``stale_after_images`` new images, and at most
``max_held_images`` are held (the least recently overlapped go first). Footprints are
recomputed with the current ``ground_z_m`` on every call (4 rays per held image).

Pixels (docs/conventions.md): OpenCV convention, centre of the top-left pixel at ``(0, 0)``. A
working-resolution keypoint maps to the full-resolution image exactly by
``u_full = (u_work + 0.5) * s_u - 0.5`` and ``v_full = (v_work + 0.5) * s_v - 0.5`` with
``s_u = width_px / working width`` and ``s_v = height_px / working height``; the working
height is ``round(height_px * working width / width_px)``, so ``s_u == s_v`` whenever that
product is an integer (3600 x 2700 at 800, 1000 or 1400 px).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from pipeline.tracking.decode import jpeg_scan_problem
from pipeline.tracking.footprint import ground_footprint, near_in_plan
from pipeline.tracking.late import emit_late, feature_sites, late_candidates, pair_ties
from pipeline.tracking.matching import NewImageMatcher, ratio_matches
from pipeline.tracking.options import MIN_MODEL_POINTS, TrackerOptions
from pipeline.tracking.records import HeldImage, TrackedImage, TrackerState, TrackStats
from seqat.errors import InputDataError
from seqat.types import EOP_SIZE, FloatArray, PinholeCamera

#: The plane gate is never tighter than this many MAGSAC thresholds.
PLANE_GATE_MIN_FACTOR = 3.0
#: Smallest height above the ground plane used by the plane gate, metres.
MIN_HEIGHT_M = 1.0
#: Confidence and iteration cap of USAC_MAGSAC.
RANSAC_CONFIDENCE = 0.999
RANSAC_MAX_ITERATIONS = 10000
#: OpenCV's SIFT defaults (Lowe 2004): layers per octave, edge threshold, base blur.
SIFT_OCTAVE_LAYERS = 3
SIFT_EDGE_THRESHOLD = 10.0
SIFT_SIGMA = 1.6
#: ORB pyramid scale factor (OpenCV's default).
ORB_SCALE_FACTOR = 1.2
#: Digits of the point id counter (``t0000001``).
POINT_ID_DIGITS = 7
#: Image sizes accepted: gray (H, W) or 3-channel BGR (H, W, 3).
BGR_CHANNELS = 3
#: JPEG reduced-decode factors and their OpenCV flags (libjpeg scaled IDCT: reduced pixel k
#: covers full pixels ``[k f, (k + 1) f)``, checked against ``INTER_AREA`` to < 0.01 px).
REDUCED_GRAY_FLAGS = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2,
                      4: cv2.IMREAD_REDUCED_GRAYSCALE_4, 8: cv2.IMREAD_REDUCED_GRAYSCALE_8}


class TrackerCamera(Protocol):
    """What the tracker needs of a camera (a :class:`pipeline.flight.schema.CameraConfig`):
    its size and the ideal pinhole ``fx_px, cx_px, cy_px`` (footprint prediction only)."""

    @property
    def width_px(self) -> int: ...
    @property
    def height_px(self) -> int: ...
    @property
    def fx_px(self) -> float: ...
    @property
    def cx_px(self) -> float: ...
    @property
    def cy_px(self) -> float: ...


@dataclass(frozen=True, kw_only=True, eq=False)
class _Candidate:
    held: HeldImage
    overlap: float  # fraction of the new footprint; NaN when a footprint is unknown


class Tracker:
    """Streaming feature tracker (see the module docstring).

    Parameters
    ----------
    options : TrackerOptions
    camera : TrackerCamera
        A :class:`pipeline.flight.schema.CameraConfig`: size and ``fx_px, cx_px, cy_px``
        (ideal pinhole, for the footprint prediction only).
    ideal_pixels : callable, optional
        Observed full-resolution pixels ``(k, 2)`` -> ideal pinhole pixels, the lens
        distortion removed (:meth:`pipeline.flight.camera.PixelCorrector.ideal_pixels`): the
        pairs are verified on them. None: the observed pixels are ideal (no distortion).
    """

    def __init__(self, options: TrackerOptions, camera: TrackerCamera,
                 ideal_pixels: Callable[[FloatArray], FloatArray] | None = None) -> None:
        self.options = options
        self.camera = camera
        self._ideal_pixels = ideal_pixels
        self._pinhole = PinholeCamera(f_px=camera.fx_px, cx_px=camera.cx_px,
                                      cy_px=camera.cy_px, width_px=camera.width_px,
                                      height_px=camera.height_px)
        w = min(options.working_width_px, camera.width_px)
        h = max(1, round(camera.height_px * w / camera.width_px))
        self.working_size_px = (w, h)
        #: Largest JPEG decode reduction that still is at least the working size and divides
        #: the camera size exactly (:func:`read_gray_image`).
        self.decode_factor = max(
            f for f in REDUCED_GRAY_FLAGS
            if f == 1 or (camera.width_px % f == 0 and camera.height_px % f == 0
                          and camera.width_px // f >= w and camera.height_px // f >= h))
        #: Full / working scale along u and v.
        self.scale_uv = (camera.width_px / w, camera.height_px / h)
        self._detector = self._make_detector(options.max_features)
        if options.opencv_threads > 0:
            cv2.setNumThreads(options.opencv_threads)
        self._held: list[HeldImage] = []
        self._seq = 0
        self._next_point = 1
        #: point number -> [track length in images, held images holding it]
        self._tracks: dict[int, list[int]] = {}
        self._origin_xy: FloatArray | None = None

    # ----------------------------------------------------------------------------------------
    def _make_detector(self, features: int) -> cv2.Feature2D:
        if self.options.detector == "orb":
            return cv2.ORB_create(nfeatures=features, scaleFactor=ORB_SCALE_FACTOR)
        # precise upscale: without it OpenCV's SIFT keypoints are 0.25 px (working resolution)
        # right of and below the true position (its doubled first octave is resampled
        # centre-aligned, then halved corner-aligned).
        return cv2.SIFT_create(features, SIFT_OCTAVE_LAYERS, self.options.sift_contrast_threshold,
                               SIFT_EDGE_THRESHOLD, SIFT_SIGMA, cv2.CV_8U, True)

    def set_max_features(self, features: int) -> None:
        """Detect at most ``features`` per image from the next one on (the latency budget's
        dial, :mod:`pipeline.run.budget`); the held images keep theirs."""
        self._detector = self._make_detector(max(1, int(features)))

    @property
    def held_images(self) -> int:
        """Number of images whose features are kept for matching (bounded)."""
        return len(self._held)

    @property
    def held_image_ids(self) -> tuple[str, ...]:
        """Ids of the held images, oldest first."""
        return tuple(h.image_id for h in self._held)

    def state(self) -> TrackerState:
        """The tracker's state after the last image (:class:`TrackerState`)."""
        tracks = np.array([[num, length, held] for num, (length, held) in self._tracks.items()],
                          dtype=np.int64).reshape(-1, 3)
        return TrackerState(seq=self._seq, next_point=self._next_point,
                            origin_xy=None if self._origin_xy is None else self._origin_xy.copy(),
                            held=tuple(dataclasses.replace(h) for h in self._held),
                            tracks=tracks)

    def restore(self, state: TrackerState) -> None:
        """Continue from ``state`` (taken from a tracker of the same options and camera)."""
        self._seq, self._next_point = state.seq, state.next_point
        self._origin_xy = None if state.origin_xy is None else np.array(state.origin_xy)
        self._held = [dataclasses.replace(h, kp_geo=self.geometric_keypoints(h.kp_work))
                      for h in state.held]
        self._tracks = {int(n): [int(length), int(held)] for n, length, held in state.tracks}

    def to_full_px(self, uv_work: FloatArray) -> FloatArray:
        """Working-resolution pixels -> full-resolution pixels (exact, see module docstring).

        Parameters
        ----------
        uv_work : (k, 2) float

        Returns
        -------
        (k, 2) float
        """
        uv = np.asarray(uv_work, dtype=np.float64).reshape(-1, 2)
        s = np.asarray(self.scale_uv)
        return (uv + 0.5) * s - 0.5

    def geometric_keypoints(self, kp_work: NDArray[np.float32]) -> NDArray[np.float32]:
        """Working-resolution keypoints with the lens distortion removed (ideal pixels at the
        working scale), where a pair's epipolar geometry holds; ``kp_work`` itself without
        ``ideal_pixels``."""
        if self._ideal_pixels is None or len(kp_work) == 0:
            return kp_work
        ideal = self._ideal_pixels(self.to_full_px(kp_work))
        return ((ideal + 0.5) / np.asarray(self.scale_uv) - 0.5).astype(np.float32)

    # ----------------------------------------------------------------------------------------
    def add_image(self, image_id: str, image: NDArray[np.uint8], nav_eop: FloatArray,
                  ground_z_m: float | None) -> TrackedImage:
        """Detect, match and track one new image.

        Parameters
        ----------
        image_id : str
            Unique within the flight.
        image : (H, W) or (H, W, 3) uint8
            Gray or BGR image of the camera's size, or of that size divided by 2, 4 or 8
            (a reduced JPEG decode, :func:`read_gray_image`) if it divides exactly and is
            not smaller than the working copy. Reduced pixel ``k`` covers full pixels
            ``[k f, (k + 1) f)``; the emitted ``uv_px`` are always full-resolution pixels.
        nav_eop : (6,) float
            Nav ``[X, Y, Z m, omega, phi, kappa rad]`` in the world frame (footprint only).
        ground_z_m : float or None
            Current terrain height estimate (world Z, metres); None before one exists, then
            ``Z - default_height_above_ground_m`` of this image is used.

        Returns
        -------
        TrackedImage
            Every kept feature of this image with its point id, full-resolution pixels.

        Raises
        ------
        InputDataError
            Wrong image size, type or channels; non-finite nav; an image id already held.
        """
        t0 = time.perf_counter()
        nav = self._check_input(image_id, image, nav_eop)
        kp_work, desc, response = self._detect(image)
        kp_geo = self.geometric_keypoints(kp_work)
        n_detected = len(kp_work)
        t1 = time.perf_counter()

        plane_z = (float(ground_z_m) if ground_z_m is not None and math.isfinite(ground_z_m)
                   else float(nav[2]) - self.options.default_height_above_ground_m)
        candidates = self._select_candidates(nav, plane_z)
        links, unlinked, n_matches, n_inliers, n_pairs = self._match(
            kp_geo, desc, candidates, nav, plane_z)
        site = feature_sites(kp_work)
        # held images none of whose tracks reached a second image yet: untied, whatever
        # this image's links to them (the larger cap of late observations)
        isolated = [rank for rank, c in enumerate(candidates)
                    if not any(self._tracks[n][0] >= 2 for n in
                               np.unique(c.held.point_nums[c.held.point_nums >= 0]).tolist())]
        point_nums, n_new, n_ext, n_conflicts = self._assign(len(kp_work), links, site)
        opts = self.options
        ties = pair_ties(links)
        ties.update({rank: 0 for rank in isolated})
        late, preferred = late_candidates(unlinked, ties, opts.late_per_pair,
                                          opts.late_untied_per_pair)
        prefer = np.asarray([f for f in dict.fromkeys(preferred) if point_nums[f] < 0],
                            dtype=np.int64)
        keep = self._emitted(kp_work, response, point_nums, site, prefer)
        fresh = keep[point_nums[keep] < 0]
        point_nums[fresh] = np.arange(self._next_point, self._next_point + len(fresh))
        for num in point_nums[fresh].tolist():
            self._tracks[num] = [1, 1]
        self._next_point += len(fresh)
        # -1: not emitted; every orientation of an emitted pixel matches into its track
        site_num = np.full(int(site.max(initial=-1)) + 1, -1, dtype=np.int64)
        site_num[site[keep]] = point_nums[keep]
        held_nums = site_num[site]
        late_out = emit_late([c.held for c in candidates], late, ties, held_nums,
                             self._tracks, opts.late_per_pair, opts.late_untied_per_pair)
        # a fresh track a late observation joined got its second image now
        fresh_nums = set(point_nums[fresh].tolist())
        n_new += len({num for _, num, _ in late_out if num in fresh_nums})
        t2 = time.perf_counter()

        # every feature is held for matching (verification needs many matches); only the
        # emitted ones carry tracks
        held = HeldImage(image_id=image_id, seq=self._seq, nav_eop=nav, kp_work=kp_work,
                          desc=desc, point_nums=held_nums, last_overlap_seq=self._seq,
                          kp_geo=kp_geo)
        self._held.append(held)
        self._seq += 1
        self._prune()

        uv_full = self.to_full_px(kp_work[keep])
        ids = tuple(_point_id(n) for n in point_nums[keep].tolist())
        late_uv = self.to_full_px(np.array([uv for _, _, uv in late_out]).reshape(-1, 2))
        t3 = time.perf_counter()
        stats = TrackStats(
            features=n_detected, emitted=len(ids),
            candidates=tuple(c.held.image_id for c in candidates),
            pairs_matched=n_pairs, matches=n_matches, inliers=n_inliers, new_tracks=n_new,
            extended_tracks=n_ext, split_conflicts=n_conflicts,
            detect_ms=1e3 * (t1 - t0), match_ms=1e3 * (t2 - t1), total_ms=1e3 * (t3 - t0),
            late=len(late_out))
        return TrackedImage(image_id=image_id, point_ids=ids, uv_px=uv_full, stats=stats,
                            late_image_ids=tuple(h for h, _, _ in late_out),
                            late_point_ids=tuple(_point_id(n) for _, n, _ in late_out),
                            late_uv_px=late_uv)

    # ----------------------------------------------------------------------------------------
    def _check_input(self, image_id: str, image: NDArray[np.uint8],
                     nav_eop: FloatArray) -> FloatArray:
        cam = self.camera
        img = np.asarray(image)
        shape_ok = (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == BGR_CHANNELS))
        w, h = self.working_size_px
        sizes = {(cam.height_px // f, cam.width_px // f) for f in REDUCED_GRAY_FLAGS
                 if cam.width_px % f == 0 and cam.height_px % f == 0
                 and cam.width_px // f >= w and cam.height_px // f >= h}
        if img.dtype != np.uint8 or not shape_ok or img.shape[:2] not in sizes:
            raise InputDataError(
                f"image {image_id!r}: expected a uint8 gray or BGR image of "
                f"{cam.width_px} x {cam.height_px} px or reduced by "
                f"{', '.join(str(f) for f in REDUCED_GRAY_FLAGS if f > 1)} to at least "
                f"{w} x {h} px, got {img.dtype} array of shape {img.shape}")
        nav = np.asarray(nav_eop, dtype=np.float64).reshape(-1)
        if nav.shape != (EOP_SIZE,) or not np.all(np.isfinite(nav)):
            raise InputDataError(f"image {image_id!r}: nav_eop must be 6 finite numbers, "
                                 f"got {nav_eop!r}")
        if any(h.image_id == image_id for h in self._held):
            raise InputDataError(f"image {image_id!r}: added twice")
        return nav

    def _detect(self, image: NDArray[np.uint8]) -> tuple[NDArray[np.float32], NDArray[np.uint8],
                                                         FloatArray]:
        """Gray working copy -> keypoints (n, 2) float32, descriptors (n, d) uint8, responses."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self.working_size_px != (gray.shape[1], gray.shape[0]):
            gray = cv2.resize(gray, self.working_size_px, interpolation=cv2.INTER_AREA)
        keypoints, desc = self._detector.detectAndCompute(gray, None)
        n_bytes = 128 if self.options.detector == "sift" else 32
        if desc is None or len(keypoints) == 0:
            return np.zeros((0, 2), np.float32), np.zeros((0, n_bytes), np.uint8), np.zeros(0)
        kp = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
        response = np.array([k.response for k in keypoints], dtype=np.float64)
        if self.options.detector == "orb":
            # ORB reports a level-l corner at x_l * s_l; the level was resampled centre-aligned
            # (cv2.resize), so the pixel is (x_l + 0.5) s_l - 0.5: add 0.5 (s_l - 1).
            level = np.array([k.octave for k in keypoints], dtype=np.float64)
            kp += 0.5 * (ORB_SCALE_FACTOR**level - 1.0)[:, None]
        return kp.astype(np.float32), np.ascontiguousarray(desc, dtype=np.uint8), response

    # ----------------------------------------------------------------------------------------
    def _footprint(self, nav: FloatArray, plane_z: float) -> NDArray[np.float32] | None:
        """Ground polygon (4, 2) of the image corners on ``Z = plane_z`` (local, CCW), or None
        (:func:`pipeline.tracking.footprint.ground_footprint`)."""
        xy = ground_footprint(nav, plane_z, self._pinhole)
        if xy is None:
            return None
        if self._origin_xy is None:
            self._origin_xy = nav[:2].copy()
        poly = (xy - self._origin_xy).astype(np.float32)
        if cv2.contourArea(poly, oriented=True) < 0:
            poly = poly[::-1].copy()
        return poly

    def _select_candidates(self, nav: FloatArray, plane_z: float) -> list[_Candidate]:
        """Held images to match, best predicted overlap first (at most ``neighbours``); the
        most recent ones where a footprint is unknown (horizon), or, when no footprint
        overlaps, those whose nadir footprint would (:func:`near_in_plan`): in a sequence an
        attitude far off (an INS glitch, a gimbal still turning) is likelier than a gap, and
        a 45 deg pitch error left an image untied, at its INS."""
        opts = self.options
        new_fp = self._footprint(nav, plane_z)
        overlapping: list[_Candidate] = []
        unknown: set[str] = set()
        new_area = cv2.contourArea(new_fp) if new_fp is not None else 0.0
        for h in self._held:
            fp = self._footprint(h.nav_eop, plane_z) if new_fp is not None else None
            if new_fp is None or fp is None or new_area <= 0:
                unknown.add(h.image_id)
                continue
            area, _ = cv2.intersectConvexConvex(new_fp, fp)
            overlap = float(area) / new_area
            if area > 0.0 and overlap >= opts.min_overlap:
                h.last_overlap_seq = self._seq
                overlapping.append(_Candidate(held=h, overlap=overlap))
        fallback = [_Candidate(held=h, overlap=math.nan)
                    for h in reversed(self._held[-opts.neighbours:])
                    if h.image_id in unknown
                    or (not overlapping and near_in_plan(nav, h.nav_eop, plane_z, self._pinhole))]
        overlapping.sort(key=lambda c: (-c.overlap, -c.held.seq))
        return (overlapping + fallback)[: opts.neighbours]

    # ----------------------------------------------------------------------------------------
    def _match(self, kp: NDArray[np.float32], desc: NDArray[np.uint8],
               candidates: list[_Candidate], nav: FloatArray,
               plane_z: float) -> tuple[dict[int, list[tuple[int, int, float]]],
                                        list[tuple[int, int, int, float]], int, int, int]:
        """Match the new image with each candidate and verify each pair.

        Verification, on the keypoints ``kp`` and the held ones with the lens distortion
        removed (:meth:`geometric_keypoints`): the geometric model (MAGSAC), then, with the
        fundamental matrix and ``max_relief_fraction`` set, the plane gate
        (:meth:`_plane_gate`).

        Returns
        -------
        links : dict
            New-feature index -> list of ``(point number, candidate rank, distance)``.
        unlinked : list
            Verified matches with a feature the candidate did not emit:
            ``(candidate rank, new feature, held feature, distance)`` (late observations).
        matches, inliers, pairs : int
        """
        opts = self.options
        links: dict[int, list[tuple[int, int, float]]] = {}
        unlinked: list[tuple[int, int, int, float]] = []
        n_matches = n_inliers = n_pairs = 0
        if len(kp) < MIN_MODEL_POINTS or not candidates:
            return links, unlinked, 0, 0, 0
        matcher = NewImageMatcher(desc, opts.detector, opts.matcher)
        for rank, cand in enumerate(candidates):
            held = cand.held
            if len(held.kp_work) < MIN_MODEL_POINTS:
                continue
            geo = held.kp_geo if held.kp_geo is not None else held.kp_work
            # ratio test; then one match per new feature (the smallest distance)
            idx_new, idx_old, dist = ratio_matches(*matcher.nearest_two(held.desc), opts.ratio)
            n_matches += len(idx_new)
            if len(idx_new) < opts.min_inliers:
                continue
            mask = self._verify(geo[idx_old], kp[idx_new])
            if mask is None or int(mask.sum()) < opts.min_inliers:
                continue
            if opts.geometry == "fundamental" and opts.max_relief_fraction is not None:
                mask &= self._plane_gate(geo[idx_old], kp[idx_new], mask,
                                         held.nav_eop, nav, plane_z)
                if int(mask.sum()) < opts.min_inliers:
                    continue
            n_pairs += 1
            n_inliers += int(mask.sum())
            for i_new, i_old, d in zip(idx_new[mask].tolist(), idx_old[mask].tolist(),
                                       dist[mask].tolist(), strict=True):
                num = int(held.point_nums[i_old])
                if num >= 0:
                    links.setdefault(i_new, []).append((num, rank, d))
                else:  # a feature the held image did not emit: a late observation, maybe
                    unlinked.append((rank, i_new, i_old, d))
        return links, unlinked, n_matches, n_inliers, n_pairs

    def _plane_gate(self, pts_old: NDArray[np.float32], pts_new: NDArray[np.float32],
                    mask: NDArray[np.bool_], nav_old: FloatArray, nav_new: FloatArray,
                    plane_z: float) -> NDArray[np.bool_]:
        """Matches within the parallax that terrain relief can cause, off the dominant plane.

        The fundamental matrix cannot reject a wrong match that lies along its epipolar line,
        and along a strip the epipolar lines run with the flight direction, the direction of
        crop rows and roads: such matches give tie points metres or hundreds of metres off.
        Seen from two nadir cameras a base ``B`` apart at height ``H`` over the ground, a
        point ``dZ`` off the plane that a homography maps moves by about
        ``f B / H * dZ / H`` pixels; matches farther than that from the pair's dominant-plane
        homography (MAGSAC) are dropped. The gate is
        ``max(PLANE_GATE_MIN_FACTOR * ransac_threshold_px, max_relief_fraction * f B / H)``
        working pixels.
        """
        opts = self.options
        height = max(float(0.5 * (nav_old[2] + nav_new[2])) - plane_z, MIN_HEIGHT_M)
        base = float(np.linalg.norm(nav_new[:3] - nav_old[:3]))
        f_work = self._pinhole.f_px / self.scale_uv[0]
        assert opts.max_relief_fraction is not None
        gate = max(PLANE_GATE_MIN_FACTOR * opts.ransac_threshold_px,
                   opts.max_relief_fraction * f_work * base / height)
        inl = np.flatnonzero(mask)
        try:
            H, _ = cv2.findHomography(pts_old[inl], pts_new[inl], cv2.USAC_MAGSAC, gate,
                                      maxIters=RANSAC_MAX_ITERATIONS,
                                      confidence=RANSAC_CONFIDENCE)
        except cv2.error:
            H = None
        if H is None:
            return np.zeros_like(mask)
        mapped = cv2.perspectiveTransform(pts_old.reshape(1, -1, 2).astype(np.float64), H)[0]
        return np.linalg.norm(mapped - pts_new, axis=1) <= gate

    def _verify(self, pts_old: NDArray[np.float32],
                pts_new: NDArray[np.float32]) -> NDArray[np.bool_] | None:
        """USAC_MAGSAC inlier mask of the pair, or None when no model is found."""
        opts = self.options
        try:
            if opts.geometry == "fundamental":
                model, mask = cv2.findFundamentalMat(
                    pts_old, pts_new, cv2.USAC_MAGSAC, opts.ransac_threshold_px,
                    RANSAC_CONFIDENCE, RANSAC_MAX_ITERATIONS)
            else:
                model, mask = cv2.findHomography(
                    pts_old, pts_new, cv2.USAC_MAGSAC, opts.ransac_threshold_px,
                    maxIters=RANSAC_MAX_ITERATIONS, confidence=RANSAC_CONFIDENCE)
        except cv2.error:  # degenerate sample sets: the pair is rejected
            return None
        if model is None or mask is None:
            return None
        return mask.reshape(-1).astype(bool)

    def _assign(self, n_features: int, links: dict[int, list[tuple[int, int, float]]],
                site: NDArray[np.int64] | None = None) -> tuple[NDArray[np.int64], int, int, int]:
        """Point number of every new feature; counts of new / extended tracks and conflicts.

        ``site``: features at one pixel (:func:`feature_sites`) continue one track at most."""
        conflicts = 0
        # each feature: the track with the most verified matches, then best rank, then distance
        choice: dict[int, tuple[int, float]] = {}  # feature -> (point number, distance)
        for feat, cands in links.items():
            support: dict[int, list[float]] = {}
            for num, rank, dist in cands:
                s = support.setdefault(num, [0, math.inf, math.inf])
                s[0] += 1
                s[1] = min(s[1], rank)
                s[2] = min(s[2], dist)
            if len(support) > 1:
                conflicts += 1
            num = min(support, key=lambda n: (-support[n][0], support[n][1], support[n][2]))
            choice[feat] = (num, support[num][2])
        # each track: at most one feature of this image (the smallest distance), each site
        # (one pixel, several SIFT orientations) at most one track
        owner: dict[int, tuple[int, float]] = {}
        used_sites: set[int] = set()
        for feat, (num, dist) in sorted(choice.items(), key=lambda c: (c[1][1], c[0])):
            at = -1 - feat if site is None else int(site[feat])
            if num in owner or at in used_sites:
                conflicts += 1
                continue
            owner[num] = (feat, dist)
            used_sites.add(at)
        point_nums = np.empty(n_features, dtype=np.int64)
        assigned = np.zeros(n_features, dtype=bool)
        n_new = n_ext = 0
        for num, (feat, _) in owner.items():
            point_nums[feat] = num
            assigned[feat] = True
            track = self._tracks[num]
            if track[0] == 1:
                n_new += 1
            else:
                n_ext += 1
            track[0] += 1
            track[1] += 1
        point_nums[~assigned] = -1  # numbered by add_image if emitted
        return point_nums, n_new, n_ext, conflicts

    def _emitted(self, kp: NDArray[np.float32], response: FloatArray,
                 point_nums: NDArray[np.int64],
                 site: NDArray[np.int64] | None = None,
                 prefer: NDArray[np.int64] | None = None) -> NDArray[np.int64]:
        """Indices of the features that become observations (``emit_per_image``).

        Continuations of tracks first (all of them), then the ``prefer`` features (matched
        to features held images did not emit: late observations, in the order given), then
        the strongest new feature of each grid cell in turn, cells visited in order of
        their strongest feature; within the budget. One observation per ``site``
        (:func:`feature_sites`): the strongest of its features.
        """
        opts = self.options
        linked = np.flatnonzero(point_nums >= 0)
        if prefer is not None and prefer.size:
            sites = site if site is not None else np.arange(point_nums.size)
            taken = set(sites[linked].tolist())
            first: list[int] = []
            for f in prefer.tolist():
                if sites[f] not in taken:
                    taken.add(int(sites[f]))
                    first.append(f)
            budget = (len(first) if opts.emit_per_image is None
                      else max(0, opts.emit_per_image - linked.size))
            linked = np.sort(np.concatenate([linked, np.asarray(first[:budget],
                                                                dtype=np.int64)]))
        new = np.setdiff1d(np.flatnonzero(point_nums < 0), linked)
        if site is not None and new.size:
            free = ~np.isin(site[new], site[linked])  # a continued site emits nothing new
            new = new[free]
            strongest = np.lexsort((-response[new], site[new]))  # by site, strongest first
            first = np.r_[True, site[new][strongest][1:] != site[new][strongest][:-1]]
            new = np.sort(new[strongest[first]])
        if opts.emit_per_image is None:
            return np.sort(np.concatenate([linked, new]))
        budget = max(0, opts.emit_per_image - linked.size)
        if budget == 0 or new.size == 0:
            return linked
        cols, rows = opts.emit_grid
        w, h = self.working_size_px
        cx = np.clip((kp[new, 0] * cols / w).astype(np.int64), 0, cols - 1)
        cy = np.clip((kp[new, 1] * rows / h).astype(np.int64), 0, rows - 1)
        cell = cy * cols + cx
        order = np.lexsort((-response[new], cell))  # by cell, strongest first within a cell
        sorted_cell = cell[order]
        first = np.searchsorted(sorted_cell, sorted_cell, side="left")
        rank_in_cell = np.arange(order.size) - first
        # round robin: all cells' best, then all cells' second best, ... (ties: stronger first)
        pick = np.lexsort((-response[new][order], rank_in_cell))[:budget]
        return np.sort(np.concatenate([linked, new[order[pick]]]))

    def _prune(self) -> None:
        """Drop stale images, then the least recently overlapped beyond ``max_held_images``."""
        opts = self.options
        newest = self._seq - 1
        keep = [h for h in self._held
                if newest - h.last_overlap_seq < opts.stale_after_images]
        if len(keep) > opts.max_held_images:
            by_use = sorted(keep, key=lambda h: (h.last_overlap_seq, h.seq))
            dropped = {id(h) for h in by_use[: len(keep) - opts.max_held_images]}
            keep = [h for h in keep if id(h) not in dropped]
        kept = {id(h) for h in keep}
        for h in self._held:
            if id(h) not in kept:
                self._release(h)
        self._held = keep

    def _release(self, held: HeldImage) -> None:
        for num in np.unique(held.point_nums[held.point_nums >= 0]).tolist():
            track = self._tracks[num]
            track[1] -= 1
            if track[1] == 0:
                del self._tracks[num]


def _point_id(num: int) -> str:
    """Track id of point number ``num`` (``t0000001``)."""
    return f"t{num:0{POINT_ID_DIGITS}d}"


def read_gray_image(path: Path | str, decode_factor: int = 1) -> NDArray[np.uint8]:
    """Read a JPEG (or any OpenCV image) as gray, optionally with a reduced JPEG decode.

    Parameters
    ----------
    path : Path or str
    decode_factor : {1, 2, 4, 8}
        :attr:`Tracker.decode_factor`: the libjpeg scaled decode skips most of the IDCT and
        the downscale of the full image (decode + working copy of a 3600 x 2700 JPEG: 43
        instead of 57 ms at 1000 px, 38 instead of 55 ms at 800 px).

    Returns
    -------
    (H / f, W / f) uint8

    Raises
    ------
    InputDataError
        The file cannot be read or decoded.
    """
    if decode_factor not in REDUCED_GRAY_FLAGS:
        raise ValueError(f"decode_factor must be one of {sorted(REDUCED_GRAY_FLAGS)}, "
                         f"got {decode_factor!r}")
    name = Path(path).name
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise InputDataError(f"{name}: cannot read: {err.strerror or err}") from err
    problem = jpeg_scan_problem(data)
    if problem is not None:
        raise InputDataError(f"{name}: {problem}")
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), REDUCED_GRAY_FLAGS[decode_factor])
    if image is None or image.ndim != 2 or image.size == 0:
        raise InputDataError(f"{name}: cannot decode the image (corrupt image data)")
    return np.asarray(image, dtype=np.uint8)
