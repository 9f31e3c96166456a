"""``report.pdf``: the report on paper, drawn with matplotlib's PDF backend (no system
package): page 1 the verdict, the warnings and the flight; then the residual map, the mosaic
and DSM; then the check point tables (as many pages as the residuals need).

The same numbers and sentences as ``report.html`` (:mod:`pipeline.report.html`).
"""

from __future__ import annotations

import io
import textwrap
from collections.abc import Sequence

from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from pipeline.report.asprs import CM_PER_M
from pipeline.report.html import (
    asprs_rows,
    flight_rows,
    residual_rows,
    title_text,
)
from pipeline.report.model import CheckpointReport, Report, main_checkpoints

#: A4 portrait, inches.
PAGE_SIZE = (8.27, 11.69)
#: Text layout of page 1: left margin and line height (fractions of the page), characters per
#: line at 9 pt.
MARGIN = 0.07
LINE = 0.0175
WRAP_CHARS = 100
#: Warnings printed on page 1 (the rest: report.html).
PDF_WARNINGS = 8
#: Residual rows per table page.
ROWS_PER_PAGE = 48


class _Writer:
    """Paragraphs down a page, wrapped."""

    def __init__(self, fig: Figure) -> None:
        self.fig, self.y = fig, 1.0 - MARGIN

    def text(self, s: str, *, size: float = 9, weight: str = "normal", color: str = "#222",
             indent: float = 0.0, gap: float = 0.3, chars: int = WRAP_CHARS) -> None:
        scale = size / 9
        for line in textwrap.wrap(s, width=int(chars / scale)) or [""]:
            if self.y < MARGIN:  # the page is full: report.html has the rest
                return
            self.fig.text(MARGIN + indent, self.y, line, fontsize=size, weight=weight,
                          color=color, va="top")
            self.y -= LINE * scale
        self.y -= LINE * gap


def _fmt(value: object, digits: int = 3) -> str:
    if isinstance(value, float):
        return f"{value:.{digits}f}" if value == value and abs(value) != float("inf") else "–"
    return str(value)


def _table_page(title: str, header: Sequence[str], rows: Sequence[Sequence[object]],
                note: str = "", digits: int = 3) -> Figure:
    fig = Figure(figsize=PAGE_SIZE)
    fig.text(MARGIN, 1 - MARGIN, title, fontsize=12, weight="bold", va="top")
    if note:
        for k, line in enumerate(textwrap.wrap(note, WRAP_CHARS)):
            fig.text(MARGIN, 1 - MARGIN - 0.025 - k * LINE, line, fontsize=8, color="#555",
                     va="top")
    ax = fig.add_axes((MARGIN, 0.05, 1 - 2 * MARGIN, 0.83))
    ax.axis("off")
    cells = [[_fmt(v, digits) for v in row] for row in rows]
    table = ax.table(cellText=cells, colLabels=list(header), loc="upper center",
                     cellLoc="right")
    table.auto_set_font_size(False)
    table.set_fontsize(7)
    table.auto_set_column_width(list(range(len(header))))
    for (r, _), cell in table.get_celld().items():
        if r == 0:
            cell.set_facecolor("#eeeeee")
    return fig


def _first_page(report: Report, main: CheckpointReport | None) -> Figure:
    fig = Figure(figsize=PAGE_SIZE)
    w = _Writer(fig)
    name, sub = title_text(report)
    w.text(name, size=18, weight="bold", chars=60)
    w.text(sub, color="#555", gap=1.0)
    w.text("Verdict", size=13, weight="bold")
    for k, line in enumerate(report.verdict):
        w.text(line, weight="bold" if k == 0 else "normal")
    if main is not None and main.table.count:
        t = main.table
        w.text("per axis (cm)       x        y        z", weight="bold", gap=0)
        for label, vals in (("mean (bias)", (t.mean_x_m, t.mean_y_m, t.mean_z_m)),
                            ("σ", (t.std_x_m, t.std_y_m, t.std_z_m)),
                            ("RMSE", (t.rmse_x_m, t.rmse_y_m, t.rmse_z_m))):
            cells = "".join(f"{_fmt(v * CM_PER_M, 1):>9}" for v in vals)
            fig.text(MARGIN, w.y, f"{label:<14}", fontsize=9, va="top")
            fig.text(MARGIN + 0.13, w.y, cells, fontsize=9, va="top", family="monospace")
            w.y -= LINE
        w.y -= LINE * 0.5
    w.y -= LINE
    warnings = report.warnings
    w.text(f"Warnings ({len(warnings)})", size=13, weight="bold")
    if not warnings:
        w.text("No stage gave a warning.")
    for x in warnings[:PDF_WARNINGS]:
        w.text(f"[{x.stage}] {x.message}", size=8, gap=0.1)
    if len(warnings) > PDF_WARNINGS:
        w.text(f"… {len(warnings) - PDF_WARNINGS} more in report.html and report.json",
               size=8, color="#555")
    w.y -= LINE
    w.text("Flight", size=13, weight="bold")
    for label, value in flight_rows(report):
        w.text(f"{label}: {value}", size=8, gap=0.1)
    return fig


def render_pdf(report: Report, figures: tuple[Figure, Figure | None]) -> bytes:
    """The bytes of ``report.pdf``; ``figures``: :func:`pipeline.report.figures.map_figures`."""
    cps = report.checkpoint_reports
    main = main_checkpoints(report)
    pages: list[Figure] = [_first_page(report, main), figures[0]]
    if figures[1] is not None:
        pages.append(figures[1])
    if main is not None and main.table.count:
        header, rows = asprs_rows([(c.method, c.table) for c in cps])
        pages.append(_table_page(
            "Check points (ASPRS 2023): every method", header, rows,
            note="Metres; σ about the mean (n − 1); classes: the smallest ASPRS (2023) X-cm "
                 "class the RMSE meets."))
        header, rows = residual_rows(main)
        for start in range(0, len(rows), ROWS_PER_PAGE):
            pages.append(_table_page(
                f"Residuals of {main.method}, largest first (intersected − known)"
                + (f", from row {start + 1}" if start else ""), header,
                rows[start:start + ROWS_PER_PAGE]))
    if report.control_reports:
        ctrl = report.control_reports
        header, rows = asprs_rows([(c.method, c.table) for c in ctrl])
        pages.append(_table_page(
            "Ground control points: fit of every method (adjusted − surveyed)", header[:-2],
            [r[:-2] for r in rows],
            note="Metres. Control points entered the adjustment: this is the fit to the "
                 "control, not an accuracy (that is the check points')."))
        header, rows = residual_rows(ctrl[0])  # type: ignore[arg-type]
        for start in range(0, len(rows), ROWS_PER_PAGE):
            pages.append(_table_page(
                f"Control residuals of {ctrl[0].method}, largest first (adjusted − surveyed)"
                + (f", from row {start + 1}" if start else ""), header,
                rows[start:start + ROWS_PER_PAGE]))
    buffer = io.BytesIO()
    with PdfPages(buffer, metadata={"Title": f"{report.title.flight_name}: seqat flight report",
                                    "Creator": "seqat report", "CreationDate": None}) as pdf:
        for fig in pages:
            pdf.savefig(fig)
    return buffer.getvalue()
