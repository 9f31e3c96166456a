"""The ``seqat report`` stage: build the report model, render it, write both files together."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline.common.atomic import write_files_atomically
from pipeline.report.html import render_html
from pipeline.report.model import (
    REPORT_HTML,
    REPORT_JSON,
    Report,
    build_report,
    format_report_json,
)


@dataclass(frozen=True, kw_only=True)
class ReportSummary:
    """Typed result of :func:`make_report` (what ``seqat report`` prints)."""

    files: tuple[Path, ...]
    report: Report


def make_report(out_dir: Path | str, compare: Sequence[Path | str] = ()) -> ReportSummary:
    """Write ``OUT/report.html`` and ``OUT/report.json`` together.

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
    files = write_files_atomically(out_dir, {
        REPORT_JSON: format_report_json(report),
        REPORT_HTML: render_html(report, extras),
    })
    return ReportSummary(files=files, report=report)
