"""The ``seqat report`` stage: build the report model, render it, write the three files
together (``report.json``, ``report.html``, ``report.pdf``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline.common.atomic import write_files_atomically
from pipeline.report.figures import map_figures
from pipeline.report.html import render_html, report_thumbnails
from pipeline.report.model import (
    REPORT_HTML,
    REPORT_JSON,
    Report,
    build_report,
    format_report_json,
)
from pipeline.report.pdf import render_pdf

#: The report on paper (matplotlib's PDF backend).
REPORT_PDF = "report.pdf"


@dataclass(frozen=True, kw_only=True)
class ReportSummary:
    """Typed result of :func:`make_report` (what ``seqat report`` prints)."""

    files: tuple[Path, ...]
    report: Report


def make_report(out_dir: Path | str, compare: Sequence[Path | str] = ()) -> ReportSummary:
    """Write ``OUT/report.html``, ``OUT/report.pdf`` and ``OUT/report.json`` together.

    Parameters
    ----------
    out_dir : Path or str
        The run folder.
    compare : sequence of Path or str
        Other run folders of the same flight (other methods).

    Raises
    ------
    InputDataError
        Not a run folder, a ``--compare`` run of another flight, malformed check points.
    """
    report, extras = build_report(out_dir, compare)
    thumbnails = report_thumbnails(report, extras)
    figures = map_figures(report, extras, thumbnails)
    files = write_files_atomically(out_dir, {
        REPORT_JSON: format_report_json(report),
        REPORT_HTML: render_html(report, extras, thumbnails, figures),
        REPORT_PDF: render_pdf(report, figures),
    })
    return ReportSummary(files=files, report=report)
