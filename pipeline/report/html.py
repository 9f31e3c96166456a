"""Rendering of the flight report: matplotlib figures embedded as base64 PNG in one HTML file.

The numbers come from :func:`pipeline.report.model.build_report`; nothing here computes accuracy.
"""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.report.model import DIRECT, REFERENCE, CheckpointReport, LiveOperation, Report
from pipeline.report.sfm_section import sfm_section_html
from pipeline.run.robustness import robustness_rows

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Figure resolution, dots per inch.
FIGURE_DPI = 90
#: Figure size, inches.
FIGURE_SIZE = (9.0, 3.2)
RT_FIGURE_SIZE = (9.0, 6.0)

_CSS = """
body{font-family:system-ui,sans-serif;max-width:60rem;margin:2rem auto;color:#222;padding:0 1rem}
h1{font-size:1.5rem}h2{font-size:1.2rem;margin-top:2rem;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5rem 0}td,th{border:1px solid #ccc;padding:.2rem .5rem;
text-align:right}th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
.warn{color:#a40}.note{color:#555}img{max-width:100%}
"""


def _fmt(value: object, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return "–" if not math.isfinite(value) else f"{value:.{digits}f}"
    return html.escape(str(value))


def _table(header: Sequence[str], rows: Sequence[Sequence[object]], digits: int = 3) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(v, digits)}</td>" for v in row) + "</tr>"
                   for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _png(fig: Figure) -> str:
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=FIGURE_DPI, bbox_inches="tight")
    plt.close(fig)
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img alt="figure" src="data:image/png;base64,{data}">'


def _error_figure(errors: Mapping[str, tuple[np.ndarray, np.ndarray]], against: str) -> str:
    import matplotlib.pyplot as plt

    fig, (ax_p, ax_a) = plt.subplots(1, 2, figsize=FIGURE_SIZE)
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
    return _png(fig)


def _realtime_figure(series: Mapping[str, list[Mapping[str, object]]],
                     plateaus: Mapping[str, int | None]) -> str:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=RT_FIGURE_SIZE)
    (ax_t, ax_w), (ax_i, ax_s) = axes
    for label, images in series.items():
        ms = [im.get("update_ms") for im in images]
        ax_t.plot(np.asarray(ms, dtype=float), lw=1, label=label)
        ax_w.plot([im.get("window_images") for im in images], lw=1, label=label)
        inv = np.array([im.get("inverse_sizes", [0, 0]) for im in images], dtype=float)
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
    return _png(fig)


def _checkpoint_figure(cp: CheckpointReport) -> str:
    import matplotlib.pyplot as plt

    fig, (ax_h, ax_v) = plt.subplots(1, 2, figsize=FIGURE_SIZE)
    d = np.array([[r.dx_m, r.dy_m, r.dz_m] for r in cp.residuals]).reshape(-1, 3)
    ax_h.scatter(d[:, 0], d[:, 1], s=12)
    ax_h.axhline(0, color="gray", lw=0.5)
    ax_h.axvline(0, color="gray", lw=0.5)
    ax_h.set(xlabel="dx (m)", ylabel="dy (m)", title=f"check point residuals ({cp.method})",
             aspect="equal")
    ax_v.bar(np.arange(d.shape[0]), d[:, 2])
    ax_v.set(xlabel="check point", ylabel="dz (m)")
    fig.tight_layout()
    return _png(fig)


def _live_section(live: LiveOperation) -> list[str]:
    """Processing and end-to-end latency, and the latency budget's threshold changes."""
    parts = ["<h2>Live operation</h2>"]
    rows: list[tuple[object, ...]] = [
        ("mode" + (f" (resumed: {live.replayed_images} images replayed from the journal)"
                   if live.replayed_images else ""), live.mode, "", ""),
        ("processing per image: tracking + update (ms)", live.processing_ms_median,
         live.processing_ms_p95, live.processing_ms_max)]
    if live.latency_ms_median is not None:
        rows.append(("end-to-end latency: input complete → estimate (ms)",
                     live.latency_ms_median, live.latency_ms_p95, live.latency_ms_max))
    parts.append(_table(["", "median", "p95", "max"], rows, digits=1))
    if live.budget_ms is None:
        return parts
    parts.append(f"<p>Latency budget {live.budget_ms:g} ms per image: "
                 f"{live.images_over_budget} image(s) over it; final Seq-R threshold "
                 f"{live.final_threshold:g}.</p>")
    if live.threshold_changes:
        parts.append(_table(["after image", "threshold", "measured (ms)", "why"], [
            (e["image"], f"{e['old_threshold']:g} → {e['new_threshold']:g}",
             e["measured_ms"], e["reason"]) for e in live.threshold_changes], digits=1))
    else:
        parts.append("<p>The threshold never changed.</p>")
    return parts


def render_html(report: Report, extras: Mapping[str, object]) -> str:
    """The self-contained ``report.html``."""
    import matplotlib

    matplotlib.use("Agg")
    f, t = report.flight_summary, report.tie_points
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>seqat report "
             f"{html.escape(report.run)}</title><style>{_CSS}</style></head><body>",
             f"<h1>Flight report: {html.escape(report.run)}</h1>"]
    parts += [f"<p class='note'>{html.escape(n)}</p>" for n in report.notes]
    parts.append("<h2>Summary</h2>")
    parts.append(_table(["", "value"], [
        ("flight", report.flight),
        ("images / duration (s)", f"{f.images} / {f.duration_s:.1f}"),
        ("GSD (cm) / forward overlap (%)", f"{f.gsd_m * 100:.2f} / {f.forward_overlap * 100:.0f}"),
        ("CRS", f.crs_name),
        ("camera", f.camera_model + (" (approximate, from EXIF)" if f.camera_approximate
                                     else "") + (f"; {f.camera_estimate}" if f.camera_estimate
                                                 else "")),
        ("tie points / observations", f"{t.count} / {t.observations}"),
        ("track length mean / median / max",
         f"{t.track_length_mean:.1f} / {t.track_length_median:.0f} / {t.track_length_max}"),
        ("image residual rms (px)", _fmt(t.image_residual_rms_px)),
        ("sigma0", _fmt(report.sigma0, 4)),
        ("methods", ", ".join(report.methods)),
        ("update time per image, median (ms) / run total (s)",
         f"{report.processing_ms_per_image_median:.2f} / {report.processing_total_s:.2f}"),
    ]))
    if report.reference is not None:
        ref = report.reference
        parts.append(_table(["COLMAP reference", "value"], [
            ("prior / self-calibration",
             f"{ref['options']['prior']} / {ref['options']['self_calibrate']}"),  # type: ignore[index]
            ("sigma0 / rms px", f"{_fmt(ref['sigma0'], 4)} / {_fmt(ref['rms_px'])}"),
            ("bundle adjustment (s)", _fmt(ref["ba_s"], 2)),
            ("termination / covariance", f"{ref['termination']} / {ref['covariance']}"),
        ]))
    if report.accuracy:
        parts.append(f"<h2>Accuracy against {report.accuracy_against}</h2>")
        rows = [(a.method, *a.pos_rmse_m, a.pos_rmse_h_m, a.pos_rmse_3d_m, *a.att_rmse_deg,
                 *a.gp_rmse_m, a.n_images, a.n_points) for a in report.accuracy.values()]
        parts.append(_table(["method", "X (m)", "Y (m)", "Z (m)", "H (m)", "3D (m)", "ω (°)",
                             "φ (°)", "κ (°)", "GP X (m)", "GP Y (m)", "GP Z (m)", "images",
                             "points"], rows, digits=4))
        errors = extras.get("errors", {})
        assert isinstance(errors, Mapping)
        parts.append(_error_figure(errors, report.accuracy_against or ""))
    if report.realtime:
        parts.append("<h2>Real-time behaviour</h2>")
        parts.append(_table(
            ["method", "update ms median", "p95", "max", "window median", "max",
             "inverse sizes max", "σ0 final", "rms GP σ final (m)", "plateau at image"],
            [(r.method, r.update_ms_median, r.update_ms_p95, r.update_ms_max,
              r.window_images_median, r.window_images_max,
              f"{r.inverse_sizes_max[0]}, {r.inverse_sizes_max[1]}", r.final_sigma0,
              r.final_rms_gp_sigma_m, r.precision_plateau_image) for r in report.realtime]))
        parts.append("<p class='note'>Plateau: the first image after which the rms GP σ stays "
                     "within 5 % of its final level — more images stop improving "
                     "precision there.</p>")
        lat = report.latency
        ortho_note = {"live": "with the live ortho (seqat run --ortho)",
                      "after the run": "ortho made after the run: listed, not in end to end",
                      "none": "no ortho"}[lat.ortho]
        parts.append(f"<h3>Latency per image, by stage ({html.escape(ortho_note)})</h3>")
        parts.append(_table(["stage", "images", "median ms", "p95 ms", "max ms"],
                            [(s.stage, s.images, s.median_ms, s.p95_ms, s.max_ms)
                             for s in lat.stages], digits=1))
        parts.append("<p class='note'>End to end: read + tracking + AT update (+ AT update "
                     "-> mosaic with the live ortho), per image. The live ortho runs on a "
                     "worker thread while the next image is tracked and adjusted, on the same "
                     "cores.</p>")
        series = extras.get("series", {})
        assert isinstance(series, Mapping)
        parts.append(_realtime_figure(series, {r.method: r.precision_plateau_index
                                               for r in report.realtime}))
    if report.live is not None:
        parts += _live_section(report.live)
    if report.sfm_agreement is not None:
        parts.append(sfm_section_html(report.sfm_agreement, Path(report.run)))
    if report.robustness is not None:
        parts.append("<h2>Blunders and GNSS faults</h2>")
        parts.append(_table(["", "value"], robustness_rows(report.robustness)))
    parts.append("<h2>Check points (ASPRS 2023)</h2>")
    if not report.checkpoint_reports:
        parts.append("<p>The flight has no check points.</p>")
    else:
        parts.append(_table(
            ["method", "count", "RMSE x (m)", "RMSE y (m)", "RMSE_H (m)", "RMSE_V (m)",
             "horizontal class (cm)", "vertical class (cm)"],
            [(c.method, c.table.count, c.table.rmse_x_m, c.table.rmse_y_m, c.table.rmse_h_m,
              c.table.rmse_v_m, c.table.horizontal_class_cm, c.table.vertical_class_cm)
             for c in report.checkpoint_reports], digits=4))
        main = report.checkpoint_reports[1] if len(report.checkpoint_reports) > 1 else (
            report.checkpoint_reports[0])
        if main.table.warning:
            parts.append(f"<p class='warn'>{html.escape(main.table.warning)}</p>")
        parts.append("<p class='note'>Product accuracy per ASPRS (2023) also includes the "
                     "survey accuracy of the check points (not known to seqat).</p>")
        parts.append(_table(["point", "images", "dx (m)", "dy (m)", "dz (m)"],
                            [(r.point, r.n_images, r.dx_m, r.dy_m, r.dz_m)
                             for r in main.residuals], digits=4))
        parts.append(_checkpoint_figure(main))
    parts.append(f"<p class='note'>Methods: {DIRECT} = GPS/INS input (direct "
                 f"georeferencing, tie points intersected with it); {REFERENCE} = COLMAP "
                 "bundle adjustment of the same observations (OUT/reference/).</p>")
    parts.append("</body></html>\n")
    return "".join(parts)
