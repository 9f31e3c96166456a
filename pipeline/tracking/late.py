"""Late observations of held images (docs/algorithm.md, *Late observations*).

A held image keeps every feature for matching but emitted only some. When a verified match
links a feature of the new image to a feature a held image did not emit, the held feature
is emitted now, as a *late observation* of the held image: it joins the track of the new
image's feature (a continued or a fresh one) unless that track holds a feature of the held
image already. Per pair at most what tops its ties (verified matches through emitted
features) up to ``late_per_pair`` (``late_untied_per_pair`` when it has none, or when the
held image has no tie with any image yet): pairs tied well get none, weak ones are filled;
smallest descriptor distance first; one per held pixel.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

#: A late observation emitted: (held image id, point number, working-resolution keypoint).
LateEmission = tuple[str, int, NDArray[np.float32]]


class Held(Protocol):
    """What :func:`emit_late` needs of a :class:`pipeline.tracking.tracker.HeldImage`."""

    image_id: str
    kp_work: NDArray[np.float32]
    point_nums: NDArray[np.int64]
    late: NDArray[np.int64]


def feature_sites(kp: NDArray[np.float32]) -> NDArray[np.int64]:
    """Site of every keypoint: keypoints at exactly the same pixel share one.

    SIFT gives a blob with two orientation peaks two keypoints at one pixel (OpenCV: ~19 %
    of Seneca's). Both descriptors help matching, but one pixel is one observation: two
    tracks through it would count the same measurement twice (a doubled weight, sigmas too
    optimistic by sqrt 2).
    """
    if len(kp) == 0:
        return np.zeros(0, dtype=np.int64)
    _, inverse = np.unique(np.ascontiguousarray(kp, dtype=np.float32).view(np.int64).ravel(),
                           return_inverse=True)
    return inverse.astype(np.int64).reshape(-1)


def pair_ties(links: dict[int, list[tuple[int, int, float]]]) -> dict[int, int]:
    """Verified matches through emitted features per candidate rank (``Tracker._match``)."""
    ties: dict[int, int] = {}
    for cands in links.values():
        for _, rank, _ in cands:
            ties[rank] = ties.get(rank, 0) + 1
    return ties


def _cap(ties: dict[int, int], rank: int, per_pair: int, untied: int) -> int:
    """Late observations allowed for the pair: ``untied`` without a tie through emitted
    features, else what tops its ties up to ``per_pair``."""
    n = ties.get(rank, 0)
    return untied if n == 0 else max(0, per_pair - n)


def late_candidates(unlinked: Sequence[tuple[int, int, int, float]], ties: dict[int, int],
                    per_pair: int, untied: int,
                    ) -> tuple[dict[int, list[tuple[int, int]]], list[int]]:
    """Matches with non-emitted held features per candidate pair, best first, and the new
    features to emit for them (the first ones within each pair's cap).

    Parameters
    ----------
    unlinked : sequence of (candidate rank, new feature, held feature, distance)
    ties : dict
        :func:`pair_ties`.
    per_pair, untied : int
        ``TrackerOptions.late_per_pair``, ``late_untied_per_pair``.

    Returns
    -------
    late : dict
        Candidate rank -> ``[(new feature, held feature), ...]`` by descriptor distance.
    preferred : list of int
        New features to emit before the grid's (``Tracker._emitted``).
    """
    if not unlinked or untied == 0:
        return {}, []
    late: dict[int, list[tuple[int, int]]] = {}
    for rank, i_new, i_old, _ in sorted(unlinked, key=lambda m: (m[0], m[3], m[1], m[2])):
        late.setdefault(rank, []).append((i_new, i_old))
    preferred: list[int] = []
    for rank, pairs in late.items():
        preferred += [f for f, _ in pairs[: _cap(ties, rank, per_pair, untied)]]
    return late, preferred


def emit_late(helds: Sequence[Held], late: dict[int, list[tuple[int, int]]],
              ties: dict[int, int], new_nums: NDArray[np.int64], tracks: dict[int, list[int]],
              per_pair: int, untied: int) -> list[LateEmission]:
    """Emit the held features matched by emitted features of the new image.

    Each joins the new feature's track (``new_nums``: point number of every new feature's
    pixel, -1: not emitted) unless the track holds a feature of that held image already; one
    per held pixel (every feature at it takes the number); at most the pair's cap. The held
    image's ``point_nums`` and ``late`` are replaced by new arrays (copy on write: tracker
    state snapshots share the old ones); ``tracks`` (number -> [images, held images]) counts
    the held image in.

    Returns
    -------
    list of (held image id, point number, working-resolution keypoint)
    """
    out: list[LateEmission] = []
    for rank in sorted(late):
        held = helds[rank]
        cap = _cap(ties, rank, per_pair, untied)
        nums = held.point_nums.copy()
        have = set(nums[nums >= 0].tolist())
        sites = feature_sites(held.kp_work)
        changed: list[NDArray[np.int64]] = []
        for i_new, i_old in late[rank]:
            if len(changed) >= cap:
                break
            num = int(new_nums[i_new])
            if num < 0 or nums[i_old] >= 0 or num in have:
                continue
            at = np.flatnonzero(sites == sites[i_old])
            nums[at] = num
            have.add(num)
            changed.append(np.column_stack([at, np.full(at.size, num)]).astype(np.int64))
            track = tracks[num]
            track[0] += 1
            track[1] += 1
            out.append((held.image_id, num, held.kp_work[i_old]))
        if changed:
            held.point_nums = nums
            held.late = np.vstack([held.late, *changed])
    return out
