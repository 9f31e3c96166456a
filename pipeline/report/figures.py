"""The report's figures (matplotlib ``Figure`` objects, no pyplot state): the HTML embeds them
as PNG (:func:`png_tag`), the PDF draws them on its pages.

Nothing here computes accuracy; the numbers come from :mod:`pipeline.report.model`.
"""

from __future__ import annotations

import base64
import io
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.colors import LightSource, TwoSlopeNorm
from matplotlib.figure import Figure

from pipeline.report.asprs import CM_PER_M
from pipeline.report.model import DIRECT, CheckpointReport, Report, main_checkpoints
from pipeline.report.thumbnails import Thumbnail

#: Figure resolution for the HTML, dots per inch.
FIGURE_DPI = 90
#: Figure sizes, inches.
FIGURE_SIZE = (9.0, 3.2)
RT_FIGURE_SIZE = (9.0, 6.0)
MAP_SIZE = (9.0, 7.0)
RASTERS_SIZE = (9.0, 4.0)
#: The longest horizontal residual is drawn this fraction of the map's width long.
ARROW_FRACTION = 0.12
#: Lengths offered for the arrow key, cm.
KEY_LENGTHS_CM = (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
#: Check points labelled on the map (the largest residuals).
MAP_LABELS = 5


def png_tag(fig: Figure, alt: str = "figure") -> str:
    """``fig`` as an inline ``<img>`` (base64 PNG)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=FIGURE_DPI, bbox_inches="tight")
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img alt="{alt}" src="data:image/png;base64,{data}">'


def key_length_m(longest_m: float) -> float:
    """A round arrow-key length (m): the largest of :data:`KEY_LENGTHS_CM` not above
    ``longest_m`` (the smallest when all are)."""
    fitting = [c for c in KEY_LENGTHS_CM if c <= longest_m * CM_PER_M + 1e-12]
    return (fitting[-1] if fitting else KEY_LENGTHS_CM[0]) / CM_PER_M


def _map_axes(ax: object, thumb: Thumbnail | None) -> None:
    if thumb is not None and thumb.same_crs:
        ax.imshow(thumb.image, extent=thumb.extent, interpolation="bilinear")  # type: ignore[attr-defined]
    ax.set_aspect("equal")  # type: ignore[attr-defined]
    ax.ticklabel_format(useOffset=False, style="plain")  # type: ignore[attr-defined]
    ax.tick_params(labelsize=7)  # type: ignore[attr-defined]
    ax.set_xlabel("x (m)", fontsize=8)  # type: ignore[attr-defined]
    ax.set_ylabel("y (m)", fontsize=8)  # type: ignore[attr-defined]


def residual_map(cp: CheckpointReport | None, cameras_xyz_m: np.ndarray,
                 points_xyz_m: np.ndarray, mosaic: Thumbnail | None,
                 control_xyz_m: np.ndarray | None = None) -> Figure:
    """Check points on the mosaic: arrows = horizontal residual (scaled, with a key), colour =
    vertical residual; camera centres as grey triangles; ground control points as black
    squares. Without check points: the cameras and the tie points coloured by height."""
    fig = Figure(figsize=MAP_SIZE)
    ax = fig.subplots()
    _map_axes(ax, mosaic)
    ax.plot(cameras_xyz_m[:, 0], cameras_xyz_m[:, 1], "^", ms=5, color="0.35", mfc="0.85",
            label="camera centres")
    if control_xyz_m is not None and len(control_xyz_m):
        ax.plot(control_xyz_m[:, 0], control_xyz_m[:, 1], "s", ms=7, color="black",
                mfc="none", mew=1.5, zorder=6, label="ground control points")
        ax.legend(fontsize=7, loc="lower right")
        cameras_xyz_m = np.vstack([cameras_xyz_m, control_xyz_m])  # in the map's extent
    if cp is None or not cp.residuals:
        if len(points_xyz_m):
            sc = ax.scatter(points_xyz_m[:, 0], points_xyz_m[:, 1], c=points_xyz_m[:, 2], s=4,
                            cmap="viridis")
            fig.colorbar(sc, ax=ax, shrink=0.8, label="tie point height (m)")
        ax.set_title("Cameras and tie points (the flight has no check points)", fontsize=10)
        ax.legend(fontsize=8, loc="upper right")
        return fig
    r = cp.residuals
    x = np.array([p.x_m for p in r])
    y = np.array([p.y_m for p in r])
    d = np.array([[p.dx_m, p.dy_m, p.dz_m] for p in r])
    xs = np.concatenate([x, cameras_xyz_m[:, 0]])
    ys = np.concatenate([y, cameras_xyz_m[:, 1]])
    span = max(float(np.ptp(xs)), float(np.ptp(ys)), 1.0)
    longest = float(np.max(np.hypot(d[:, 0], d[:, 1])))
    factor = ARROW_FRACTION * span / longest if longest > 0 else 1.0
    zmax = max(float(np.max(np.abs(d[:, 2]))), 1e-6) * CM_PER_M
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-zmax, vmax=zmax)
    q = ax.quiver(x, y, d[:, 0], d[:, 1], angles="xy", scale_units="xy", scale=1.0 / factor,
                  width=0.004, color="black", zorder=3)
    sc = ax.scatter(x, y, c=d[:, 2] * CM_PER_M, cmap="RdBu_r", norm=norm, s=40,
                    edgecolors="black", linewidths=0.5, zorder=4)
    key = key_length_m(longest)
    ax.quiverkey(q, 0.78, 1.035, key, f"{key * CM_PER_M:g} cm horizontal", labelpos="E",
                 coordinates="axes", fontproperties={"size": 8})
    for p in r[:MAP_LABELS]:  # residuals are sorted largest first
        ax.annotate(p.point, (p.x_m, p.y_m), xytext=(4, 4), textcoords="offset points",
                    fontsize=7, zorder=5)
    fig.colorbar(sc, ax=ax, shrink=0.8, label="vertical residual dz (cm)")
    pad = 0.08 * span
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(ys.min() - pad, ys.max() + pad)
    ax.set_title(f"Check point residuals ({cp.method})\narrows: horizontal residual, "
                 f"×{factor:.3g}; colour: vertical"
                 + ("\nsquares: ground control points (not checks)" if control_xyz_m is not None
                    and len(control_xyz_m) else ""), fontsize=9, loc="left")
    return fig


def map_figures(report: Report, extras: Mapping[str, object],
                thumbnails: tuple[Thumbnail | None, Thumbnail | None]) -> tuple[
                    Figure, Figure | None]:
    """The residual map and the mosaic / DSM figure (None without either), drawn once for
    both the HTML and the PDF."""
    mosaic, dsm = thumbnails
    cams, pts = extras["cameras_xyz_m"], extras["points_xyz_m"]
    ctrl = extras.get("control_xyz_m")
    return (residual_map(main_checkpoints(report), cams, pts, mosaic,  # type: ignore[arg-type]
                         ctrl),  # type: ignore[arg-type]
            rasters_figure(mosaic, dsm, cams))  # type: ignore[arg-type]


def rasters_figure(mosaic: Thumbnail | None, dsm: Thumbnail | None,
                   cameras_xyz_m: np.ndarray) -> Figure | None:
    """The mosaic and the DSM (hill-shaded, coloured by height) side by side; None without
    either."""
    shown = [(t, what) for t, what in ((mosaic, "mosaic"), (dsm, "DSM")) if t is not None]
    if not shown:
        return None
    fig = Figure(figsize=RASTERS_SIZE)
    axes = fig.subplots(1, len(shown), squeeze=False)[0]
    for ax, (thumb, what) in zip(axes, shown, strict=True):
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.tick_params(labelsize=6)
        if what == "mosaic":
            ax.imshow(thumb.image, extent=thumb.extent, interpolation="bilinear")
        else:
            z = thumb.image
            finite = np.isfinite(z)
            if finite.any():
                lo, hi = np.percentile(z[finite], [2, 98])
                filled = np.where(finite, z, float(np.median(z[finite])))
                cell = (thumb.extent[1] - thumb.extent[0]) / z.shape[1]
                shaded = LightSource(azdeg=315, altdeg=45).shade(
                    filled, cmap=_cmap("terrain"), vmin=lo, vmax=max(hi, lo + 1e-3),
                    blend_mode="soft", dx=cell, dy=cell)
                shaded[~finite, 3] = 0.0
                ax.imshow(shaded, extent=thumb.extent, interpolation="bilinear")
                from matplotlib.cm import ScalarMappable
                from matplotlib.colors import Normalize

                fig.colorbar(ScalarMappable(norm=Normalize(lo, hi), cmap=_cmap("terrain")),
                             ax=ax, shrink=0.8, label="height (m)")
        if thumb.same_crs:
            ax.plot(cameras_xyz_m[:, 0], cameras_xyz_m[:, 1], "^", ms=3, color="0.2",
                    mfc="white")
        ax.set_aspect("equal")
        ax.set_title(f"{what}: {thumb.path.name}", fontsize=9)
    fig.tight_layout()
    return fig


def _cmap(name: str) -> object:
    import matplotlib

    return matplotlib.colormaps[name]


def error_figure(errors: Mapping[str, tuple[np.ndarray, np.ndarray]], against: str) -> Figure:
    """Per-image 3D position and largest attitude error of each method."""
    fig = Figure(figsize=FIGURE_SIZE)
    ax_p, ax_a = fig.subplots(1, 2)
    for label, (pos, att) in errors.items():
        style = ":" if label == DIRECT else "-"
        ax_p.plot(pos, style, lw=1, label=label)
        ax_a.plot(att, style, lw=1, label=label)
    ax_p.set(xlabel="image", ylabel="position error (m)", yscale="log",
             title=f"3D position error vs {against}")
    ax_a.set(xlabel="image", ylabel="max |angle error| (deg)", yscale="log",
             title=f"attitude error vs {against}")
    ax_p.legend(fontsize=8)
    fig.tight_layout()
    return fig


def realtime_figure(series: Mapping[str, Sequence[Mapping[str, object]]],
                    plateaus: Mapping[str, int | None]) -> Figure:
    """Update time, window size, orders of the inverted matrices and rms GP σ per image."""
    fig = Figure(figsize=RT_FIGURE_SIZE)
    (ax_t, ax_w), (ax_i, ax_s) = fig.subplots(2, 2)
    for label, images in series.items():
        ms = [im.get("update_ms") for im in images]
        ax_t.plot(np.asarray(ms, dtype=float), lw=1, label=label)
        ax_w.plot([im.get("window_images") for im in images], lw=1, label=label)
        inv = np.array([im.get("inverse_sizes", [0, 0]) for im in images],
                       dtype=float).reshape(-1, 2)
        ax_i.plot(inv[:, 0], lw=1, label=f"{label}: I + P2 A21 N11^-1 A21^T")
        ax_i.plot(inv[:, 1], "--", lw=1, label=f"{label}: M22 + L22")
        g = [float(np.sqrt(np.mean(np.square(im["rms_gp_sigma_m"]))))  # type: ignore[arg-type]
             if None not in im["rms_gp_sigma_m"] else np.nan for im in images]  # type: ignore[operator]
        ax_s.plot(g, lw=1, label=f"{label}: rms GP sigma (m)")
        plateau = plateaus.get(label)
        if plateau is not None:
            ax_s.axvline(plateau, color="gray", ls=":", lw=1)
    ax_t.set(ylabel="update time (ms)", yscale="log")
    ax_w.set(ylabel="window (images)")
    ax_i.set(xlabel="image", ylabel="order of inverted matrix")
    ax_s.set(xlabel="image", ylabel="rms GP sigma (m)", yscale="log",
             title="dotted: precision plateau")
    ax_t.legend(fontsize=8)
    ax_i.legend(fontsize=7)
    fig.tight_layout()
    return fig


def checkpoint_figure(cp: CheckpointReport) -> Figure:
    """Horizontal residuals as a scatter around the origin (a bias shows as an offset cloud)
    and the vertical residuals per check point, largest first."""
    fig = Figure(figsize=FIGURE_SIZE)
    ax_h, ax_v = fig.subplots(1, 2)
    d = np.array([[r.dx_m, r.dy_m, r.dz_m] for r in cp.residuals]).reshape(-1, 3) * CM_PER_M
    ax_h.scatter(d[:, 0], d[:, 1], s=12)
    ax_h.axhline(0, color="gray", lw=0.5)
    ax_h.axvline(0, color="gray", lw=0.5)
    if d.shape[0]:
        ax_h.plot([d[:, 0].mean()], [d[:, 1].mean()], "r+", ms=12, label="mean")
        ax_h.legend(fontsize=8)
        lim = max(float(np.max(np.abs(d[:, :2]))), 1e-3) * 1.15
        ax_h.set(xlim=(-lim, lim), ylim=(-lim, lim))
    ax_h.set(xlabel="dx (cm)", ylabel="dy (cm)", title=f"horizontal residuals ({cp.method})",
             aspect="equal")
    ax_v.bar(np.arange(d.shape[0]), d[:, 2])
    if d.shape[0]:
        ax_v.axhline(float(d[:, 2].mean()), color="red", lw=1, label="mean")
        ax_v.legend(fontsize=8)
    ax_v.set(xlabel="check point (table order)", ylabel="dz (cm)", title="vertical residuals")
    fig.tight_layout()
    return fig
