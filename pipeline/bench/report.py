"""Typed report of the benchmark (:mod:`pipeline.bench.strip`) and its rendering: figures, markdown.

The report types are frozen dataclasses serialised to ``bench.json``; :func:`write_figures`
draws seed 000's Figures 4-11 (matplotlib, Agg) and :func:`render_markdown` writes ``bench.md``
with the paper's values beside the measured ones and PASS/FAIL computed from the targets.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from seqat.simulate import StripSimConfig

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Triple = tuple[float, float, float]

# ---------------------------------------------------------------------------- targets
#: Seed 000 §3.2: RMSE of the GPS/INS input ("direct") and of every AT method, overall r.m.s.
#: of the three components: position m, attitude deg, ground points m.
PAPER_DIRECT = (0.32, 0.1, 1.0)
PAPER_AT = (0.18, 0.05, 0.10)
#: Seq-R / Seq-F RMSE may differ from Sim's by at most this fraction, on every component.
TARGET_RMSE_REL_TO_SIM = 0.05
#: Standard deviation of the GP differences to Sim, per component, metres (seed 000 Fig. 7).
TARGET_GP_DIFF_STD_M = 0.01
#: Seq-R update time per image: median and 99th percentile, milliseconds.
TARGET_MEDIAN_MS = 2.0
TARGET_P99_MS = 10.0
#: Median update time of a late block of images over an early block (bounded cost per image).
TARGET_LATE_EARLY_RATIO = 1.2
#: Stage label of the initial simultaneous images of the sequential methods (not timed).
INITIAL_STAGE = "initial-sim"
#: Figure resolution, dots per inch (small PNGs for the docs).
FIGURE_DPI = 90
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Lower y limit of Fig. 7 (cm): before the sequential stage the methods agree to ~1e-7 cm.
FIG7_MIN_CM = 0.01


class Method(enum.StrEnum):
    """Methods compared (seed 000 §3)."""

    DIRECT = "direct"
    SEQ_R = "seq-r"
    SEQ_R_SMOOTHED = "seq-r-smoothed"  # final values after the RTS backward pass
    SEQ_F = "seq-f"
    SIM = "sim"


#: Methods compared with Sim (differences, checks).
SEQUENTIAL = (Method.SEQ_R, Method.SEQ_R_SMOOTHED, Method.SEQ_F)


# ---------------------------------------------------------------------------- report types
def rms_of(t: Triple) -> float:
    """r.m.s. of three components (NaN propagates)."""
    return float(np.sqrt(np.mean(np.square(t))))


@dataclass(frozen=True, kw_only=True)
class Accuracy:
    """RMSE against truth per component, and the r.m.s. over the three (the paper's figures)."""

    pos_rmse_m: Triple
    att_rmse_deg: Triple
    gp_rmse_m: Triple
    pos_m: float
    att_deg: float
    gp_m: float
    n_images: int
    n_points: int

    @classmethod
    def from_rmse(cls, pos: Triple, att: Triple, gp: Triple, *, n_images: int,
                  n_points: int) -> Accuracy:
        """From the per-component RMSEs; the single figures are their r.m.s."""
        return cls(pos_rmse_m=pos, att_rmse_deg=att, gp_rmse_m=gp, pos_m=rms_of(pos),
                   att_deg=rms_of(att), gp_m=rms_of(gp), n_images=n_images,
                   n_points=n_points)


@dataclass(frozen=True, kw_only=True)
class Timing:
    """Update time per image of the timed images (sequential stage; Sim: its refits)."""

    mode: str
    n_timed: int
    median_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float
    mean_ms: float
    early_images: tuple[int, int]  # 0-based, end excluded
    late_images: tuple[int, int]
    early_median_ms: float
    late_median_ms: float
    late_early_ratio: float


@dataclass(frozen=True, kw_only=True)
class Series:
    """What the estimator reported after each image (seed 000 Figs 8-11); NaN where none."""

    stage: tuple[str, ...]
    update_ms: tuple[float, ...]
    window_images: tuple[int, ...]
    window_params: tuple[int, ...]
    gp_params: tuple[int, ...]  # Sim: order of N_pp
    inverse_a: tuple[int, ...]  # order of [I + P2bar A21 N11^-1 A21^T]
    inverse_b: tuple[int, ...]  # order of (M22 + L22)
    sim_reduced_size: tuple[int, ...]  # Sim: order of N_r
    sigma0: tuple[float, ...]
    rms_gp_sigma_m: tuple[float, ...]  # r.m.s. over X, Y, Z


@dataclass(frozen=True, kw_only=True)
class MethodRun:
    """One method on one seed."""

    method: str
    label: str
    threshold: float | None
    accuracy: Accuracy
    timing: Timing | None
    run_s: float
    final_sigma0: float
    series: Series | None


@dataclass(frozen=True, kw_only=True)
class DiffVsSim:
    """Final estimates of a sequential method minus Sim's (images and common points)."""

    label: str
    pos_rms_m: Triple
    att_rms_deg: Triple
    gp_rms_m: Triple
    gp_std_m: Triple
    n_points: int


@dataclass(frozen=True, kw_only=True)
class SeedResult:
    seed: int
    n_images: int
    n_points: int
    n_observations: int
    methods: tuple[MethodRun, ...]
    differences: tuple[DiffVsSim, ...]


@dataclass(frozen=True, kw_only=True)
class Curve:
    """RMSE of all current estimates after image ``image_count`` (first seed; Figs 4-7)."""

    label: str
    image_count: tuple[int, ...]
    pos_m: tuple[float, ...]
    att_deg: tuple[float, ...]
    gp_m: tuple[float, ...]
    gp_diff_std_m: tuple[Triple, ...]  # vs Sim at the same image (NaN: no Sim snapshot)


@dataclass(frozen=True, kw_only=True)
class Check:
    """One target: ``passed`` is ``value <= target`` (``abs(value)`` when ``two_sided``)."""

    label: str
    name: str
    value: float
    target: float
    unit: str
    two_sided: bool
    passed: bool


@dataclass(frozen=True, kw_only=True)
class Machine:
    platform: str
    python: str
    numpy: str
    scipy: str
    cpu_count: int
    cpu_model: str
    load_average_1m: float  # at the start of the benchmark
    load_average_1m_end: float  # other processes compete for the CPUs: timings are noisy


@dataclass(frozen=True, kw_only=True)
class BenchReport:
    config_path: str
    simulation: StripSimConfig
    seeds: tuple[int, ...]
    thresholds: tuple[float, ...]
    sim_mode: str
    date: str
    runtime_s: float
    machine: Machine
    results: tuple[SeedResult, ...]
    summary: tuple[MethodRun, ...]  # accuracy: mean over seeds; timing: all seeds pooled
    checks: tuple[Check, ...]
    curves: tuple[Curve, ...]
    figures: tuple[str, ...]


def mean_triple(ts: Sequence[Triple]) -> Triple:
    """Component-wise mean of triples (e.g. per-seed RMSEs)."""
    m = np.mean(np.asarray(ts, dtype=np.float64), axis=0)
    return (float(m[0]), float(m[1]), float(m[2]))


# ---------------------------------------------------------------------------- figures
def write_figures(first: SeedResult, curves: Sequence[Curve], fig_dir: Path) -> list[Path]:
    """Seed 000's Figures 4-11 and the σ plots of one seed as PNGs in ``fig_dir``.

    Parameters
    ----------
    first : SeedResult
        The seed the per-image series come from (Figs 8-11, σ).
    curves : sequence of Curve
        Per-image RMSE and GP-difference curves of the same seed (Figs 4-7).
    fig_dir : Path

    Returns
    -------
    list of Path
        The files written, sorted by name.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_dir.mkdir(parents=True, exist_ok=True)
    colours = {"Direct (GPS/INS)": "tab:green", "Seq-F": "tab:blue", "Sim": "tab:pink"}
    reds = iter(["tab:red", "tab:orange", "tab:brown", "tab:purple", "tab:olive", "tab:cyan",
                 "black"])
    for m in first.methods:
        colours.setdefault(m.label, next(reds, "tab:gray"))
    seq_r = next(m for m in first.methods if m.method == Method.SEQ_R)
    seq_f = next(m for m in first.methods if m.method == Method.SEQ_F)
    sim = next(m for m in first.methods if m.method == Method.SIM)
    paths: list[Path] = []
    x_label = "images acquired"

    def save(fig: Figure, name: str) -> None:
        path = fig_dir / name
        fig.savefig(path, dpi=FIGURE_DPI, bbox_inches="tight")
        plt.close(fig)
        paths.append(path)

    for name, attr, unit, fig_no in (
        ("fig04_position_rmse.png", "pos_m", "m", 4),
        ("fig05_attitude_rmse.png", "att_deg", "deg", 5),
        ("fig06_gp_rmse.png", "gp_m", "m", 6),
    ):
        fig, ax = plt.subplots(figsize=(7, 4))
        for c in curves:
            ax.plot(
                c.image_count,
                getattr(c, attr),
                label=c.label,
                color=colours[c.label],
                lw=1.2,
                ls="--" if c.label == "Sim" else "-",
            )
        what = {4: "EOP position", 5: "EOP attitude", 6: "ground points"}[fig_no]
        ax.set(
            xlabel=x_label,
            ylabel=f"RMSE ({unit}, r.m.s. of 3 components)",
            title=f"RMSE of {what} after each image (seed 000 Fig. {fig_no}, seed {first.seed})",
        )
        if fig_no == 6:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        save(fig, name)

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6), sharey=True)
    for c in curves:
        d = np.asarray(c.gp_diff_std_m, dtype=np.float64)
        if not np.any(np.isfinite(d)):
            continue
        for k, ax in enumerate(axes):
            ax.plot(c.image_count, 100 * d[:, k], label=f"{c.label} − Sim", color=colours[c.label])
    for k, ax in enumerate(axes):
        ax.set(xlabel=x_label, title=f"GP {'XYZ'[k]}", yscale="log")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("std of GP difference (cm)")
    axes[0].set_ylim(bottom=FIG7_MIN_CM)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Std of ground point differences to Sim (seed 000 Fig. 7, seed {first.seed})")
    save(fig, "fig07_gp_diff_std.png")

    def time_plot(methods: Sequence[MethodRun], title: str, name: str, log: bool) -> None:
        fig, ax = plt.subplots(figsize=(7, 4))
        for m in methods:
            assert m.series is not None
            ms = np.asarray(m.series.update_ms, dtype=np.float64)
            x = np.arange(1, ms.size + 1)
            ok = np.isfinite(ms)
            ax.plot(
                x[ok],
                ms[ok],
                label=m.label,
                color=colours[m.label],
                lw=0.9,
                marker="." if m.method == Method.SIM and not np.all(ok) else None,
            )
        ax.set(xlabel=x_label, ylabel="update time per image (ms)", title=title)
        if log:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        save(fig, name)

    sim_mode = sim.timing.mode if sim.timing is not None else ""
    time_plot(
        [seq_r, seq_f, sim],
        f"Processing time per image (seed 000 Fig. 8; Sim: {sim_mode})",
        "fig08_time_per_image.png",
        log=True,
    )
    time_plot(
        [m for m in first.methods if m.method in (Method.SEQ_R, Method.SEQ_F)],
        "Processing time, sequential methods (seed 000 Fig. 10)",
        "fig10_time_zoom.png",
        log=False,
    )

    fig, ax = plt.subplots(figsize=(7, 4))
    x = np.arange(1, first.n_images + 1)
    for m, style in ((seq_r, "-"), (seq_f, ":")):
        assert m.series is not None
        seq = np.asarray(m.series.stage) != INITIAL_STAGE
        ax.plot(
            x[seq],
            np.asarray(m.series.inverse_a)[seq],
            style,
            color="tab:red",
            lw=0.9,
            label=f"{m.label}: [I + P̄₂A₂₁N₁₁⁻¹A₂₁ᵀ]",
        )
        ax.plot(
            x[seq],
            np.asarray(m.series.inverse_b)[seq],
            style,
            color="tab:blue",
            lw=0.9,
            label=f"{m.label}: (M₂₂ + L₂₂)",
        )
    assert sim.series is not None
    nr = np.asarray(sim.series.sim_reduced_size, dtype=np.float64)
    ok = nr > 0
    ax.plot(x[ok], nr[ok], color="tab:pink", label="Sim: N_r (6 × images)")
    ax.plot(x, sim.series.gp_params, color="tab:purple", ls="--", label="Sim: N_pp (3 × points)")
    ax.set(
        xlabel=x_label,
        ylabel="order of the inverted matrix",
        yscale="log",
        title="Dimension of the inverse matrices (seed 000 Fig. 9)",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    save(fig, "fig09_inverse_sizes.png")

    fig, ax = plt.subplots(figsize=(7, 4))
    for m in first.methods:
        if m.method in (Method.SEQ_R, Method.SEQ_F):
            assert m.series is not None
            same_as_default = "without RTS gains" in m.label  # the same window, drawn dotted
            ax.plot(x, m.series.window_params, label=m.label, color=colours[m.label], lw=1.0,
                    ls=":" if same_as_default else "-")
    ax.set(
        xlabel=x_label,
        ylabel="parameters in the update (window)",
        title="Size of the parameter vector (seed 000 Fig. 11)",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save(fig, "fig11_window_size.png")

    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 3.6))
    for m in first.methods:
        if m.series is None:
            continue
        a0.plot(x, m.series.sigma0, label=m.label, color=colours[m.label], lw=0.9)
        a1.plot(
            x,
            100 * np.asarray(m.series.rms_gp_sigma_m, dtype=np.float64),
            label=m.label,
            color=colours[m.label],
            lw=0.9,
        )
    a0.set(xlabel=x_label, ylabel="σ0 (a posteriori, unitless)", title="σ0 after each image")
    a1.set(
        xlabel=x_label,
        ylabel="r.m.s. GP σ (cm)",
        yscale="log",
        title="r.m.s. σ of the ground points in the update (window)",
    )
    for a in (a0, a1):
        a.grid(alpha=0.3)
    a0.legend(fontsize=8)
    save(fig, "sigma_per_image.png")
    return sorted(paths)


# ---------------------------------------------------------------------------- markdown
def _f(v: float, digits: int) -> str:
    return f"{v:.{digits}f}" if math.isfinite(v) else "—"


def _t(t: Triple, digits: int) -> str:
    return " / ".join(_f(v, digits) for v in t)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def render_markdown(report: BenchReport) -> str:
    """``bench.md``: settings, machine, accuracy, timing, differences to Sim, checks."""
    m = report.machine
    seeds = ", ".join(str(s) for s in report.seeds)
    first = report.results[0]
    out = [
        f"# seqat benchmark — {Path(report.config_path).name}\n",
        f"- date: {report.date}; runtime {report.runtime_s:.0f} s",
        f"- machine: {m.cpu_model}, {m.cpu_count} CPUs, {m.platform}, Python {m.python}, "
        f"numpy {m.numpy}, scipy {m.scipy}; 1-min load average {m.load_average_1m:.2f} at the "
        f"start, {m.load_average_1m_end:.2f} at the end",
        f"- strip: {first.n_images} images, {first.n_points} points, "
        f"{first.n_observations} image points (seed {first.seed}); seeds {seeds}",
        f"- Seq-R thresholds: {', '.join(f'{t:g}' for t in report.thresholds)}; "
        f"Sim: {report.sim_mode} (estimates only, no covariance)",
        "- accuracy: mean over seeds of each seed's RMSE vs truth (r.m.s. of the components "
        "for the single figures); timing: all seeds pooled; checks: worst seed",
        "- Seq-R rows are the real-time values (parameters that left the window keep their "
        "estimate at departure, as in the paper); *RTS-smoothed* rows are the same run's final "
        "solution after the backward pass of `SequentialAT.solution()`\n",
    ]
    out.append("## Accuracy (final solution vs truth)\n")
    rows = []
    for r in report.summary:
        paper = PAPER_DIRECT if r.method == Method.DIRECT else PAPER_AT
        a = r.accuracy
        rows.append(
            [
                r.label,
                _f(a.pos_m, 3),
                _f(paper[0], 2),
                _f(a.att_deg, 4),
                _f(paper[1], 2),
                _f(a.gp_m, 3),
                _f(paper[2], 2),
                str(a.n_points),
            ]
        )
    out.append(
        _table(
            ["method", "position m", "paper", "attitude °", "paper", "GP m", "paper", "GPs"], rows
        )
    )
    out.append("\nPer component (X / Y / Z m; ω / φ / κ °; GP X / Y / Z m):\n")
    out.append(
        _table(
            ["method", "position", "attitude", "ground points"],
            [
                [
                    r.label,
                    _t(r.accuracy.pos_rmse_m, 3),
                    _t(r.accuracy.att_rmse_deg, 4),
                    _t(r.accuracy.gp_rmse_m, 3),
                ]
                for r in report.summary
            ],
        )
    )
    out.append("\nPer seed (position m / attitude ° / GP m):\n")
    out.append(
        _table(
            ["method", *[f"seed {s.seed}" for s in report.results]],
            [
                [
                    r.label,
                    *[
                        f"{_f(s.methods[i].accuracy.pos_m, 3)} / "
                        f"{_f(s.methods[i].accuracy.att_deg, 4)} / "
                        f"{_f(s.methods[i].accuracy.gp_m, 3)}"
                        for s in report.results
                    ],
                ]
                for i, r in enumerate(report.summary)
            ],
        )
    )
    out.append("\n## Update time per image\n")
    rows = []
    for r in report.summary:
        t = r.timing
        if t is None:
            continue
        rows.append(
            [
                r.label,
                t.mode,
                str(t.n_timed),
                _f(t.median_ms, 2),
                _f(t.p95_ms, 2),
                _f(t.p99_ms, 2),
                _f(t.max_ms, 1),
                f"{_f(t.early_median_ms, 2)} ({t.early_images[0]}-{t.early_images[1]})",
                f"{_f(t.late_median_ms, 2)} ({t.late_images[0]}-{t.late_images[1]})",
                _f(t.late_early_ratio, 2),
                _f(r.run_s, 1),
            ]
        )
    out.append(
        _table(
            [
                "method",
                "timed",
                "n",
                "median ms",
                "p95 ms",
                "p99 ms",
                "max ms",
                "early median ms",
                "late median ms",
                "late/early",
                "run s/seed",
            ],
            rows,
        )
    )
    out.append("\n## Final differences to Sim (mean over seeds)\n")
    rows = []
    for i, d in enumerate(report.results[0].differences):
        ds = [s.differences[i] for s in report.results]
        rows.append(
            [
                d.label,
                _t(mean_triple([x.pos_rms_m for x in ds]), 4),
                _t(mean_triple([x.att_rms_deg for x in ds]), 5),
                _t(mean_triple([x.gp_rms_m for x in ds]), 4),
                _t(mean_triple([x.gp_std_m for x in ds]), 4),
                str(int(np.mean([x.n_points for x in ds]))),
            ]
        )
    out.append(
        _table(
            [
                "method",
                "position RMS m (X/Y/Z)",
                "attitude RMS ° (ω/φ/κ)",
                "GP RMS m (X/Y/Z)",
                "GP std m (X/Y/Z)",
                "common GPs",
            ],
            rows,
        )
    )
    out.append("\n## Targets\n")
    out.append(
        _table(
            ["method", "check", "value", "target", "result"],
            [
                [
                    c.label,
                    c.name,
                    f"{_f(c.value, 3)} {c.unit}".strip(),
                    (
                        f"within ±{c.target:g} {c.unit}"
                        if c.two_sided
                        else f"≤ {c.target:g} {c.unit}"
                    ).strip(),
                    "PASS" if c.passed else "FAIL",
                ]
                for c in report.checks
            ],
        )
    )
    out.append(f"\n## Figures (seed {first.seed})\n")
    out += [f"![{Path(f).stem}]({f})" for f in report.figures]
    return "\n".join(out) + "\n"
