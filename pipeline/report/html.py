"""Rendering of the flight report as one self-contained HTML file (CSS inline, figures as
base64 PNG), laid out for a surveyor: the verdict first, then the warnings, the map, the check
points, accuracy or agreement, the flight, and the estimator's internals in an appendix.

The numbers come from :func:`pipeline.report.model.build_report`; nothing here computes
accuracy. Layout: docs/formats.md, *Report*; a screenshot: docs/figures/report_1024.png.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from matplotlib.figure import Figure

from pipeline.report.asprs import CM_PER_M, AsprsTable
from pipeline.report.figures import (
    checkpoint_figure,
    error_figure,
    map_figures,
    png_tag,
    realtime_figure,
)
from pipeline.report.model import (
    DIRECT,
    REFERENCE,
    CheckpointReport,
    LiveOperation,
    Report,
    main_checkpoints,
)
from pipeline.report.sfm_section import sfm_section_html
from pipeline.report.thumbnails import DSM_FILE, MOSAIC_FILE, Thumbnail, read_thumbnail
from pipeline.run.robustness import robustness_rows

#: Warnings listed before the rest fold away.
WARNINGS_SHOWN = 8

# Tables scroll sideways inside the page (display:block) instead of widening it; text cells
# wrap, number cells do not.
_CSS = """
body{font-family:system-ui,sans-serif;max-width:62rem;margin:1.5rem auto;color:#222;
padding:0 1rem;line-height:1.4}
h1{font-size:1.6rem;margin-bottom:.2rem}.sub{color:#555;margin-top:0}
h2{font-size:1.2rem;margin-top:2rem;border-bottom:1px solid #ccc}h3{font-size:1rem}
table{border-collapse:collapse;margin:.5rem 0;display:block;overflow-x:auto;max-width:100%;
font-size:.9rem}
td,th{border:1px solid #ccc;padding:.2rem .45rem;text-align:right;white-space:nowrap}
th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
td.text{text-align:left;white-space:normal;min-width:12rem}
.verdict{border:2px solid #2a7a45;background:#f1f9f3;padding:.3rem 1rem .6rem;
border-radius:6px}.verdict.caveat{border-color:#b07a00;background:#fdf7e8}
.verdict h2{border:none;margin-top:.6rem}.verdict p{margin:.35rem 0}
.verdict p.lead{font-size:1.1rem;font-weight:600}
ul.warnings{padding-left:0;list-style:none}
ul.warnings li{display:flex;gap:.6rem;margin:.2rem 0;overflow-wrap:anywhere}
.stage{flex:0 0 6.5rem;color:#a40;font-weight:600}.msg{flex:1 1 auto;min-width:0}
.warn{color:#a40}.note{color:#555}img{max-width:100%;height:auto}
details summary{cursor:pointer;color:#345}
.appendix{margin-top:3rem;border-top:3px double #ccc}
"""


def _num(value: object, digits: int = 3) -> str:
    """A number with ``digits`` decimals, ``–`` when unknown; anything else as text."""
    if value is None:
        return "–"
    if isinstance(value, float):
        return "–" if not math.isfinite(value) else f"{value:.{digits}f}"
    return html.escape(str(value))


def class_cm(value: float | None) -> str:
    """An ASPRS class as a surveyor writes it: ``7.5 cm`` (``–`` when none)."""
    return "–" if value is None else f"{value:g} cm"


def _table(header: Sequence[str], rows: Sequence[Sequence[object]],
           digits: int | Sequence[int] = 3, text_columns: Sequence[int] = ()) -> str:
    """An HTML table; ``digits``: decimals of every number, or one per column."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    per = [digits] * len(header) if isinstance(digits, int) else list(digits)
    body = "".join(
        "<tr>" + "".join(f"<td class='text'>{_num(v, per[k])}</td>" if k in text_columns
                         else f"<td>{_num(v, per[k])}</td>" for k, v in enumerate(row))
        + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def asprs_rows(tables: Sequence[tuple[str, AsprsTable]]) -> tuple[list[str], list[list[object]]]:
    """Header and rows of the ASPRS table (metres to the millimetre, classes in cm)."""
    header = ["method", "n", "RMSE_H", "RMSE_V", "RMSE x", "RMSE y", "mean x",
              "mean y", "mean z", "σ x", "σ y", "σ z", "H class", "V class"]
    rows = [[label, t.count, t.rmse_h_m, t.rmse_v_m, t.rmse_x_m, t.rmse_y_m, t.mean_x_m,
             t.mean_y_m, t.mean_z_m, t.std_x_m, t.std_y_m, t.std_z_m,
             class_cm(t.horizontal_class_cm), class_cm(t.vertical_class_cm)]
            for label, t in tables]
    return header, rows


def residual_rows(cp: CheckpointReport) -> tuple[list[str], list[list[object]]]:
    """Header and rows of the residual table, largest first (the model's order)."""
    header = ["point", "images", "dx (m)", "dy (m)", "dz (m)", "horizontal (m)", "3D (m)"]
    rows = [[r.point, r.n_images, r.dx_m, r.dy_m, r.dz_m, math.hypot(r.dx_m, r.dy_m),
             math.sqrt(r.dx_m**2 + r.dy_m**2 + r.dz_m**2)] for r in cp.residuals]
    return header, rows


def _verdict(report: Report, main: CheckpointReport | None) -> list[str]:
    n = 0 if main is None else main.table.count
    caveat = n == 0 or (main is not None and main.table.warning is not None)
    lines = report.verdict
    parts = [f"<div class='verdict{' caveat' if caveat else ''}'><h2>Verdict</h2>",
             f"<p class='lead'>{html.escape(lines[0])}</p>"]
    parts += [f"<p>{html.escape(line)}</p>" for line in lines[1:]]
    if main is not None and n:
        t = main.table
        parts.append(_table(["", "x", "y", "z"], [
            ("mean (bias), cm", t.mean_x_m * CM_PER_M, t.mean_y_m * CM_PER_M,
             t.mean_z_m * CM_PER_M),
            ("σ, cm", t.std_x_m * CM_PER_M, t.std_y_m * CM_PER_M, t.std_z_m * CM_PER_M),
            ("RMSE, cm", t.rmse_x_m * CM_PER_M, t.rmse_y_m * CM_PER_M, t.rmse_z_m * CM_PER_M),
        ], digits=1))
    parts.append("</div>")
    return parts


def _warnings(report: Report) -> list[str]:
    w = report.warnings
    parts = [f"<h2>Warnings ({len(w)})</h2>"]
    if not w:
        return [*parts, "<p>No stage gave a warning.</p>"]

    def items(ws: Sequence[object]) -> str:
        return "".join(f"<li><span class='stage'>{html.escape(x.stage)}</span>"  # type: ignore[attr-defined]
                       f"<span class='msg'>{html.escape(x.message)}</span></li>"  # type: ignore[attr-defined]
                       for x in ws)

    parts.append(f"<ul class='warnings'>{items(w[:WARNINGS_SHOWN])}</ul>")
    if len(w) > WARNINGS_SHOWN:
        parts.append(f"<details><summary>{len(w) - WARNINGS_SHOWN} more</summary>"
                     f"<ul class='warnings'>{items(w[WARNINGS_SHOWN:])}</ul></details>")
    return parts


def _map(mosaic: Thumbnail | None, figures: tuple[Figure, Figure | None]) -> list[str]:
    parts = ["<h2>Map</h2>", png_tag(figures[0], "check point residual map")]
    if mosaic is not None and not mosaic.same_crs:
        parts.append("<p class='note'>The mosaic is in another CRS than the run (seqat ortho "
                     "--crs): drawn beside, not under, the check points.</p>")
    rasters = figures[1]
    if rasters is not None:
        parts.append(png_tag(rasters, "mosaic and DSM"))
    else:
        parts.append("<p class='note'>No mosaic or DSM in this run folder (seqat run --ortho, "
                     "or seqat process with a DSM or lidar, makes them).</p>")
    return parts


def _checkpoints(report: Report, main: CheckpointReport | None) -> list[str]:
    parts = ["<h2>Check points (ASPRS 2023)</h2>"]
    if main is None:
        return [*parts, "<p>The flight has no check points.</p>"]
    header, rows = asprs_rows([(c.method, c.table) for c in report.checkpoint_reports])
    parts.append(_table(header, rows))
    parts.append("<p class='note'>Metres; σ: standard deviation (n − 1) about the mean, the "
                 "random part; mean: the systematic part (bias); RMSE² = mean² + σ²(n − 1)/n. "
                 f"Classes: the smallest ASPRS (2023) X-cm class the RMSE meets. "
                 f"{DIRECT} = GPS/INS only, {REFERENCE} = COLMAP on the same tie points.</p>")
    if main.excluded_control:
        parts.append(f"<p class='note'>Left out as ground control points of the run: "
                     f"{html.escape(', '.join(main.excluded_control))}.</p>")
    parts.append(f"<h3>Residuals of {html.escape(main.method)}, largest first "
                 "(intersected − known)</h3>")
    header, rows = residual_rows(main)
    parts.append(_table(header, rows))
    parts.append(png_tag(checkpoint_figure(main), "check point residuals"))
    return parts


def _control(report: Report) -> list[str]:
    """Ground control points: every method's fit to them, the run's residuals (a table apart
    from the check points; the verdict is the check points')."""
    if report.control is None:
        return []
    parts = ["<h2>Ground control points</h2>",
             "<p class='note'>These points entered the adjustment with their surveyed "
             "coordinates: their residuals (adjusted − surveyed) show how well it fits its "
             "control, not its accuracy. The verdict rests on the independent check points"
             + (" (a point that is both is control: left out of the check statistics)."
                if report.checkpoint_reports else ").") + "</p>"]
    ctrl = report.control_reports
    if not ctrl:
        return [*parts, "<p>No method adjusted the control points.</p>"]
    header, rows = asprs_rows([(c.method, c.table) for c in ctrl])
    parts.append(_table(header[:-2], [r[:-2] for r in rows]))
    main = next((c for c in ctrl if c.method == report.methods[1]), ctrl[0])
    parts.append(f"<h3>Control residuals of {html.escape(main.method)}, largest first "
                 "(adjusted − surveyed)</h3>")
    header, rows = residual_rows(main)  # type: ignore[arg-type]
    parts.append(_table(header, rows))
    if main.not_adjusted:
        parts.append(f"<p class='note'>Not adjusted (fewer rays than needed): "
                     f"{html.escape(', '.join(main.not_adjusted))}</p>")
    return parts


def _accuracy(report: Report, extras: Mapping[str, object]) -> list[str]:
    if not report.accuracy:
        return []
    if report.accuracy_against == "reference":
        parts = ["<h2>Agreement with the COLMAP reference</h2>",
                 "<p class='note'>An agreement, not an accuracy: COLMAP adjusted the same tie "
                 "points with the same GPS/INS priors; errors both share (the tie points, the "
                 "nav, the camera) do not show here.</p>"]
    else:
        parts = ["<h2>Accuracy against truth</h2>",
                 "<p class='note'>The flight is simulated or rendered: truth/ holds the exact "
                 "orientations and points.</p>"]
    rows = [(a.method, *a.pos_rmse_m, a.pos_rmse_h_m, a.pos_rmse_3d_m, *a.att_rmse_deg,
             *a.gp_rmse_m, a.n_images, a.n_points) for a in report.accuracy.values()]
    parts.append(_table(["method", "X (m)", "Y (m)", "Z (m)", "H (m)", "3D (m)", "ω (°)",
                         "φ (°)", "κ (°)", "GP X (m)", "GP Y (m)", "GP Z (m)", "images",
                         "points"], rows, digits=3))
    parts.append("<p class='note'>RMS differences per axis: camera positions, attitudes "
                 "(ω φ κ) and ground points (GP), matched by id.</p>")
    errors = extras.get("errors", {})
    assert isinstance(errors, Mapping)
    what = "the COLMAP reference" if report.accuracy_against == "reference" else "truth"
    parts.append(png_tag(error_figure(errors, what), "per-image differences"))
    return parts


def flight_rows(report: Report) -> list[tuple[str, str]]:
    """The flight's key figures (label, text)."""
    f, t = report.flight_summary, report.tie_points
    camera = f.camera_model + (" (approximate, from EXIF)" if f.camera_approximate else "")
    return [
        ("flight folder", report.flight),
        ("run folder", report.run),
        ("images / duration", f"{f.images} / {f.duration_s:.1f} s"),
        ("GSD / forward overlap", f"{_num(f.gsd_m * CM_PER_M, 1)} cm / "
                                  f"{_num(f.forward_overlap * 100, 0)} %"),
        ("CRS", f.crs_name),
        ("camera", camera + (f"; {f.camera_estimate}" if f.camera_estimate else "")),
        ("tie points / observations", f"{t.count} / {t.observations}"),
        ("track length mean / median / max",
         f"{t.track_length_mean:.1f} / {t.track_length_median:.0f} / {t.track_length_max}"),
        ("image residual rms", f"{_num(t.image_residual_rms_px, 2)} px"),
        ("σ0 (a posteriori)", _num(report.sigma0, 3)),
        ("methods compared", ", ".join(report.methods)),
    ]


def _appendix(report: Report, extras: Mapping[str, object]) -> list[str]:
    parts = ["<div class='appendix'><h2>Appendix: estimator internals</h2>",
             "<p class='note'>For the developer and the curious: how the adjustment ran, not "
             "what it delivered.</p>",
             _table(["", "value"], [
                 ("update time per image, median / run total",
                  f"{report.processing_ms_per_image_median:.1f} ms / "
                  f"{report.processing_total_s:.1f} s")], text_columns=(1,))]
    if report.reference is not None:
        ref = report.reference
        opts = ref.get("options", {})
        assert isinstance(opts, Mapping)
        parts.append("<h3>COLMAP reference</h3>")
        parts.append(_table(["", "value"], [
            ("prior / self-calibration", f"{opts.get('prior')} / {opts.get('self_calibrate')}"),
            ("σ0 / rms image residual", f"{_num(ref.get('sigma0'), 3)} / "
                                        f"{_num(ref.get('rms_px'), 3)} px"),
            ("bundle adjustment", f"{_num(ref.get('ba_s'), 2)} s"),
            ("termination / covariance", f"{ref.get('termination')} / {ref.get('covariance')}"),
        ], text_columns=(1,)))
    if report.realtime:
        parts.append("<h3>Real-time behaviour</h3>")
        parts.append(_table(
            ["method", "update ms median", "p95", "max", "window median", "window max",
             "inverse sizes max", "σ0 final", "rms GP σ final (m)", "plateau at image"],
            [(r.method, r.update_ms_median, r.update_ms_p95, r.update_ms_max,
              r.window_images_median, r.window_images_max,
              f"{r.inverse_sizes_max[0]}, {r.inverse_sizes_max[1]}", r.final_sigma0,
              r.final_rms_gp_sigma_m, r.precision_plateau_image) for r in report.realtime],
            digits=(1, 1, 1, 1, 1, 0, 0, 3, 3, 0)))
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
                     "-> mosaic with the live ortho), per image. The refinement after the AT "
                     "update (the window's re-linearisation) runs once the image's estimate is "
                     "out, before the next image: not in end to end. The live ortho runs on a "
                     "worker thread while the next image is tracked and adjusted, on the same "
                     "cores.</p>")
        series = extras.get("series", {})
        assert isinstance(series, Mapping)
        parts.append(png_tag(realtime_figure(series, {r.method: r.precision_plateau_index
                                                      for r in report.realtime}),
                             "update time, window, matrix sizes and precision per image"))
    if report.live is not None:
        parts += _live_section(report.live)
    parts.append("</div>")
    return parts


def _change(event: Mapping[str, object], dial: str) -> str:
    """``old → new`` of a budget event's dial, or empty when it did not change."""
    old, new = event.get(f"old_{dial}"), event.get(f"new_{dial}")
    if old == new:
        return ""
    return f"{'none' if old is None else old} → {'none' if new is None else new}"


def _live_section(live: LiveOperation) -> list[str]:
    """Processing and end-to-end latency, and the latency budget's threshold changes."""
    parts = ["<h3>Live operation</h3>"]
    rows: list[tuple[object, ...]] = [
        ("mode" + (f" (resumed: {live.replayed_images} images replayed from the journal)"
                   if live.replayed_images else ""), live.mode, "", ""),
        ("processing per image: tracking + update + second start (ms)", live.processing_ms_median,
         live.processing_ms_p95, live.processing_ms_max)]
    if live.latency_ms_median is not None:
        rows.append(("end-to-end latency: input complete → estimate (ms)",
                     live.latency_ms_median, live.latency_ms_p95, live.latency_ms_max))
    parts.append(_table(["", "median", "p95", "max"], rows, digits=1))
    if live.budget_mode is None:
        return parts
    features = ("" if live.final_features is None
                else f"; final tracker features {live.final_features}")
    if live.budget_mode == "keep-up":
        parts.append("<p>Latency budget: keep up with the arrivals"
                     + ("" if live.budget_ms is None else
                        f" (last interval {live.budget_ms:.0f} ms)")
                     + f": {live.images_over_budget} image(s) over it; final Seq-R threshold "
                     f"{live.final_threshold:g}{features}.</p>")
    else:
        parts.append(f"<p>Latency budget {live.budget_ms:g} ms per image: "
                     f"{live.images_over_budget} image(s) over it; final Seq-R threshold "
                     f"{live.final_threshold:g}{features}.</p>")
    if live.threshold_changes:
        parts.append(_table(
            ["after image", "threshold", "features", "window cap", "measured (ms)", "why"], [
                (e["image"], f"{e['old_threshold']:g} → {e['new_threshold']:g}",
                 _change(e, "features"), _change(e, "window_cap"), e["measured_ms"],
                 e["reason"]) for e in live.threshold_changes], digits=1))
    else:
        parts.append("<p>The dials never changed.</p>")
    return parts


def title_text(report: Report) -> tuple[str, str]:
    """The title (the flight's name) and the line under it (date, method)."""
    t = report.title
    return t.flight_name, f"Flight report · {t.date_kind} {t.date} · method {t.method}"


def report_thumbnails(report: Report, extras: Mapping[str, object]) -> tuple[
        Thumbnail | None, Thumbnail | None]:
    """The run's mosaic and DSM read small (None where absent)."""
    run_path = Path(str(extras.get("run_path", report.run)))
    crs = extras["crs"]
    return (read_thumbnail(run_path / MOSAIC_FILE, crs),  # type: ignore[arg-type]
            read_thumbnail(run_path / DSM_FILE, crs, heights=True))  # type: ignore[arg-type]


def render_html(report: Report, extras: Mapping[str, object],
                thumbnails: tuple[Thumbnail | None, Thumbnail | None] | None = None,
                figures: tuple[Figure, Figure | None] | None = None) -> str:
    """The self-contained ``report.html`` (``thumbnails`` and the map ``figures`` are made
    here unless given)."""
    if thumbnails is None:
        thumbnails = report_thumbnails(report, extras)
    if figures is None:
        figures = map_figures(report, extras, thumbnails)
    main = main_checkpoints(report)
    name, sub = title_text(report)
    parts = ["<!doctype html><html><head><meta charset='utf-8'>"
             "<meta name='viewport' content='width=device-width, initial-scale=1'>"
             f"<title>{html.escape(name)}: seqat flight report</title><style>{_CSS}</style>"
             "</head><body>", f"<h1>{html.escape(name)}</h1>",
             f"<p class='sub'>{html.escape(sub)}</p>"]
    parts += _verdict(report, main)
    parts += _warnings(report)
    parts += _map(thumbnails[0], figures)
    parts += _checkpoints(report, main)
    parts += _control(report)
    parts += _accuracy(report, extras)
    parts.append("<h2>Flight</h2>")
    parts.append(_table(["", "value"], flight_rows(report), text_columns=(1,)))
    if report.robustness is not None:
        parts.append("<h2>Blunders and GNSS faults</h2>")
        parts.append(_table(["", "value"], robustness_rows(report.robustness),
                            text_columns=(1,)))
    if report.sfm_agreement is not None:
        parts.append(sfm_section_html(report.sfm_agreement, Path(report.run)))
    parts += _appendix(report, extras)
    parts.append(f"<p class='note'>Methods: {DIRECT} = GPS/INS input (direct "
                 f"georeferencing, tie points intersected with it); {REFERENCE} = COLMAP "
                 "bundle adjustment of the same observations (OUT/reference/). Made by seqat "
                 "report (docs/formats.md, <i>Report</i>).</p>")
    parts.append("</body></html>\n")
    return "".join(parts)
