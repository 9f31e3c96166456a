"""``seqat bench``: every benchmark (docs/benchmarks.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from pipeline.cli.common import DEGREE_FORMAT, METRE_FORMAT, console, fmt, guarded, table

app = typer.Typer()

#: ``seqat bench faults``: the fault benchmark instead of a config.
FAULTS_BENCH = "faults"
#: ``seqat bench rendered RUN --config CONFIG.yaml [--json FILE]``: products of a rendered
#: flight against its truth (:mod:`pipeline.bench.rendered`; its own arguments follow).
RENDERED_BENCH = "rendered"
#: ``seqat bench ortho --out DIR [--images N] [--no-occlusion] [--no-write] [--sync-writes]
#: [--live MODE] [--rate-hz R] [--nice N]``: timing of the ortho stage
#: (:mod:`pipeline.bench.ortho`; its own arguments follow).
ORTHO_BENCH = "ortho"
#: ``seqat bench gtsam [--seed N ...] [--lag N ...] [--out DIR] [--config CONFIG.yaml]
#: [--extra-updates N] [--sigma pose|all ...]``: GTSAM's fixed-lag smoother beside Seq-R on
#: simulated strips (:mod:`pipeline.bench.gtsam`, optional package gtsam; its own arguments
#: follow).
GTSAM_BENCH = "gtsam"
#: ``seqat bench fuzz [--seed S ...] [--cases N] [--case K ...] [--jobs J] [--timeout-s T]
#: [--kind KIND ...] [--flight NAME ...] [--keep]``: seeded mutations of the sample flights run
#: as subprocesses (:mod:`pipeline.bench.fuzz.suite`; its own arguments follow).
FUZZ_BENCH = "fuzz"
#: ``seqat bench live --out DIR [--flight F] [--clients N ...] [--repeat K] [--rate-hz R]
#: [--limit N] [--page sse|poll]``: the live map's targets, seqat feed into seqat watch
#: --ortho --serve with page-like clients (:mod:`pipeline.bench.live`; its own arguments
#: follow).
LIVE_BENCH = "live"
#: ``seqat bench dask --out DIR [--flights N] [--repeats R] [--no-kill]``: a campaign's ortho
#: and mosaic stages on 1 and 2 Dask workers, pixel equality, a worker killed
#: (:mod:`pipeline.bench.campaign`; its own arguments follow).
DASK_BENCH = "dask"


def _passes_arguments(config: Path) -> bool:
    """Only the rendered, ortho, gtsam, fuzz, live and dask benchmarks take arguments of their
    own."""
    return not config.exists() and str(config) in (RENDERED_BENCH, ORTHO_BENCH, GTSAM_BENCH,
                                                   FUZZ_BENCH, LIVE_BENCH, DASK_BENCH)


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def bench(
    ctx: typer.Context,
    config: Annotated[Path, typer.Argument(
        help="Simulation config (configs/*_sim.yaml), an image flight folder, or 'long' "
             "(memory and time along a 10,000-image strip); 'faults' (seeded faults), "
             "'rendered RUN --config CONFIG.yaml' (a rendered flight's products against its "
             "truth), 'ortho' (timing of the ortho stage), 'gtsam' (GTSAM's fixed-lag "
             "smoother beside Seq-R; --lag, --config), 'fuzz' (seeded bad inputs; --cases, "
             "--case K replays one), 'live' (the live map: feed into watch --ortho --serve "
             "with page-like clients; --flight, --clients, --repeat, --page) or 'dask' (a "
             "campaign on 1 and 2 Dask workers; --flights, --repeats; see docs/benchmarks.md).")],
    out: Annotated[Path, typer.Option("--out", help="Benchmark output folder.")] = Path(
        "out/bench"),
    seed: Annotated[list[int] | None, typer.Option(
        "--seed", help="Seed of one simulated flight (repeat for several).")] = None,
    threshold: Annotated[list[float] | None, typer.Option(
        "--threshold", help="Seq-R correlation threshold (repeat for several).")] = None,
    case: Annotated[list[str] | None, typer.Option(
        "--case", help="bench faults: strip, block or rendered (repeat; default all); bench "
                       "fuzz: a case index to replay (with --seed).")] = None,
    strip_config: Annotated[Path, typer.Option(
        "--strip-config", help="bench faults: config of the strip case.")] = Path(
        "configs/paper_sim.yaml"),
    rendered: Annotated[Path, typer.Option(
        "--rendered", help="bench faults: flight folder (with truth/) of the rendered case.")]
    = Path("sample_data/autzen_rendered"),
) -> None:
    """Compare direct georeferencing, Seq-R, Seq-F and Sim on simulated flights, or, for an
    image flight folder, Seq-R (tracking) with Sim and Seq-F on the same tie points.
    seqat bench faults: seeded blunders, a GNSS jump and a dropout; seqat bench rendered,
    ortho, gtsam, fuzz and live take the arguments of their modules (docs/benchmarks.md)."""
    if ctx.args and not _passes_arguments(config):
        first = ctx.args[0]
        ctx.fail(f"No such option: {first}" if first.startswith("-") else
                 f"Got unexpected extra argument ({' '.join(ctx.args)})")
    _bench(ctx=ctx, config=config, out=out, seed=seed, threshold=threshold, case=case,
           strip_config=strip_config, rendered=rendered)


@guarded
def _bench(*, ctx: typer.Context, config: Path, out: Path, seed: list[int] | None,
           threshold: list[float] | None, case: list[str] | None, strip_config: Path,
           rendered: Path) -> None:
    """The body of :func:`bench` under the exit-code contract."""
    from pipeline.bench.strip import run_bench
    from pipeline.common.outdir import check_not_input

    name = str(config) if not config.exists() else None
    check_not_input(out, [config if config.exists() else None,
                          *((strip_config, rendered) if name == FAULTS_BENCH else ()),
                          *(_fuzz_inputs() if name == FUZZ_BENCH else ())])
    if name == RENDERED_BENCH:
        from pipeline.bench.rendered import main as rendered_main

        rendered_main(ctx.args)
        return
    if name == ORTHO_BENCH:
        from pipeline.bench.ortho import main as ortho_main

        ortho_main(["--out", str(out), *ctx.args])
        return
    if name == DASK_BENCH:
        from pipeline.bench.campaign import main as dask_main

        dask_main(["--out", str(out), *ctx.args])
        return
    if name == GTSAM_BENCH:
        from pipeline.bench.gtsam import main as gtsam_main

        seeds = [arg for s in seed or () for arg in ("--seed", str(s))]
        gtsam_main(["--out", str(out), *seeds, *ctx.args])
        return
    if name == FUZZ_BENCH:
        _fuzz_bench(out, seed, case, ctx.args)
        return
    if name == LIVE_BENCH:
        from pipeline.bench.live import main as live_main

        live_main(["--out", str(out), *ctx.args])
        return
    if str(config) == "long":
        _long_bench(out)
        return
    if str(config) == FAULTS_BENCH and not config.exists():
        _faults_bench(out, seed, case, strip_config, rendered)
        return
    if config.is_dir():
        _flight_bench(config, out)
        return

    kwargs: dict[str, tuple[int, ...] | tuple[float, ...]] = {}
    if seed:
        kwargs["seeds"] = tuple(seed)
    if threshold:
        kwargs["thresholds"] = tuple(threshold)
    report = run_bench(config, out, **kwargs)  # type: ignore[arg-type]
    table = Table(title="seqat bench: targets", title_justify="left")
    for col in ("method", "check", "value", "target", "result"):
        table.add_column(col)
    for c in report.checks:
        bound = f"within ±{c.target:g}" if c.two_sided else f"≤ {c.target:g}"
        table.add_row(c.label, c.name, f"{c.value:.4g} {c.unit}", f"{bound} {c.unit}",
                      "PASS" if c.passed else "FAIL")
    console().print(table)
    console().print(f"benchmark written to {out}")


def _long_bench(out: Path) -> None:
    from pipeline.bench.long import run_long_bench

    b = run_long_bench(out)
    rows = []
    for v in b.variants:
        first, last = v.samples[0], v.samples[-1]
        rows.append((v.name, f"RSS {first.rss_mb:.0f} -> {last.rss_mb:.0f} MB "
                             f"({v.rss_growth_kb_per_image:.1f} KB/image), update ms "
                             f"{first.median_update_ms:.2f} -> {last.median_update_ms:.2f}, "
                             f"{v.wall_s:.0f} s"))
    rows.append(("written", str(out)))
    console().print(table(f"seqat bench long ({b.images} images)", rows))
def _faults_bench(out: Path, seeds: list[int] | None, cases: list[str] | None,
                  strip_config: Path, rendered: Path) -> None:
    from pipeline.bench.faults.cases import CASES
    from pipeline.bench.faults.report import summary_rows
    from pipeline.bench.faults.suite import run_fault_bench

    cases = [c.strip().lower() for c in cases or ()]  # any case, as every choice option
    report = run_fault_bench(out, seeds=tuple(seeds or (1, 2, 3)), cases=tuple(cases or CASES),
                             strip_config=strip_config, rendered_flight=rendered)
    table = Table(title="seqat bench faults (mean over seeds)", title_justify="left")
    header, rows = summary_rows(report)
    for col in header:
        table.add_column(col)
    for row in rows:
        table.add_row(*row)
    console().print(table)
    console().print(f"benchmark written to {out / 'faults.json'} and {out / 'faults.md'}")


def _camera_rows(b: object) -> list[tuple[str, str]]:
    """Rows of the flight bench about the camera: its estimate, and the other model."""
    rows = []
    for method, est in b.camera_estimate.items():  # type: ignore[attr-defined]
        if est:
            v, sg = est["values"], est["sigma"]
            rows.append((f"camera ({method})", ", ".join(
                f"{n} {v[n]:.4g}±{sg[n]:.2g}" for n in est["free"])))
    other = b.other_camera  # type: ignore[attr-defined]
    label = "self-calibrated" if other["self_calibration"] else "fixed camera"
    rows.append((f"{label}: sigma0 (seq-r / sim)", " / ".join(
        f"{other['sigma0'][m]:.3f}" for m in ("seq-r", "sim"))))
    d = other["seq_r_minus_sim"]
    rows.append((f"{label}: Seq-R - Sim rms", f"{fmt(d.pos_rms_m, METRE_FORMAT)} m, "
                 f"{fmt(d.att_rms_deg, DEGREE_FORMAT)} deg"))
    s = other["at_ms"]
    rows.append((f"{label}: AT ms (median, p95, max)",
                 f"{s.median:.0f} / {s.p95:.0f} / {s.max:.0f}"))
    return rows


def _fuzz_bench(out: Path, seeds: list[int] | None, cases: list[str] | None,
                extra: list[str]) -> None:
    from pipeline.bench.fuzz.cases import CaseResult
    from pipeline.bench.fuzz.report import SUMMARY_HEADER, failing_rows, summary_row
    from pipeline.bench.fuzz.suite import main

    argv = ["--out", str(out), *(a for s in seed_args(seeds) for a in s),
            *(a for c in cases or () for a in ("--case", c)), *extra]
    replay = bool(cases)
    out_console = console()

    def progress(case: CaseResult) -> None:
        codes = " ".join(f"{c.name}={'timeout' if c.exit_code is None else c.exit_code}"
                         for c in case.commands)
        mark = "[red]FAIL[/red]" if case.defects or case.leftover else "ok"
        out_console.print(f"{case.seed}/{case.index} {case.flight} {case.mutation.kind} "
                          f"{case.mutation.target}: {codes} {mark}", markup=True,
                          highlight=False, soft_wrap=True)
        if replay:
            out_console.print(f"  {case.mutation.description}", soft_wrap=True, markup=False)
            for c in case.commands:
                out_console.print(f"  $ seqat {' '.join(c.argv)}  -> exit {c.exit_code}",
                                  soft_wrap=True, markup=False)
                if c.stderr:
                    out_console.print(c.stderr.rstrip(), soft_wrap=True, markup=False,
                                      highlight=False)
                for a in c.absurd:
                    out_console.print(f"  absurd: {a}", soft_wrap=True, markup=False)
            for p in case.inputs_changed:
                out_console.print(f"  input changed: {p}", soft_wrap=True, markup=False)

    report = main(argv, progress=progress)
    summary = Table(title="seqat bench fuzz", title_justify="left")
    for col in SUMMARY_HEADER:
        summary.add_column(col)
    summary.add_row(*summary_row(report))
    out_console.print(summary)
    fails = failing_rows(report)
    if fails:
        t = Table(title="failing cases (replay: seqat bench fuzz --seed S --case K)",
                  title_justify="left")
        for col in ("seed/case", "flight", "mutation", "defects", "message"):
            t.add_column(col)
        for row in fails:
            t.add_row(*row)
        out_console.print(t)
    if report.sample_data_changed:
        out_console.print(f"sample data changed: {', '.join(report.sample_data_changed)}")
    where = f"{out / 'fuzz.csv'}, {out / 'fuzz.json'} and {out / 'fuzz.md'}"
    if replay:
        where += f"; case folders in {out / 'cases'}"
    out_console.print(f"benchmark written to {where}")


def _fuzz_inputs() -> tuple[Path, ...]:
    from pipeline.bench.fuzz.suite import SAMPLE_DATA

    return (SAMPLE_DATA,)


def seed_args(seeds: list[int] | None) -> list[tuple[str, str]]:
    return [("--seed", str(s)) for s in seeds or ()]


def _flight_bench(flight: Path, out: Path) -> None:
    from pipeline.bench.flight import run_flight_bench

    b = run_flight_bench(flight, out)

    def stats(s: object) -> str:
        return f"{s.median:.0f} / {s.p95:.0f} / {s.max:.0f}"  # type: ignore[attr-defined]

    def diff(d: object) -> str:
        return (f"{fmt(d.pos_rms_m, METRE_FORMAT)} m, "  # type: ignore[attr-defined]
                f"{fmt(d.att_rms_deg, DEGREE_FORMAT)} deg")  # type: ignore[attr-defined]

    rows = [
        ("images (with a verified pair) / skipped",
         f"{b.images} ({b.images_with_verified_pair}) / {b.skipped}"),
        ("tracks >= 2 rays, length median / mean",
         f"{b.tracks}, {b.track_length_median:g} / {b.track_length_mean:.2f}"),
        ("residual px rms, median (seq-r / sim / seq-f)",
         " / ".join(f"{b.rms_residual_px[m]:.2f}, {b.median_residual_px[m]:.2f}"
                    for m in ("seq-r", "sim", "seq-f"))),
        ("sigma0 (seq-r / sim / seq-f)",
         " / ".join(f"{b.sigma0[m]:.3f}" for m in ("seq-r", "sim", "seq-f"))),
        ("read / detect / match ms (median, p95, max)",
         f"{stats(b.read_ms)}; {stats(b.detect_ms)}; {stats(b.match_ms)}"),
        ("AT ms, latency ms (median, p95, max)", f"{stats(b.at_ms)}; {stats(b.latency_ms)}"),
        ("AT ms p99", f"{b.at_ms.p99:.0f}"),
        ("AT + refinement after it ms (median, p95, p99, max)",
         f"{stats(b.at_refine_ms)}, p99 {b.at_refine_ms.p99:.0f}"),
        ("Seq-R - Sim rms", diff(b.seq_r_minus_sim)),
        ("Seq-F - Sim rms", diff(b.seq_f_minus_sim)),
        ("nav - Sim rms", diff(b.nav_minus_sim)),
        ("COLMAP reference (sigma0, loss)",
         str(b.colmap.get("error")) if "error" in b.colmap else
         f"{float(b.colmap['sigma0']):.3f}, {b.colmap['loss']}"),  # type: ignore[arg-type]
        ("COLMAP - Sim rms",
         "-" if b.colmap_minus_sim is None else diff(b.colmap_minus_sim)),
        ("Seq-R - COLMAP rms",
         "-" if b.seq_r_minus_colmap is None else diff(b.seq_r_minus_colmap)),
        *_camera_rows(b),
        ("written", str(out)),
    ]
    console().print(table(f"seqat bench {flight}", rows))
