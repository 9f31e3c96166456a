"""What :class:`seqat.sequential.SequentialAT` reports after each update, and the rows it
records for verification against batch (``record=True``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqat.geometry import wrap_angle
from seqat.precision import rms_point_sigma, sigma_scale
from seqat.types import EOP_SIZE, GP_SIZE, EopEstimate, FloatArray, Frame, ImageUpdate
from seqat.update import LinearRows
from seqat.window import Key, key_size


@dataclass(frozen=True, kw_only=True, eq=False)
class RecordedRows:
    """One image's linearised rows in absolute form ``b = A xi + e`` (for verification).

    ``columns`` names each column ``(kind, index, component)``.
    """

    columns: tuple[tuple[str, int, int], ...]
    A: FloatArray
    b: FloatArray
    w: FloatArray


class ReportMixin:
    """Per-image report and recorded rows of :class:`seqat.sequential.SequentialAT`."""

    def _record(
        self,
        touched_keys: list[Key],
        touched: np.ndarray,
        born: list[int],
        i: int,
        rows: LinearRows,
        x1t: FloatArray,
        x2_0: FloatArray,
    ) -> None:
        cols: list[tuple[str, int, int]] = []
        for k in touched_keys + [("e", i)] + [("p", p) for p in born]:
            cols += [(k[0], k[1], c) for c in range(key_size(k))]
        m2, m3 = rows.l2.size, rows.l3.size
        A = np.zeros((m2 + m3, len(cols)))
        A[:m2, : touched.size] = rows.A21
        A[:m2, touched.size :] = rows.A22
        A[m2:, touched.size :] = rows.A32
        b = np.concatenate([rows.l2, rows.l3]) + A @ np.concatenate([x1t, x2_0])
        assert self.recorded is not None
        self.recorded.append(
            RecordedRows(columns=tuple(cols), A=A, b=b, w=np.concatenate([rows.w2, rows.w3]))
        )

    def _report(
        self,
        frame: Frame,
        i: int,
        ms: float,
        rows: LinearRows,
        n2: int,
        n_born: int,
        used: int,
        skipped: int,
        iterations: int,
        dropped: int,
    ) -> ImageUpdate:
        w = self._w
        # first the variances: factorising may drop a GP the data do not determine
        # (Window.on_singular), which moves the offsets read below
        diag = w.q_diagonal()
        scale = sigma_scale(self.sigma0, self._redundancy)
        idx = w.index(("e", i))
        eop = w.x[idx].copy()
        eop[:3] += self._origin  # type: ignore[operator]
        eop[3:] = wrap_angle(eop[3:])
        gp_offs = np.fromiter((w.offset[k] for k in w.keys if k[0] == "p"), dtype=np.int64)
        var = diag[gp_offs[:, None] + np.arange(GP_SIZE)] * scale**2
        rms = rms_point_sigma(var)
        n_img = len(self._window_images)
        return ImageUpdate(
            image_id=frame.image_id,
            index=i,
            stage="sequential",
            update_ms=ms,
            window_images=n_img,
            window_first_image=self._image_ids[self._window_images[0]],
            window_params=w.x.size,
            window_eop_params=EOP_SIZE * n_img,
            window_gp_params=w.x.size - EOP_SIZE * n_img - self._cam.size,
            inverse_sizes=(rows.l2.size, n2),
            sim_reduced_size=0,
            sigma0=self.sigma0,
            redundancy=self._redundancy,
            rms_gp_sigma_m=rms,  # type: ignore[arg-type]
            n_points_total=self._n_points,
            new_points=n_born,
            observations_used=used,
            observations_skipped=skipped,
            iterations=iterations,
            eop=EopEstimate(
                image_id=frame.image_id, eop=eop, sigma=np.sqrt(diag[idx]) * scale
            ),
            images_left_window=dropped,
        )


