"""Late observations in the sequential update (Seq-F, Seq-R).

Mixed into :class:`seqat.sequential.SequentialAT` (its state lives there). A frame may carry
observations of *earlier* images that the tracker emitted only now (``Frame.late_*``,
docs/algorithm.md, *Late observations*). They enter before the frame's own rays:

* a late ray of a point that is not a ground point yet is a *pending ray* of its image
  that arrives now: the point is born as soon as its rays suffice (e.g. from the late ray of
  image j and the new ray of image i), its rays entering as y12 / y22 rows as any pending
  ray's; a late ray of a departed image (Seq-R) is kept as that image's pending rays are, and
  the image re-opens when the point is born (:meth:`DepartureMixin._reopen`);
* a late ray of a ground point already estimated (in the window, or departed and still
  re-openable) is a row of two existing parameters, the image's EOP and the point, added
  with the update's other rows (a y2 row with ``A22 = 0``); a departed image or point
  re-opens for it.

A late ray of an image or point that can no longer re-enter the window (left more than
``reopen_max_age`` images ago, or finalised by ``smoothing_lag``) is skipped and counted in
``ImageUpdate.observations_skipped``, as a new image's ray of such a point is.
"""

from __future__ import annotations

from seqat.errors import InputDataError
from seqat.types import FloatArray, Frame

#: A late ray: (image index, point index, ideal pixel, sigma).
LateRay = tuple[int, int, FloatArray, float]


class LateMixin:
    """Late observations of :class:`SequentialAT` (see the module docstring)."""

    def _image_of(self, frame: Frame, image_id: str) -> int:
        """Index of an earlier image named by a late observation of ``frame``."""
        j = self._image_index.get(image_id)
        if j is None:
            raise InputDataError(
                f"image {frame.image_id!r}: late observation of image {image_id!r}, which the "
                "estimator has not received (late observations are of earlier images)")
        return j

    def _key_usable(self, key: tuple[str, int], i: int) -> bool:
        """In the window, or departed and still re-openable."""
        return key in self._w.offset or self._reopenable(key, i)

    def _insert_late(self, frame: Frame, i: int) -> tuple[list[LateRay], list[int], int]:
        """Take the frame's late observations before its own rays (see the module docstring).

        Returns
        -------
        rows : list of (image, point, uv, sigma)
            Late rays of ground points already estimated: rows of this update.
        pending : list of int
            Points that got a late pending ray.
        skipped : int
            Late rays of images or points that can no longer re-enter the window.
        """
        rows: list[LateRay] = []
        pending: list[int] = []
        skipped = 0
        s = frame.sigma_px
        for iid, pid, uv in zip(frame.late_image_ids, frame.late_point_ids, frame.late_uv_px,
                                strict=True):
            j = self._image_of(frame, iid)
            p = self._point_index.get(pid)
            if p is None:
                p = self._point_index[pid] = len(self._point_ids)
                self._point_ids.append(pid)
            if not self._key_usable(("e", j), i):
                skipped += 1  # finalised, or left too long ago to re-open
                continue
            in_window = ("e", j) in self._w.offset
            if in_window and p in self._img_points[j]:
                raise InputDataError(
                    f"image {frame.image_id!r}: late observation of point {pid!r} in image "
                    f"{iid!r}, which already observes it")
            if ("p", p) in self._w.offset or p in self._frozen_gp:
                if self._key_usable(("p", p), i):
                    rows.append((j, p, uv, s))
                else:
                    skipped += 1
                continue
            if p in self._final_gp or p in self._sunk:
                skipped += 1
                continue
            rays = self._pending.setdefault(p, [])
            if any(r[0] == j for r in rays):
                raise InputDataError(
                    f"image {frame.image_id!r}: late observation of point {pid!r} in image "
                    f"{iid!r}, which already observes it")
            rays.append((j, uv, s))
            pending.append(p)
            if in_window:
                self._img_points[j].append(p)
            else:
                self._keep_departed_ray(j, p)
        return rows, pending, skipped

    def _keep_departed_ray(self, j: int, p: int) -> None:
        """A late pending ray of departed image ``j``: kept with that image's pending rays,
        in order of departure, so that :meth:`_forget_old_rays` drops it in time."""
        rays = self._departed_rays
        for jj, points in rays:
            if jj == j:
                points.append(p)
                return
        left = self._departed[("e", j)][0]
        entries = list(rays)
        pos = len(entries)
        for k, (jj, _) in enumerate(entries):
            other = self._departed.get(("e", jj))
            if other is not None and other[0] > left:
                pos = k
                break
        entries.insert(pos, (j, [p]))
        rays.clear()
        rays.extend(entries)
