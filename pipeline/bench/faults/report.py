"""Markdown tables of ``seqat bench faults`` (``faults.md``; docs/benchmarks.md quotes them).

Ratios compare a run with its reference: blunder runs with the *oracle* (the same seed
without the blundered observations), the others with the clean run without snooping. The
ratio shown is the worst of the components (X, Y, Z, ω, φ, κ for EOPs; X, Y, Z for GPs).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping, Sequence

import numpy as np

from pipeline.bench.faults.cases import OFF, ON, ORACLE, SIM, FaultBenchReport, FaultRun

#: Rows of a case in this order of faults' first word and variants.
VARIANT_ORDER = (ORACLE, ON, OFF, SIM)


def _f(value: float | None, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value:.{digits}f}"


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _t(t: Sequence[float], digits: int = 3) -> str:
    return " / ".join(_f(v, digits) for v in t)


def _reference(run: FaultRun, runs: Sequence[FaultRun]) -> FaultRun | None:
    """Blunder runs: the oracle; a jump or dropout with snooping on: the clean run with it
    on; everything else: the clean run without snooping."""
    same = [r for r in runs if r.case == run.case and r.seed == run.seed and not r.error]
    if run.fault.startswith("blunders") and run.variant != ORACLE:
        return next((r for r in same if r.fault == run.fault and r.variant == ORACLE), None)
    if (run.fault == "clean" and run.variant == OFF) or run.variant == ORACLE:
        return None
    variant = ON if run.variant == ON and run.fault != "clean" else OFF
    return next((r for r in same if r.fault == "clean" and r.variant == variant), None)


def worst_ratios(run: FaultRun, ref: FaultRun | None) -> tuple[float, float]:
    """Largest EOP and GP RMSE component ratio of ``run`` to ``ref`` (NaN without one)."""
    if ref is None or run.error:
        return math.nan, math.nan
    e = np.asarray(run.pos_rmse_m + run.att_rmse_deg) / np.asarray(ref.pos_rmse_m
                                                                   + ref.att_rmse_deg)
    g = np.asarray(run.gp_rmse_m) / np.asarray(ref.gp_rmse_m)
    return float(np.nanmax(e)), float(np.nanmax(g))


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out + [""]


def _order(runs: Sequence[FaultRun]) -> list[FaultRun]:
    faults = list(dict.fromkeys(r.fault for r in runs))
    return sorted(runs, key=lambda r: (r.seed, faults.index(r.fault),
                                       VARIANT_ORDER.index(r.variant)))


def summary_rows(report: FaultBenchReport) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the short console summary (case, fault, variant, ratios, detection)."""
    header = ["case", "fault", "variant", "EOP ÷ ref", "GP ÷ ref", "precision", "recall",
              "jump flagged", "dropout max ÷ nbr"]
    rows = []
    for case in report.cases:
        for row in _summary_cells(case, report.runs):
            rows.append([case, row[0], row[1], row[3], row[4], row[7], row[8], row[9], row[10]])
    return header, rows


def _summary(case: str, runs: Sequence[FaultRun]) -> list[str]:
    return _table(["fault", "variant", "runs ok", "EOP ÷ ref, mean / max", "GP ÷ ref, mean / max",
                   "GPs off > limit", "rejected", "precision", "recall", "jump flagged",
                   "dropout max ÷ nbr rms (worst)", "update ms median"],
                  _summary_cells(case, runs))


def _summary_cells(case: str, runs: Sequence[FaultRun]) -> list[list[str]]:
    rows = []
    mine = [r for r in runs if r.case == case]
    keys = list(dict.fromkeys((r.fault, r.variant) for r in _order(mine)))
    for fault, variant in keys:
        sel = [r for r in mine if r.fault == fault and r.variant == variant]
        ok = [r for r in sel if not r.error]
        ratios = [worst_ratios(r, _reference(r, runs)) for r in ok]
        e = [x for x, _ in ratios if math.isfinite(x)]
        g = [y for _, y in ratios if math.isfinite(y)]
        det = [r.detection for r in ok if r.detection is not None]
        jump = [r.jump_flagged for r in ok if r.jump_flagged is not None]
        gap = [r.dropout_position for r in ok if r.dropout_position is not None]
        rows.append([
            fault, variant, f"{len(ok)}/{len(sel)}",
            f"{_f(float(np.mean(e)), 2)} / {_f(max(e), 2)}" if e else "–",
            f"{_f(float(np.mean(g)), 2)} / {_f(max(g), 2)}" if g else "–",
            _f(float(np.mean([r.gp_outliers for r in ok])), 1) if ok else "–",
            _f(float(np.mean([r.rejected for r in ok])), 1) if ok else "–",
            _f(_mean([d.precision for d in det]), 3),
            _f(_mean([d.recall for d in det]), 3),
            f"{sum(jump)}/{len(jump)}" if jump else "–",
            _f(max(s.ratio_max for s in gap), 2) if gap else "–",
            _f(float(np.median([r.update_ms_median for r in ok])), 1) if ok else "–",
        ])
    return rows


def _accuracy(case: str, runs: Sequence[FaultRun]) -> list[str]:
    rows = []
    for r in _order([r for r in runs if r.case == case]):
        if r.error:
            rows.append([str(r.seed), r.fault, r.variant, "failed: " + r.error] + [""] * 9)
            continue
        e, g = worst_ratios(r, _reference(r, runs))
        rows.append([str(r.seed), r.fault, r.variant, str(r.n_images), _t(r.pos_rmse_m),
                     _t(r.att_rmse_deg, 4), _t(r.gp_rmse_m), str(r.gp_outliers), str(r.rejected),
                     _f(r.sigma0, 2), _f(e, 2), _f(g, 2),
                     f"{_f(r.update_ms_median, 1)} / {_f(r.update_ms_p95, 1)}"])
    return _table(["seed", "fault", "variant", "images", "pos RMSE X/Y/Z (m)",
                   "att RMSE ω/φ/κ (°)", "GP RMSE X/Y/Z (m)", "GPs off", "rejected", "σ0",
                   "EOP ÷ ref", "GP ÷ ref", "update ms median / p95"], rows)


def _detection(case: str, runs: Sequence[FaultRun]) -> list[str]:
    rows = []
    for r in _order([r for r in runs if r.case == case and r.detection is not None
                     and r.variant == ON]):  # without snooping nothing is rejected
        d, t = r.detection, r.detection_testable
        assert d is not None
        rows.append([str(r.seed), r.fault, str(d.injected), str(d.rejected),
                     str(d.true_positives), _f(d.precision), _f(d.recall),
                     f"{_f(t.recall)} ({t.injected})" if t is not None else "–"])
    return _table(["seed", "fault", "injected", "rejected", "true positives", "precision",
                   "recall", "recall of testable (count)"], rows) + [
        "Testable: blunders of points with at least `min_rays` observations (a point seen "
        "fewer times never enters with snooping on).", ""]


def _jump(case: str, runs: Sequence[FaultRun], report: FaultBenchReport) -> list[str]:
    rows = []
    for r in _order([r for r in runs if r.case == case and r.fault.startswith("jump")]):
        setup = next(s for s in report.setups if s.case == case and s.seed == r.seed)
        others = [n for n in r.nav_downweighted if n != f"{setup.jump_image}: position"]
        e, _ = worst_ratios(r, _reference(r, runs))
        rows.append([str(r.seed), setup.jump_image, r.variant,
                     "–" if r.error else ("yes" if r.jump_flagged else "no"),
                     str(len(others)), _f(r.jump_error_m), _f(e, 2), r.error[:60]])
    return _table(["seed", "image", "variant", "flagged", "other nav groups down-weighted",
                   "error at jump image (m)", "EOP ÷ clean", "failure"], rows)


def report_from_json(doc: Mapping[str, object]) -> FaultBenchReport:
    """A :class:`FaultBenchReport` from ``faults.json`` (``null`` numbers become NaN), to
    render the tables again without running the benchmark."""
    return _build(FaultBenchReport, doc)  # type: ignore[no-any-return]


def _build(tp: object, value: object) -> object:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(tp) and isinstance(value, Mapping):
        hints = typing.get_type_hints(tp)
        return tp(**{f.name: _build(hints[f.name], value[f.name])  # type: ignore[operator]
                     for f in dataclasses.fields(tp) if f.name in value})
    if origin in (types.UnionType, typing.Union):
        if value is None and type(None) in args:
            return None
        return _build(next(a for a in args if a is not type(None)), value)
    if origin is tuple and isinstance(value, list):
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_build(args[0], v) for v in value)
        return tuple(_build(a, v) for a, v in zip(args, value, strict=True))
    if tp is float:
        return math.nan if value is None else float(value)  # type: ignore[arg-type]
    return value


def _dropout(case: str, runs: Sequence[FaultRun], report: FaultBenchReport) -> list[str]:
    rows = []
    for r in _order([r for r in runs if r.case == case and r.fault.startswith("dropout")]):
        setup = next(s for s in report.setups if s.case == case and s.seed == r.seed)
        p, a = r.dropout_position, r.dropout_attitude
        if r.error or p is None or a is None:
            rows.append([str(r.seed), str(len(setup.dropout_images)), r.variant,
                         "failed: " + r.error] + [""] * 6)
            continue
        rows.append([str(r.seed), f"{len(setup.dropout_images)} ({setup.dropout_span_s:.1f} s)",
                     r.variant, str(r.skipped), _f(p.gap_max), _f(p.gap_rms),
                     _f(p.neighbour_rms), f"{_f(p.ratio_max, 2)} / {_f(p.ratio_rms, 2)}",
                     f"{_f(a.ratio_max, 2)} / {_f(a.ratio_rms, 2)}",
                     _f(worst_ratios(r, _reference(r, runs))[0], 2)])
    return _table(["seed", "images (span)", "variant", "skipped", "pos error max (m)",
                   "pos rms (m)", "neighbours rms (m)", "pos max / rms ÷ nbr rms",
                   "att max / rms ÷ nbr rms", "EOP ÷ clean"], rows)


def _span(images: Sequence[str]) -> str:
    return f"{len(images)}: {images[0]}–{images[-1]}" if images else "0"


def render_fault_markdown(report: FaultBenchReport) -> str:
    """All tables of a fault benchmark, one section per case."""
    o, m = report.options, report.machine
    lines = [f"# Fault benchmark ({report.date})", "",
             f"Seeds {', '.join(map(str, report.seeds))}; runtime {report.runtime_s:.0f} s; "
             f"{m.cpu_count} CPUs ({m.cpu_model}), 1-min load {m.load_average_1m:.1f} at the "
             f"start, {m.load_average_1m_end:.1f} at the end.",
             f"Blunders {', '.join(f'{100 * b:g} %' for b in o.blunder_fractions)} "
             f"({o.blunder_min_px:g}–{o.blunder_max_px:g} px); jump {o.jump_m:g} m; dropout "
             f"{o.dropout_s:g} s. Seq-R ρ ≥ {o.threshold:g}, RTS-smoothed; snooping on: "
             f"critical w {o.snooping_critical:g}, min_rays {o.min_rays}. GPs off: error > "
             f"{o.gp_outlier_m:g} m. Ratios: worst component; blunder runs ÷ oracle, jump and "
             "dropout ÷ clean with the same snooping setting, clean with snooping ÷ clean "
             "without.", ""]
    for case in report.cases:
        lines += [f"## {case}", ""]
        setups = [s for s in report.setups if s.case == case]
        lines += _table(["seed", "images", "observations", "blunders", "jump image",
                         "dropout images"],
                        [[str(s.seed), str(s.n_images), str(s.n_observations),
                          " / ".join(map(str, s.blunders)), s.jump_image, _span(s.dropout_images)]
                         for s in setups])
        lines += ["### Summary (over seeds)", ""] + _summary(case, report.runs)
        lines += ["### Blunder detection", ""] + _detection(case, report.runs)
        lines += ["### GNSS jump", ""] + _jump(case, report.runs, report)
        lines += ["### GNSS dropout", ""] + _dropout(case, report.runs, report)
        lines += ["### Accuracy per run", ""] + _accuracy(case, report.runs)
    return "\n".join(lines)
