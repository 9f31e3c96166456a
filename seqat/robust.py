"""Robust weighting of image points: a least-squares core with a Cauchy tail, by iteratively
re-weighted least squares (IRLS).

One wrong tie point (a repeated texture matched to the wrong field corner) must not move the
solution (docs/algorithm.md, *Robust loss (default)*). Each image point's squared normalised
residual ``u² = |v|² / σ²`` (both coordinates) enters the cost through

    ρ(u²) = u²                              for u² ≤ k²,
    ρ(u²) = k² + k² ln(1 + (u² − k²) / k²)   beyond,

with ``k`` the scale in σ (``robust_scale``; the options' default :data:`ROBUST_SCALE` = 3;
None is least squares, the paper's estimator). The IRLS weight is ``ρ'(u²)``: 1
for every point within ``k`` σ (98.9 % of Gaussian 2D errors: clean data are adjusted by
least squares, unchanged), then ``k² / u²``-like: a point 40σ off keeps 0.6 % of its weight
and pulls on the solution by less than ``k`` σ. Sim re-weights every Gauss-Newton iteration;
Seq-F / Seq-R weight each new image's rows in every update iteration (the first one least
squares: its start values may be 20° off) and the window re-linearisation keeps those
weights. Why it is the default: docs/algorithm.md.

The GPS/INS prior of each image is two groups, position and attitude (3 DoF each, diagonal
σ). Each group's squared Mahalanobis norm ``u² = Σ (r / σ)²`` (``r = nav − estimate``)
enters through the same ρ with the core scaled by the group's degrees of freedom ``d``,
``k² d`` (``nav_robust_scale`` = ``k``, default :data:`NAV_ROBUST_SCALE` = 3: a group is
least squares within ``u² <= 27``, χ²₃ beyond it has probability 6e-6): a 5 m GNSS jump at
σ = 0.3 m (``u² ≈ 280``) keeps ~10 % of its weight and pulls like a 1.6σ residual instead of
a 17σ one. Sim turns it on once Gauss-Newton has converged with least-squares GPS/INS (the
priors carry the datum: a bad start must not down-weight them); a sequential update once
its rows have converged with the image loss alone, one group at a time (position first);
finish() re-weights the window's GPS/INS rows until they settle (Seq-F == Sim). Data
snooping still tests the groups when on (docs/algorithm.md, *Robust loss*).
"""

from __future__ import annotations

import math

import numpy as np

from seqat.types import FloatArray, PinholeCamera

#: Default robust scale (sigmas) of SimOptions and SequentialOptions.
ROBUST_SCALE = 3.0
#: Default robust scale of the GPS/INS groups (sigmas per degree of freedom).
NAV_ROBUST_SCALE = 3.0
#: The GPS/INS groups of an image: name and components of its 6-vector.
NAV_GROUPS = (("position", slice(0, 3)), ("attitude", slice(3, 6)))
#: A group whose weight factor is below this is reported as down-weighted (run.json).
NAV_REPORT_WEIGHT = 0.9
#: A tie point is published only while at least this many of its rays lie within the loss's
#: core at the final estimate (:func:`disagreeing_points`).
MIN_AGREEING_RAYS = 2
#: Times Sim and the finished Seq-R adjust again without the tie points whose rays disagree
#: or fit two places as well (:func:`uninformative_points`).
MAX_AMBIGUOUS_ROUNDS = 3
#: ... a ray counts as left out by another answer only this many times the core's radius
#: beyond it there: three noisy rays near the core's edge are one answer.
CLEARLY_BEYOND = 2.0
#: An image's ray counts against its estimate (:func:`unsupported_images`) this many times
#: the core's radius beyond it: a poor start leaves its rays hundreds of sigmas off, wrong
#: matches among good ones pull an image only a few sigmas off its rays.
POOR_START_BEYOND = 10.0
#: ... and an image is judged so on this many rays at least: fewer cannot tell a poor start
#: from a wrong match or two (Seneca's own tie points with a fifth of them moved 10-100 px:
#: images judged on one to five rays to known points were rejected and carried by their INS
#: alone, 34 deg off; docs/algorithm.md, *A poor start*).
MIN_JUDGED_RAYS = 6
#: A tie point whose rays spread less than this (degrees, the largest angle between them at
#: the final EOPs) is not published (:func:`narrow_points`): COLMAP filters its points at
#: 1.5 degrees after bundle adjustment; no point is born under 1 degree during the flight
#: (seqat.births.MIN_FORCED_RAY_ANGLE_DEG).
MIN_PUBLISHED_RAY_ANGLE_DEG = 1.0
#: A flight whose tie points of three rays or more have more than this fraction of their
#: rays clearly beyond the core (:func:`contamination`) trusts none of its two-ray tie points
#: (:func:`untrusted_two_ray_points`).
MAX_CONTAMINATION = 0.10
#: ... but for those of an image with fewer rays than this in points of three rays or more:
#: the two-ray points are most of its ties (a light UAV's flight, two rays per track).
MIN_IMAGE_TIES = 12
#: A tie point whose rays may fit two places (:func:`ambiguous_points`) is not tested with
#: more rays than this (their pairs grow as n²; a wrong pair against many good rays is no
#: match).
MAX_AMBIGUOUS_RAYS = 12
#: Above :data:`MAX_CONTAMINATION` the image points' loss narrows its core to this many σ
#: (when the configured one is wider; :func:`scale_in_force`): with a fifth of the rays
#: wrong matches, those 3-6 σ off enter near full weight and pull the estimate (the rendered
#: block at 20 % blunders, seed 8: EOPs 1.61 times the oracle's RMSE at 3 σ, 1.16 at 2 σ);
#: on clean rays a 2 σ core still weighs 86 % of them fully (docs/algorithm.md, *The loss
#: of a contaminated flight*).
CONTAMINATED_SCALE = 2.0


def check_scale(name: str, value: float | None) -> None:
    """A robust scale option: a positive number or None (off); else :class:`ConfigError`."""
    from seqat.errors import ConfigError

    if value is not None and not (isinstance(value, int | float) and value > 0
                                  and np.isfinite(value)):
        raise ConfigError(f"{name}: expected a positive number (sigmas) or null, "
                          f"got {value!r}")


def ray_u2(res_px: FloatArray, sigma_px: FloatArray) -> FloatArray:
    """Squared normalised residual ``|v|² / σ²`` of each image point (k,), both coordinates."""
    res = np.asarray(res_px, dtype=np.float64).reshape(-1, 2)
    return np.sum(res**2, axis=1) / np.asarray(sigma_px, dtype=np.float64).reshape(-1) ** 2


def unsupported_images(u2: FloatArray, image: np.ndarray, scale: float | None,
                       beyond: float = POOR_START_BEYOND) -> np.ndarray:
    """Images (the distinct values of ``image``, sorted) most of whose rays lie far beyond
    the loss's core (``u > beyond scale``, :data:`POOR_START_BEYOND` unless said) at the
    estimate: an estimate its own image points reject.

    The redescending loss keeps such an estimate near a poor start (an INS tens of degrees
    off: every ray is then hundreds of sigmas off and all are down-weighted) instead of where
    the rays put the image (docs/algorithm.md, *A poor start*). Far beyond, not just beyond:
    an image among many wrong matches may be a few sigmas off most of its rays and still
    better than its GPS/INS. An image with fewer than :data:`MIN_JUDGED_RAYS` rays is not
    judged. Without a loss: none.
    """
    image = np.asarray(image, dtype=np.int64).reshape(-1)
    if scale is None or image.size == 0:
        return np.zeros(0, dtype=np.int64)
    ids, pos = np.unique(image, return_inverse=True)
    rays = np.bincount(pos, minlength=ids.size)
    inside = np.bincount(pos, weights=np.asarray(u2).reshape(-1)
                         <= (beyond * scale) ** 2, minlength=ids.size)
    return ids[(2 * inside < rays) & (rays >= MIN_JUDGED_RAYS)]


def robust_weight(u2: FloatArray, scale: float | None) -> FloatArray:
    """``ρ'(u²)`` of squared normalised residuals ``u2`` (k,): the IRLS weight factor."""
    u2 = np.asarray(u2, dtype=np.float64)
    if scale is None:
        return np.ones(u2.size)
    k2 = scale**2
    return 1.0 / (1.0 + np.maximum(u2 - k2, 0.0) / k2)


def core_u2(scale: float, sigma0: float = 1.0) -> float:
    """The loss's core as a bound on a ray's ``u²``: ``k²``, widened to ``k² σ0²`` by an a
    posteriori σ0 above 1 (image points whose σ was set too small)."""
    return scale**2 * max(1.0, sigma0 if np.isfinite(sigma0) else 1.0) ** 2


def disagreeing_points(u2: FloatArray, point: np.ndarray, scale: float | None,
                       sigma0: float = 1.0) -> np.ndarray:
    """The points (sorted, unique values of ``point``) with fewer than
    :data:`MIN_AGREEING_RAYS` rays within the loss's core (``u² <= k²``), from each ray's
    squared normalised residual ``u2`` and its point ``point`` (k,); none without a scale.
    An a posteriori ``sigma0`` above 1 widens the core by that factor: image points whose
    σ was set too small must not lose every two-ray point.

    Two rays, one of them a wrong match, meet where neither is right: the loss cannot tell
    which ray is wrong and leaves both beyond the core (each with half the mismatch across
    the epipolar line), the point metres off along it. The data do not determine such a
    point: the estimators keep it in the adjustment with the weights the loss gives its
    rays but do not publish it (docs/algorithm.md, *Points whose rays disagree*)."""
    point = np.asarray(point, dtype=np.int64)
    if scale is None or point.size == 0:
        return np.zeros(0, dtype=np.int64)
    pts, pos = np.unique(point, return_inverse=True)
    core = core_u2(scale, sigma0)
    inside = np.bincount(pos, weights=np.asarray(u2) <= core, minlength=pts.size)
    return pts[inside < MIN_AGREEING_RAYS]


def ambiguous_points(u2: FloatArray, point: np.ndarray, eop: FloatArray, uv_px: FloatArray,
                     sigma_px: FloatArray, camera: PinholeCamera, scale: float | None,
                     sigma0: float = 1.0) -> np.ndarray:
    """The points (sorted) whose rays fit two places equally well.

    Every pair of a point's rays is intersected and every ray of the point tested there:
    the rays within the loss's core form that place's consensus. The point is ambiguous
    when two of its largest consensuses are different answers: they share at most one ray,
    and each leaves a ray of the other clearly beyond the core (:data:`CLEARLY_BEYOND`
    times its radius; rays near the core's edge decide nothing). Three rays, one of them a
    wrong match lying along the epipolar line of a good one, are such a point: the two
    good rays meet at one place, the wrong one and the good one it lies along at another.
    The loss keeps one pair and down-weights the third ray, and which pair it keeps
    depends on where the adjustment started: the estimators adjust again without such a
    point and do not publish it (docs/algorithm.md, *Points whose rays fit two places*).
    A larger consensus wins: three good rays against a wrong pair are not ambiguous.

    The test reads the EOPs only, not the point's estimate (which the loss's choice
    moved), so that two estimators a few millimetres apart find the same points. Only
    points of three rays or more (at most :data:`MAX_AMBIGUOUS_RAYS`) with a ray beyond the
    core at the estimate are looked at (clean data: next to none).

    Parameters
    ----------
    u2 : (k,) float
        Each ray's squared normalised residual at the estimate (selects the points tested).
    point : (k,) int
        Each ray's point.
    eop : (k, 6) float
        The EOP of each ray's image at the estimate.
    uv_px, sigma_px : (k, 2), (k,) float
        Each ray's image point and its σ.
    camera : PinholeCamera
    scale, sigma0
        The loss's scale (None: no core, nothing is ambiguous) and the a posteriori σ0 that
        widens the core (as in :func:`disagreeing_points`).
    """
    pts, answers = _pair_consensus(u2, point, eop, uv_px, sigma_px, camera, scale, sigma0)
    return pts[np.asarray([c for c, a in answers.items() if _two_places(a)], dtype=np.int64)]


def wrong_pair_points(u2: FloatArray, point: np.ndarray, eop: FloatArray, uv_px: FloatArray,
                  sigma_px: FloatArray, camera: PinholeCamera, scale: float | None,
                  sigma0: float = 1.0) -> np.ndarray:
    """The points (sorted) whose estimate is not where most of their rays meet: a pair of
    their rays meets at a place whose consensus (:func:`ambiguous_points`) holds more rays
    than the estimate's core does, and a ray of that consensus is clearly beyond the core
    (:data:`CLEARLY_BEYOND`) at the estimate. A point born on a wrong match and a good ray
    (the two meet exactly when the wrong one lies along the epipolar line) stays there
    under the redescending loss when the later good rays arrive: they are down-weighted
    instead (the rendered flight at 20 % blunders: 4 rays, 2 of them beyond the core, the
    point 10.7 m off). The estimators do not publish it. Arguments as
    :func:`ambiguous_points`."""
    pts, answers = _pair_consensus(u2, point, eop, uv_px, sigma_px, camera, scale, sigma0)
    return pts[np.asarray([c for c, a in answers.items() if _elsewhere(a)], dtype=np.int64)]


#: A tested point's largest consensus (:func:`_pair_consensus`): its distinct answers as
#: ``(within, beyond)`` bit sets of the point's rays, its size, and the rays within the core
#: and clearly beyond it at the estimate (bit sets).
_Consensus = tuple[set[tuple[int, int]], int, int, int]


def _two_places(answer: _Consensus) -> bool:
    """Two of the largest consensuses are different answers (:func:`ambiguous_points`)."""
    sets = answer[0]
    return any(bin(w1 & w2).count("1") <= 1 and w1 & o2 and w2 & o1
               for w1, o1 in sets for w2, o2 in sets)


def _elsewhere(answer: _Consensus) -> bool:
    """The largest consensus holds more rays than the estimate's core, one of them clearly
    beyond it at the estimate (:func:`wrong_pair_points`)."""
    sets, size, inside, beyond = answer
    return size > bin(inside).count("1") and any(w & beyond for w, _ in sets)


def _pair_consensus(u2: FloatArray, point: np.ndarray, eop: FloatArray, uv_px: FloatArray,
                    sigma_px: FloatArray, camera: PinholeCamera, scale: float | None,
                    sigma0: float) -> tuple[np.ndarray, dict[int, _Consensus]]:
    """The largest consensuses of the points :func:`ambiguous_points` tests: the distinct
    values of ``point`` (sorted) and, for each tested one (its position there), the distinct
    answers of its largest consensus as ``(within, beyond)`` bit sets of its rays (in the
    order of ``point``), that consensus's size, and the rays within the core and clearly
    beyond it at the estimate (from ``u2``), as bit sets."""
    from seqat.geometry import depth, intersect_rays, project

    point = np.asarray(point, dtype=np.int64)
    if scale is None or point.size == 0:
        return np.zeros(0, dtype=np.int64), {}
    u2 = np.asarray(u2, dtype=np.float64)
    core = core_u2(scale, sigma0)
    clear = CLEARLY_BEYOND**2 * core
    pts, pos = np.unique(point, return_inverse=True)
    count = np.bincount(pos, minlength=pts.size)
    out = np.bincount(pos, weights=u2 > core, minlength=pts.size)
    cand = np.flatnonzero((count >= 3) & (count <= MAX_AMBIGUOUS_RAYS) & (out > 0))
    if not cand.size:
        return pts, {}
    order = np.argsort(pos, kind="stable")
    start = np.cumsum(count) - count
    # every pair of rays of each candidate (ray indices), and the point's rays for each pair
    pa, pb, pp = [], [], []
    for c in cand:
        i, j = np.triu_indices(int(count[c]), 1)
        pa.append(order[start[c] + i])
        pb.append(order[start[c] + j])
        pp.append(np.full(i.size, c))
    a, b, pair_pt = (np.concatenate(v) for v in (pa, pb, pp))
    m = a.size
    eop = np.asarray(eop, dtype=np.float64).reshape(-1, 6)
    uv_px = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    sigma_px = np.asarray(sigma_px, dtype=np.float64).reshape(-1)
    ends = np.concatenate([a, b])
    X, _ = intersect_rays(eop[ends], uv_px[ends], np.tile(np.arange(m), 2), m, camera)
    ok = np.all(np.isfinite(X), axis=1)
    X = np.nan_to_num(X)
    ok &= np.all((depth(eop[ends], np.tile(X, (2, 1))) > 0).reshape(2, m), axis=0)
    lens = count[pair_pt]
    local = np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
    rays = order[np.repeat(start[pair_pt], lens) + local]
    pair_of = np.repeat(np.arange(m), lens)
    u2_at = ray_u2(uv_px[rays] - project(eop[rays], X[pair_of], camera), sigma_px[rays])
    front = depth(eop[rays], X[pair_of]) > 0
    bit = np.left_shift(np.int64(1), local)
    within = np.bincount(pair_of, weights=np.where((u2_at <= core) & front, bit, 0),
                         minlength=m).astype(np.int64)  # each pair's consensus, as bits
    beyond = np.bincount(pair_of, weights=np.where((u2_at > clear) | ~front, bit, 0),
                         minlength=m).astype(np.int64)
    size = np.bincount(pair_of, weights=(u2_at <= core) & front, minlength=m)
    # the estimate's core and clearly-beyond rays, as bits in the same order
    rank = np.empty(point.size, dtype=np.int64)
    rank[order] = np.arange(point.size)
    tested = count[pos] <= MAX_AMBIGUOUS_RAYS  # the others' bits are not read (nor shifted)
    ray_bit = np.left_shift(np.int64(1), np.where(tested, rank - start[pos], 0))
    est_in = np.bincount(pos, weights=np.where(u2 <= core, ray_bit, 0),
                         minlength=pts.size).astype(np.int64)
    est_out = np.bincount(pos, weights=np.where(u2 > clear, ray_bit, 0),
                          minlength=pts.size).astype(np.int64)
    answers: dict[int, _Consensus] = {}
    for c in np.unique(pair_pt[ok]):
        mine = np.flatnonzero(ok & (pair_pt == c))
        best = mine[size[mine] == size[mine].max()]
        answers[int(c)] = ({(int(within[q]), int(beyond[q])) for q in best},  # distinct
                           int(size[best[0]]), int(est_in[c]), int(est_out[c]))
    return pts, answers


def narrow_points(point: np.ndarray, eop: FloatArray, uv_px: FloatArray,
                  camera: PinholeCamera) -> np.ndarray:
    """The points (sorted, distinct values of ``point``) whose rays, cast from the EOPs
    ``eop`` (k, 6) through the image points ``uv_px`` (k, 2), spread less than
    :data:`MIN_PUBLISHED_RAY_ANGLE_DEG`: nearly parallel rays fix the point's depth by next
    to nothing, and a wrong match along the epipolar line of a good ray sends it kilometres
    off with a consistent fit (the rendered flight at 20 % blunders: two rays 0.8 degrees
    apart, the point 1.9 km below the ground, σ_z 330 m). The estimators do not publish it
    (docs/algorithm.md, *Points whose rays barely spread*)."""
    from seqat.geometry import intersect_rays

    point = np.asarray(point, dtype=np.int64)
    if point.size == 0:
        return np.zeros(0, dtype=np.int64)
    pts, pos = np.unique(point, return_inverse=True)
    _, spread = intersect_rays(np.asarray(eop, dtype=np.float64).reshape(-1, 6), uv_px, pos,
                               pts.size, camera)
    return pts[spread < np.radians(MIN_PUBLISHED_RAY_ANGLE_DEG)]


def uninformative_points(u2: FloatArray, point: np.ndarray, eop: FloatArray, uv_px: FloatArray,
                         sigma_px: FloatArray, camera: PinholeCamera, scale: float | None,
                         sigma0: float = 1.0) -> np.ndarray:
    """The points (sorted) Sim and the finished Seq-R adjust again without: their rays
    disagree (:func:`disagreeing_points`) or fit another place as well
    (:func:`ambiguous_points`); the arguments are :func:`ambiguous_points`'s.

    Neither carries information on the images, and where the redescending loss leaves
    either depends on the start: a point of two rays, one a wrong match, is cheapest on
    either ray with the whole mismatch on the other (two minima), so that Sim and Seq-R,
    each in one of them, stood 37 mm and 0.028° r.m.s. apart on a subset of the real flight
    (docs/algorithm.md, *Points whose rays disagree*)."""
    return np.union1d(disagreeing_points(u2, point, scale, sigma0),
                      ambiguous_points(u2, point, eop, uv_px, sigma_px, camera, scale, sigma0))


def withheld_points(u2: FloatArray, point: np.ndarray, eop: FloatArray, uv_px: FloatArray,
                    sigma_px: FloatArray, camera: PinholeCamera, scale: float | None,
                    sigma0: float = 1.0) -> np.ndarray:
    """The points (sorted) the estimators do not publish: their rays disagree
    (:func:`disagreeing_points`), fit another place as well (:func:`ambiguous_points`) or
    better (:func:`wrong_pair_points`); the arguments are :func:`ambiguous_points`'s."""
    pts, answers = _pair_consensus(u2, point, eop, uv_px, sigma_px, camera, scale, sigma0)
    off = [c for c, a in answers.items() if _two_places(a) or _elsewhere(a)]
    return np.union1d(disagreeing_points(u2, point, scale, sigma0),
                      pts[np.asarray(off, dtype=np.int64)])


def contamination(u2: FloatArray, point: np.ndarray, scale: float | None,
                  sigma0: float = 1.0) -> float:
    """The fraction of the rays of points with three rays or more that lie clearly beyond
    the loss's core (:data:`CLEARLY_BEYOND`; ``u2`` and ``point`` as in
    :func:`disagreeing_points`): the wrong matches a ray test can see. NaN without a scale
    or without such points."""
    point = np.asarray(point, dtype=np.int64)
    if scale is None or point.size == 0:
        return math.nan
    _, pos, count = np.unique(point, return_inverse=True, return_counts=True)
    seen = count[pos] >= 3
    if not seen.any():
        return math.nan
    clear = CLEARLY_BEYOND**2 * core_u2(scale, sigma0)
    return float(np.count_nonzero(np.asarray(u2)[seen] > clear) / np.count_nonzero(seen))


def untrusted_two_ray_points(u2: FloatArray, point: np.ndarray, image: np.ndarray,
                             scale: float | None,
                             sigma0: float = 1.0) -> tuple[np.ndarray, float]:
    """The two-ray points (sorted distinct values of ``point`` with exactly two rays) the
    estimators leave out of their final adjustment, and the :func:`contamination` that
    decides it: when it exceeds :data:`MAX_CONTAMINATION`, all of them but those with a
    ray in an image (``image``, each ray's) that has fewer than :data:`MIN_IMAGE_TIES`
    rays in points of three rays or more; else none.

    A wrong match lying along the epipolar line of a two-ray point fits both rays (a wrong
    depth), and one whose component across the line is under the core enters at full
    weight as a 2-3 σ error of the relative orientation: no test on two rays sees either.
    How many such points a flight holds grows with its wrong matches, which the points of
    three rays or more measure. On the rendered 12-image block at 20 % blunders (21 % of
    those rays clearly beyond) the two-ray points made the EOPs up to 2.9 times the
    oracle's RMSE, without them 1.2 (docs/algorithm.md, *Two-ray points of a contaminated
    flight*)."""
    point = np.asarray(point, dtype=np.int64)
    eps = contamination(u2, point, scale, sigma0)
    if not eps > MAX_CONTAMINATION:
        return np.zeros(0, dtype=np.int64), eps
    pts, pos, count = np.unique(point, return_inverse=True, return_counts=True)
    ids, img = np.unique(np.asarray(image, dtype=np.int64), return_inverse=True)
    ties = np.bincount(img, weights=count[pos] >= 3, minlength=ids.size)
    weak = np.zeros(pts.size, dtype=bool)
    np.logical_or.at(weak, pos, ties[img] < MIN_IMAGE_TIES)
    return pts[(count == 2) & ~weak], eps


def scale_in_force(scale: float | None, eps: float) -> float | None:
    """The image points' robust scale the estimators adjust with at the contamination
    ``eps`` (:func:`contamination`): the configured ``scale``, narrowed to
    :data:`CONTAMINATED_SCALE` above :data:`MAX_CONTAMINATION` (NaN: not judged)."""
    if scale is None or not eps > MAX_CONTAMINATION:
        return scale
    return min(scale, CONTAMINATED_SCALE)


def robust_rho(u2: FloatArray, scale: float | None) -> FloatArray:
    """``ρ(u²)`` of each squared normalised residual ``u2`` (``u²`` without a scale)."""
    u2 = np.asarray(u2, dtype=np.float64)
    if scale is None:
        return u2.copy()
    k2 = scale**2
    return np.where(u2 > k2, k2 + k2 * np.log1p(np.maximum(u2 - k2, 0.0) / k2), u2)


def robust_cost(u2: FloatArray, scale: float | None) -> float:
    """``Σ ρ(u²)`` of squared normalised residuals ``u2`` (``Σ u²`` without a scale)."""
    return float(np.sum(robust_rho(u2, scale)))


def cauchy_weight(res_px: FloatArray, sigma_px: FloatArray, scale: float | None) -> FloatArray:
    """IRLS weight factor in (0, 1] of each image point (k,) from its residual (k, 2)."""
    return robust_weight(ray_u2(res_px, sigma_px), scale)


def cauchy_cost(res_px: FloatArray, sigma_px: FloatArray, scale: float | None) -> float:
    """``Σ ρ(u²)`` of the image points (``Σ u²`` without a scale: least squares)."""
    return robust_cost(ray_u2(res_px, sigma_px), scale)


def nav_dof() -> np.ndarray:
    """Degrees of freedom of each :data:`NAV_GROUPS` group."""
    return np.array([sl.stop - sl.start for _, sl in NAV_GROUPS])


#: Each group's degrees of freedom, its first component, and each component's group.
_NAV_DOF = nav_dof().astype(np.float64)
_NAV_STARTS = np.array([sl.start for _, sl in NAV_GROUPS])
_NAV_GROUP_OF = np.repeat(np.arange(len(NAV_GROUPS)), nav_dof())


def nav_u2(res: FloatArray, sigma: FloatArray) -> FloatArray:
    """Squared Mahalanobis norm of each image's GPS/INS groups (:data:`NAV_GROUPS`), (n, g),
    from residuals ``res`` and sigmas ``sigma`` (n, 6; diagonal covariance)."""
    z2 = (np.asarray(res, dtype=np.float64).reshape(-1, 6)
          / np.asarray(sigma, dtype=np.float64).reshape(-1, 6)) ** 2
    return np.add.reduceat(z2, _NAV_STARTS, axis=1)  # each group summed in order


def nav_group_weight(u2: FloatArray, scale: float | None, dof: int = 3) -> FloatArray:
    """``ρ'`` of groups with ``dof`` degrees of freedom and squared norms ``u2``: 1 within
    ``u² <= k² dof``, ``k² dof / u²``-like beyond; all ones without a scale."""
    u2 = np.asarray(u2, dtype=np.float64)
    if scale is None:
        return np.ones(u2.shape)
    return robust_weight(u2.ravel() / dof, scale).reshape(u2.shape)


def nav_components(group_weights: FloatArray) -> FloatArray:
    """Group weights (n, g) as weights of the 6 GPS/INS components (n, 6)."""
    wg = np.asarray(group_weights, dtype=np.float64).reshape(-1, len(NAV_GROUPS))
    return wg[:, _NAV_GROUP_OF]


def nav_groups_of(component_weights: FloatArray) -> FloatArray:
    """Component weights (n, 6) as group weights (n, g) (each group's first component)."""
    w = np.asarray(component_weights, dtype=np.float64).reshape(-1, 6)
    return w[:, [sl.start for _, sl in NAV_GROUPS]]


def nav_weight(res: FloatArray, sigma: FloatArray, scale: float | None,
               on: np.ndarray | None = None) -> FloatArray:
    """IRLS weight factor of every GPS/INS component (n, 6): its group's, in (0, 1]
    (``on``: (g,) bool, the groups the loss applies to; default all)."""
    u2 = nav_u2(res, sigma)
    if scale is None:
        return np.ones((u2.shape[0], 6))
    wg = robust_weight(u2 / _NAV_DOF, scale).reshape(u2.shape)  # each group's own dof
    return nav_components(wg if on is None else np.where(on, wg, 1.0))


def nav_tail_curvature(res: FloatArray, sigma: FloatArray, scale: float | None) -> FloatArray:
    """(n, 6, 6): what IRLS leaves out of the GPS/INS groups' curvature, as the normal
    matrix holds it (half the Hessian of :func:`nav_cost`): ``(2 ρ''(s) / d) a aᵀ`` per
    group beyond the loss's core, ``s = u² / d``, ``a = r / σ²`` its components, zero
    within the core and without a scale.

    In the tail ``ρ'' = -k² / s²``: the group's cost is concave along its residual (the
    curvature there is ``-ρ'`` where IRLS takes ``+ρ'``), so Gauss-Newton on IRLS weights
    moves a GNSS fault's image toward its rays by a constant fraction per iteration
    (``2 ρ' / (K + ρ')``, ``K`` the rays' stiffness). Added to the normal matrix, the
    step is Newton's on the groups' loss (:func:`seqat.adjustment.adjust_block`)."""
    r = np.asarray(res, dtype=np.float64).reshape(-1, 6)
    sig = np.asarray(sigma, dtype=np.float64).reshape(-1, 6)
    out = np.zeros((r.shape[0], 6, 6))
    if scale is None:
        return out
    k2 = scale**2
    a = r / sig**2
    u2 = nav_u2(r, sig)
    for g, (_, sl) in enumerate(NAV_GROUPS):
        d = sl.stop - sl.start
        s = u2[:, g] / d
        coef = np.where(s > k2, -2.0 * k2 / (np.maximum(s, k2) ** 2 * d), 0.0)
        ag = a[:, sl]
        out[:, sl, sl] = coef[:, None, None] * ag[:, :, None] * ag[:, None, :]
    return out


def nav_cost(res: FloatArray, sigma: FloatArray, scale: float | None) -> float:
    """``Σ d ρ(u² / d)`` of the GPS/INS groups (``Σ (r / σ)²`` without a scale)."""
    u2 = nav_u2(res, sigma)
    if scale is None:
        return float(np.sum(u2))
    return float(sum(d * robust_cost(u2[:, g] / d, scale) for g, d in enumerate(nav_dof())))


def nav_outside(res: FloatArray, sigma: FloatArray, scale: float | None) -> np.ndarray:
    """(n, g) bool: the GPS/INS groups beyond the loss's least-squares core (none without
    a scale)."""
    u2 = nav_u2(res, sigma)
    return np.zeros(u2.shape, dtype=bool) if scale is None else u2 > nav_dof() * scale**2


#: An image with this many rays to known points within the loss's core (most of its rays
#: to them) is placed by its rays, whatever its GPS/INS says (RowBuilder.rays_hold; a start
#: within POOR_START_BEYOND of it, RestartMixin._rays_hold). Six: a resection's redundancy
#: of six, the tracker's own minimum for one (pipeline/run/resection.py); at 8 an image of
#: a sparse strip resected on seven rays within 2.3 sigma was carried by an INS 90 deg off.
RAYS_OVER_NAV = 6


def rays_hold(u2: FloatArray, scale: float | None, beyond: float = 1.0) -> bool:
    """At least :data:`RAYS_OVER_NAV` of an image's rays (their squared normalised residuals
    ``u2``) lie within ``beyond`` times the loss's core, and they are most of them: the rays
    fix the image (a resection), whatever its GPS/INS says. Never without a loss."""
    u2 = np.asarray(u2, dtype=np.float64).reshape(-1)
    if scale is None:
        return False
    inside = int(np.count_nonzero(u2 <= (beyond * scale) ** 2))
    return inside >= RAYS_OVER_NAV and 2 * inside > u2.size


def nav_far_beyond(res: FloatArray, sigma: FloatArray, scale: float | None) -> np.ndarray:
    """(n, g) bool: the GPS/INS groups :data:`POOR_START_BEYOND` times the core's radius
    beyond it (none without a scale): no GNSS jump for the loss to weigh but a GPS/INS that
    is wrong (an INS 45 deg off with a sigma of 0.1 deg is 450 sigma off)."""
    u2 = nav_u2(res, sigma)
    if scale is None:
        return np.zeros(u2.shape, dtype=bool)
    return u2 > nav_dof() * (POOR_START_BEYOND * scale) ** 2


def nav_within_core(res: FloatArray, sigma: FloatArray, scale: float | None) -> bool:
    """Every GPS/INS group within the loss's least-squares core (weight 1): the
    least-squares solution is the robust one."""
    return not nav_outside(res, sigma, scale).any()


def nav_report(image_ids: list[str] | tuple[str, ...],
               weights: FloatArray) -> list[tuple[str, str, float]]:
    """``(image id, group, weight)`` of the groups (weights (n, 2)) below
    :data:`NAV_REPORT_WEIGHT`."""
    return [(image_ids[i], NAV_GROUPS[g][0], round(float(weights[i, g]), 4))
            for i, g in zip(*np.nonzero(weights < NAV_REPORT_WEIGHT), strict=True)]
