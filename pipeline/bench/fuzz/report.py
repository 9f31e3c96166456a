"""``seqat bench fuzz`` outputs: ``fuzz.csv`` (one row per command of each case), ``fuzz.json``
(everything) and ``fuzz.md`` (the summary table of docs/benchmarks.md and the failing cases)."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from pathlib import Path

from pipeline.bench.fuzz.cases import FuzzReport
from pipeline.common.atomic import write_files_atomically
from pipeline.run.store import to_jsonable

CSV_COLUMNS = ("seed", "case", "flight", "mutation", "target", "description", "command",
               "exit", "seconds", "traceback", "absurd", "inputs_changed", "leftover",
               "first_stderr_line", "error_line", "replay")

SUMMARY_HEADER = ("cases", "commands", "exit 0", "exit 2", "exit 1 / other", "tracebacks",
                  "absurd outputs", "inputs changed", "left behind")


def replay_command(seed: int, index: int) -> str:
    return f"seqat bench fuzz --seed {seed} --case {index}"


def summary_row(report: FuzzReport) -> tuple[str, ...]:
    s = report.summary
    return tuple(str(v) for v in (s.cases, s.commands, s.exit_0, s.exit_2, s.exit_other,
                                  s.tracebacks, s.absurd_outputs, s.inputs_changed, s.leftovers))


def case_rows(report: FuzzReport) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    for case in report.cases:
        for c in case.commands or [None]:  # type: ignore[list-item]
            rows.append({
                "seed": case.seed, "case": case.index, "flight": case.flight,
                "mutation": case.mutation.kind, "target": case.mutation.target,
                "description": case.mutation.description,
                "command": c.name if c else "", "exit": "" if c is None else (
                    "timeout" if c.exit_code is None else c.exit_code),
                "seconds": c.seconds if c else "", "traceback": bool(c and c.traceback),
                "absurd": "; ".join(c.absurd) if c else "",
                "inputs_changed": "; ".join(case.inputs_changed),
                "leftover": "; ".join(case.leftover),
                "first_stderr_line": c.first_stderr_line if c else "",
                "error_line": c.error_line if c else "",
                "replay": replay_command(case.seed, case.index),
            })
    return rows


def failing_rows(report: FuzzReport) -> list[tuple[str, ...]]:
    """``(seed/case, flight, mutation, defects, message)`` of every failing case."""
    out = []
    for case in report.cases:
        if case.defects or case.leftover:
            msg = next((c.error_line or c.first_stderr_line for c in case.commands
                        if c.exit_code != 0 or c.absurd), "")
            out.append((f"{case.seed}/{case.index}", case.flight,
                        f"{case.mutation.kind} {case.mutation.target}: "
                        f"{case.mutation.description}",
                        "; ".join(case.defects + case.leftover), msg[:160]))
    return out


def by_mutation(report: FuzzReport) -> dict[str, tuple[int, int, int, int]]:
    """Per mutation class: cases, ``seqat run`` exits 0 and 2, failing cases."""
    out: dict[str, list[int]] = {}
    for case in report.cases:
        row = out.setdefault(case.mutation.kind, [0, 0, 0, 0])
        run = next((c for c in case.commands if c.name == "run"), None)
        row[0] += 1
        row[1] += run is not None and run.exit_code == 0
        row[2] += run is not None and run.exit_code == 2
        row[3] += bool(case.defects or case.leftover)
    return {k: tuple(v) for k, v in sorted(out.items())}  # type: ignore[misc]


def render_markdown(report: FuzzReport) -> str:
    m = report.machine
    lines = [f"# seqat bench fuzz ({report.date})", "",
             f"seeds {report.seeds}, {report.cases_per_seed} cases per seed, "
             f"{report.wall_s:.0f} s; {m.cpu_count} cores ({m.cpu_model}), "  # type: ignore[attr-defined]
             f"load {m.load_average_1m:.2f} -> {m.load_average_1m_end:.2f}", "",  # type: ignore[attr-defined]
             "| " + " | ".join(SUMMARY_HEADER) + " |",
             "|" + "---|" * len(SUMMARY_HEADER),
             "| " + " | ".join(summary_row(report)) + " |", ""]
    lines += ["| mutation | cases | run exit 0 | run exit 2 | failing |", "|---|---|---|---|---|"]
    for kind, row in by_mutation(report).items():
        lines.append(f"| {kind} | " + " | ".join(str(v) for v in row) + " |")
    lines.append("")
    if report.sample_data_changed:
        lines += [f"sample data changed: {', '.join(report.sample_data_changed)}", ""]
    fails = failing_rows(report)
    if fails:
        lines += ["| seed/case | flight | mutation | defects | message |", "|---|---|---|---|---|"]
        lines += ["| " + " | ".join(x.replace("|", "\\|") for x in row) + " |" for row in fails]
        lines.append("")
    return "\n".join(lines)


def report_dict(report: FuzzReport) -> dict:
    return to_jsonable(dataclasses.asdict(report))  # type: ignore[no-any-return]


def write_outputs(report: FuzzReport, out: Path) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(case_rows(report))
    write_files_atomically(out, {
        "fuzz.csv": buf.getvalue(),
        "fuzz.json": json.dumps(report_dict(report), indent=1, allow_nan=False) + "\n",
        "fuzz.md": render_markdown(report),
    })
