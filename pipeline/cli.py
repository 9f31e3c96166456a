"""The ``seqat`` command line (DESIGN.md "Command line").

Commands only parse arguments, call one stage function and print its typed summary.
Exit codes: 0 success; 2 bad input or configuration (any :class:`~seqat.errors.SeqatError`,
one line ``seqat: error: <message>`` on stderr, and usage errors); 1 anything else (a one-line
message; the traceback with ``--debug`` or ``SEQAT_DEBUG=1``). Stages write their outputs
atomically, so a failed command leaves nothing half-written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, ParamSpec, TypeVar

import typer
from rich.console import Console
from rich.table import Table

from seqat.errors import SeqatError

if TYPE_CHECKING:
    from pipeline.run.runner import Method, RunSummary

#: Exit code for bad input or configuration (also click's usage errors).
EXIT_BAD_INPUT = 2
#: Exit code for any other failure.
EXIT_FAILURE = 1
#: Conventional exit code after Ctrl-C (128 + SIGINT).
EXIT_INTERRUPTED = 130
#: Environment variable that turns on tracebacks like ``--debug``.
DEBUG_ENV = "SEQAT_DEBUG"

P = ParamSpec("P")
R = TypeVar("R")

app = typer.Typer(
    name="seqat",
    help="Sequential aerial triangulation of UAV image sequences.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@dataclasses.dataclass(kw_only=True)
class _Options:
    """Global options of the current invocation (set by the app callback)."""

    debug: bool = False


_OPTIONS = _Options()


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks of internal errors.")]
    = False,
) -> None:
    """Sequential aerial triangulation of UAV image sequences."""
    _OPTIONS.debug = debug


def _debug_enabled() -> bool:
    return _OPTIONS.debug or os.environ.get(DEBUG_ENV, "") not in ("", "0")


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _guarded(command: Callable[P, R]) -> Callable[P, R]:
    """Map exceptions to the exit codes of the command-line contract."""

    @functools.wraps(command)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except SeqatError as err:
            typer.echo(f"seqat: error: {_one_line(str(err))}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from err
        except KeyboardInterrupt as err:
            typer.echo("seqat: interrupted", err=True)
            raise typer.Exit(EXIT_INTERRUPTED) from err
        except Exception as err:  # noqa: BLE001 - the contract: anything else exits 1
            if _debug_enabled():
                traceback.print_exc()
            typer.echo(f"seqat: internal error: {type(err).__name__}: {_one_line(str(err))} "
                       f"(rerun with --debug or {DEBUG_ENV}=1 for the traceback)", err=True)
            raise typer.Exit(EXIT_FAILURE) from err

    return wrapper


def _console() -> Console:
    return Console()


#: Display formats: metres to the millimetre, degrees to 1e-4, anything else 6 digits.
METRE_FORMAT = ".3f"
DEGREE_FORMAT = ".4f"
GENERAL_FORMAT = ".6g"


def _fmt(value: object, spec: str = GENERAL_FORMAT) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else format(value, spec)
    if isinstance(value, tuple) and all(isinstance(v, float) for v in value):
        return "  ".join(_fmt(v, spec) for v in value)
    return str(value)


def _table(title: str, rows: list[tuple[str, str]]) -> Table:
    table = Table(title=title, show_header=False, title_justify="left")
    table.add_column("what", style="bold")
    table.add_column("value")
    for key, value in rows:
        table.add_row(key, value)
    return table


def _stats_ms(t: object) -> str:
    return (f"{t.median_ms:.1f} / {t.p95_ms:.1f} / {t.max_ms:.1f}")  # type: ignore[attr-defined]


def _run_rows(summary: RunSummary, final_only: bool = False) -> list[tuple[str, str]]:
    """The table ``seqat run`` and ``seqat watch`` print."""
    t = summary.update_ms
    rows = [
        ("method", summary.method.value + (" (final only)" if final_only else "")),
        ("images / points / observations",
         f"{summary.n_images} / {summary.n_points} / {summary.n_observations}"),
        ("sigma0 (redundancy)", f"{_fmt(summary.sigma0, '.4f')} ({summary.redundancy})"),
        ("update ms median / p95 / max", _stats_ms(t)),
    ]
    ts = summary.sequential_update_ms
    if math.isfinite(ts.median_ms):
        rows.append(("  sequential stage only", _stats_ms(ts)))
    if summary.latency_ms is not None:
        rows.append(("latency ms median / p95 / max", _stats_ms(summary.latency_ms)))
    b = summary.budget
    if b is not None:
        rows.append(("budget / over / threshold changes",
                     f"{b.budget_ms:g} ms / {b.images_over_budget} images / "
                     f"{len(b.events)} (final threshold {b.final_threshold:g})"))
    if summary.replayed:
        rows.append(("replayed from the journal", f"{summary.replayed} images"))
    if summary.skipped:
        rows.append(("skipped", f"{len(summary.skipped)} images (run.json skipped)"))
    rows += [
        ("total update / wall", f"{t.total_ms / 1e3:.2f} s / {summary.wall_s:.2f} s"),
    ]
    acc = summary.accuracy
    if acc is not None:
        rows += [
            ("EOP position RMSE x y z (m)", _fmt(acc.pos_rmse_m, METRE_FORMAT)),
            ("  GPS/INS input (m)", _fmt(acc.nav_pos_rmse_m, METRE_FORMAT)),
            ("EOP attitude RMSE ω φ κ (deg)", _fmt(acc.att_rmse_deg, DEGREE_FORMAT)),
            ("  GPS/INS input (deg)", _fmt(acc.nav_att_rmse_deg, DEGREE_FORMAT)),
            ("ground point RMSE x y z (m)", _fmt(acc.gp_rmse_m, METRE_FORMAT)),
        ]
    rows.append(("results", str(summary.out_dir)))
    return rows


@app.command()
@_guarded
def simulate(
    config: Annotated[Path, typer.Argument(help="Simulation config (configs/*_sim.yaml).")],
    out: Annotated[Path, typer.Option("--out", help="Flight folder to write.")],
    seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
) -> None:
    """Simulate a flight and write it as a flight folder with truth/."""
    from pipeline.simulate.stage import simulate_to_folder

    summary = simulate_to_folder(config, out, seed)
    _console().print(_table("seqat simulate", [
        ("flight", str(summary.out_dir)),
        ("crs", summary.crs),
        ("seed", str(summary.seed)),
        ("images", str(summary.n_images)),
        ("points", str(summary.n_points)),
        ("observations", str(summary.n_observations)),
        ("duration", f"{summary.duration_s:.1f} s"),
    ]))


# Options shared by `run` and `watch`.
MethodOption = Annotated[str, typer.Option("--method", help="seq-r, seq-f or sim.")]
ThresholdOption = Annotated[float | None, typer.Option(
    "--threshold", help="seq-r: EOP correlation threshold in [0, 1].")]
InitialImagesOption = Annotated[int | None, typer.Option(
    "--initial-images", help="Images of the initial simultaneous stage.")]
EstimatorOptionsFile = Annotated[Path | None, typer.Option(
    "--options", help="Estimator options YAML (sections sequential:, sim:).")]
BudgetOption = Annotated[float | None, typer.Option(
    "--budget-ms", help="seq-r: processing budget per image (tracking + update), ms; over it "
    "the window threshold tightens.")]


@app.command()
@_guarded
def run(
    flight: Annotated[Path, typer.Argument(help="Flight folder.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    method: MethodOption = "seq-r",
    final_only: Annotated[bool, typer.Option(
        "--final-only", help="sim: adjust once after the last image.")] = False,
    threshold: ThresholdOption = None,
    initial_images: InitialImagesOption = None,
    options: EstimatorOptionsFile = None,
    progress: Annotated[bool, typer.Option(
        "--progress/--no-progress", help="Progress bar on a terminal.")] = True,
    observations: Annotated[Path | None, typer.Option(
        "--observations", help="Image points to use instead of the flight's own or of "
        "tracking (e.g. OUT/observations.csv of an earlier run).")] = None,
    ortho: Annotated[bool, typer.Option(
        "--ortho", help="Orthorectify each image as soon as it is georeferenced and build "
        "the mosaic live (ortho/, mosaic.tif, cameras.gpkg, ortho.json).")] = False,
    dsm: Annotated[Path | None, typer.Option(
        "--dsm", help="--ortho: DSM GeoTIFF (default: OUT/dsm.tif, the flight's lidar, else a "
        "flat plane).")] = None,
    ortho_options: Annotated[Path | None, typer.Option(
        "--ortho-options", help="--ortho: options YAML (sections ortho:, mosaic:, live:).")]
    = None,
    report: Annotated[bool, typer.Option(
        "--report", help="Then write OUT/report.html and report.json (as seqat report).")]
    = False,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue an interrupted run from OUT/journal/ (same results as an "
        "uninterrupted run).")] = False,
    budget_ms: BudgetOption = None,
) -> None:
    """Adjust a flight folder and write eop.csv, points.csv, run.json, nav.csv and
    observations.csv."""
    from pipeline.run.runner import run_flight
    from seqat.errors import ConfigError

    if not ortho and (dsm is not None or ortho_options is not None):
        raise ConfigError("--dsm and --ortho-options go with --ortho")
    live = None
    if ortho:
        from pipeline.ortho.live import open_live_ortho

        live = open_live_ortho(flight, out, dsm_path=dsm, options_path=ortho_options)
    with live if live is not None else contextlib.nullcontext():
        summary = run_flight(flight, out, method=_method(method), final_only=final_only,
                             options_path=options, threshold=threshold,
                             initial_images=initial_images, progress=progress,
                             observations=observations, resume=resume, budget_ms=budget_ms,
                             listeners=(live,) if live is not None else ())
    _console().print(_table(f"seqat run {summary.flight_dir}", _run_rows(summary, final_only)))
    if live is not None:
        o = live.result()
        assert o.live is not None
        _console().print(
            f"orthos and mosaic (live): {o.mosaic} ({len(o.images)} images, "
            f"{len(o.live.images_reorthorectified)} orthorectified again at the end; "
            f"surface: {o.dsm_source}); ortho ms median {o.compute_ms.median_ms:.0f}, "
            f"image to mosaic latency ms median / max {o.live.latency_ms.median_ms:.0f} / "
            f"{o.live.latency_ms.max_ms:.0f}")
    if report:
        from pipeline.report.stage import make_report

        r = make_report(summary.out_dir)
        _console().print("report: " + ", ".join(str(f) for f in r.files))


def _method(method: str) -> Method:
    from pipeline.run.runner import Method
    from seqat.errors import ConfigError

    try:
        return Method(method)
    except ValueError as err:
        raise ConfigError(f"--method: expected one of "
                          f"{', '.join(m.value for m in Method)}, got {method!r}") from err


@app.command()
@_guarded
def watch(
    flight: Annotated[Path, typer.Argument(help="Flight folder being written (flight.yaml "
                                           "present).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    method: MethodOption = "seq-r",
    threshold: ThresholdOption = None,
    initial_images: InitialImagesOption = None,
    options: EstimatorOptionsFile = None,
    budget_ms: BudgetOption = None,
    idle_timeout_s: Annotated[float | None, typer.Option(
        "--idle-timeout-s", "--idle-timeout", help="Stop after this many seconds without new "
        "input (default: until Ctrl-C).")] = None,
    wait_timeout_s: Annotated[float, typer.Option(
        "--wait-timeout-s", help="Seconds an image waits for its nav row (or a nav row for "
        "its image) before it is skipped.")] = 10.0,
    poll_s: Annotated[float, typer.Option("--poll-s", help="Seconds between polls.")] = 0.05,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue from OUT/journal/ (after a crash or an earlier stop).")]
    = False,
) -> None:
    """Georeference images as they appear in a growing flight folder; one line per image.
    Ctrl-C or --idle-timeout-s stops and publishes the results (as seqat run)."""
    from pipeline.run.watch import WatchOptions, watch_flight

    summary = watch_flight(flight, out, method=_method(method), options_path=options,
                           threshold=threshold, initial_images=initial_images,
                           budget_ms=budget_ms, resume=resume,
                           watch=WatchOptions(idle_timeout_s=idle_timeout_s,
                                              wait_timeout_s=wait_timeout_s, poll_s=poll_s))
    rows = [("stopped", summary.stopped), *_run_rows(summary)]
    _console().print(_table(f"seqat watch {summary.flight_dir}", rows))


@app.command()
@_guarded
def feed(
    src: Annotated[Path, typer.Argument(help="Flight folder to replay.")],
    dst: Annotated[Path, typer.Argument(help="Folder to write (absent or empty).")],
    rate: Annotated[float, typer.Option("--rate", help="Images per second.")] = 2.0,
    limit: Annotated[int | None, typer.Option("--limit", help="Only the first N images.")]
    = None,
    delay_s: Annotated[float, typer.Option(
        "--delay-s", help="Seconds between writing flight.yaml and the first image.")] = 0.0,
) -> None:
    """Copy a flight into a folder image by image at the camera's rate (for seqat watch),
    with the partial-file convention (name.jpg.part, then renamed)."""
    from pipeline.run.feed import feed_flight

    s = feed_flight(src, dst, rate_hz=rate, limit=limit, delay_s=delay_s)
    _console().print(f"fed {s.images} images in {s.duration_s:.1f} s (at most "
                     f"{s.late_s * 1e3:.0f} ms late)")


@app.command()
@_guarded
def bench(
    config: Annotated[Path, typer.Argument(
        help="Simulation config (configs/*_sim.yaml), an image flight folder, or 'long' "
             "(memory and time along a 10,000-image strip).")],
    out: Annotated[Path, typer.Option("--out", help="Benchmark output folder.")] = Path(
        "out/bench"),
    seed: Annotated[list[int] | None, typer.Option(
        "--seed", help="Seed of one simulated flight (repeat for several).")] = None,
    threshold: Annotated[list[float] | None, typer.Option(
        "--threshold", help="Seq-R correlation threshold (repeat for several).")] = None,
    case: Annotated[list[str] | None, typer.Option(
        "--case", help="bench faults: strip, block or rendered (repeat; default all).")] = None,
    strip_config: Annotated[Path, typer.Option(
        "--strip-config", help="bench faults: config of the strip case.")] = Path(
        "configs/paper_sim.yaml"),
    rendered: Annotated[Path, typer.Option(
        "--rendered", help="bench faults: flight folder (with truth/) of the rendered case.")]
    = Path("sample_data/autzen_rendered"),
) -> None:
    """Compare direct georeferencing, Seq-R, Seq-F and Sim on simulated flights, or, for an
    image flight folder, Seq-R (tracking) with Sim and Seq-F on the same tie points.
    ``seqat bench faults``: seeded blunders, a GNSS jump and a dropout (docs/benchmarks.md)."""
    from pipeline.bench.strip import run_bench

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
    _console().print(table)
    _console().print(f"benchmark written to {out}")


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
    _console().print(_table(f"seqat bench long ({b.images} images)", rows))
#: ``seqat bench faults``: the fault benchmark instead of a config.
FAULTS_BENCH = "faults"


def _faults_bench(out: Path, seeds: list[int] | None, cases: list[str] | None,
                  strip_config: Path, rendered: Path) -> None:
    from pipeline.bench.faults.cases import CASES
    from pipeline.bench.faults.report import summary_rows
    from pipeline.bench.faults.suite import run_fault_bench

    report = run_fault_bench(out, seeds=tuple(seeds or (1, 2, 3)), cases=tuple(cases or CASES),
                             strip_config=strip_config, rendered_flight=rendered)
    table = Table(title="seqat bench faults (mean over seeds)", title_justify="left")
    header, rows = summary_rows(report)
    for col in header:
        table.add_column(col)
    for row in rows:
        table.add_row(*row)
    _console().print(table)
    _console().print(f"benchmark written to {out / 'faults.json'} and {out / 'faults.md'}")


def _flight_bench(flight: Path, out: Path) -> None:
    from pipeline.bench.flight import run_flight_bench

    b = run_flight_bench(flight, out)

    def stats(s: object) -> str:
        return f"{s.median:.0f} / {s.p95:.0f} / {s.max:.0f}"  # type: ignore[attr-defined]

    def diff(d: object) -> str:
        return (f"{_fmt(d.pos_rms_m, METRE_FORMAT)} m, "  # type: ignore[attr-defined]
                f"{_fmt(d.att_rms_deg, DEGREE_FORMAT)} deg")  # type: ignore[attr-defined]

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
        ("Seq-R - Sim rms", diff(b.seq_r_minus_sim)),
        ("Seq-F - Sim rms", diff(b.seq_f_minus_sim)),
        ("nav - Sim rms", diff(b.nav_minus_sim)),
        ("written", str(out)),
    ]
    _console().print(_table(f"seqat bench {flight}", rows))


@app.command()
@_guarded
def reference(
    out: Annotated[Path, typer.Argument(help="Run folder (seqat run ... --out OUT).")],
    self_calibrate: Annotated[bool, typer.Option(
        "--self-calibrate", help="Also estimate fx, fy, cx, cy, k1, k2, p1, p2.")] = False,
    prior: Annotated[str, typer.Option(
        "--prior", help="GPS/INS prior: pose (6-DoF, as Sim) or position.")] = "pose",
    robust_loss: Annotated[str, typer.Option(
        "--robust-loss", help="trivial (off), huber, cauchy or soft_l1.")] = "trivial",
) -> None:
    """COLMAP bundle adjustment of a run's observations with GPS/INS priors: OUT/reference/."""
    from pipeline.reference.colmap_ba import PriorKind, ReferenceOptions, RobustLoss
    from pipeline.reference.stage import run_reference
    from seqat.errors import ConfigError

    for flag, value, kind in (("--prior", prior, PriorKind),
                              ("--robust-loss", robust_loss, RobustLoss)):
        if value not in {k.value for k in kind}:
            raise ConfigError(f"{flag}: expected one of {', '.join(k.value for k in kind)}, "
                              f"got {value!r}")
    options = ReferenceOptions(prior=PriorKind(prior), robust_loss=RobustLoss(robust_loss),
                               self_calibrate=self_calibrate)
    rec = run_reference(out, options).record
    _console().print(_table(f"seqat reference {out}", [
        ("images / points / observations",
         f"{rec.n_images_adjusted} / {rec.n_points} / {rec.n_observations}"),
        ("prior", f"{rec.options.prior.value} ({rec.n_prior_residuals} residuals of "
                  f"{rec.n_residuals})"),
        ("sigma0 (redundancy)", f"{_fmt(rec.sigma0, '.4f')} ({rec.redundancy})"),
        ("rms image residual (px)", _fmt(rec.rms_px, '.3f')),
        ("termination (iterations)", f"{rec.termination} ({rec.iterations})"),
        ("bundle adjustment", f"{rec.ba_s:.2f} s"),
        ("covariance", rec.covariance),
        ("camera", f"{rec.camera_model} fx {rec.camera.fx_px:.2f} fy {rec.camera.fy_px:.2f} "
                   f"cx {rec.camera.cx_px:.2f} cy {rec.camera.cy_px:.2f}"),
        ("results", str(out / "reference")),
    ]))


@app.command()
@_guarded
def report(
    out: Annotated[Path, typer.Argument(help="Run folder (seqat run ... --out OUT).")],
    compare: Annotated[list[Path] | None, typer.Option(
        "--compare", help="Another run folder of the same flight (repeat for several).")]
    = None,
) -> None:
    """Flight report: OUT/report.html (figures embedded) and OUT/report.json."""
    from pipeline.report.stage import make_report

    summary = make_report(out, compare or ())
    rep = summary.report
    rows = [("methods", ", ".join(rep.methods))]
    for acc in rep.accuracy.values():
        rows.append((f"{acc.method}: position H / 3D RMSE (m) vs {acc.against}",
                     f"{_fmt(acc.pos_rmse_h_m, METRE_FORMAT)} / "
                     f"{_fmt(acc.pos_rmse_3d_m, METRE_FORMAT)}"))
    cp = rep.checkpoints
    rows.append(("check points", "none" if cp is None else
                 f"{cp['count']}: RMSE_H {_fmt(cp['rmse_h_m'], METRE_FORMAT)} m, "
                 f"RMSE_V {_fmt(cp['rmse_v_m'], METRE_FORMAT)} m"))
    rows += [(n, "") for n in rep.notes]
    rows += [("written", "  ".join(str(f) for f in summary.files))]
    _console().print(_table(f"seqat report {out}", rows))


@app.command()
@_guarded
def dsm(
    las: Annotated[list[Path], typer.Argument(help="LAS or LAZ files.")],
    out: Annotated[Path, typer.Option("--out", help="DSM COG to write.")],
    crs: Annotated[str | None, typer.Option(
        "--crs", help="Working CRS (EPSG:XXXX, projected, metres); default: UTM zone.")] = None,
    cell_m: Annotated[float | None, typer.Option("--cell-m", help="Cell size, metres.")] = None,
    las_crs: Annotated[str | None, typer.Option(
        "--las-crs", help="CRS of the LAS files (EPSG:XXXX or a WKT file), overriding "
                          "theirs.")] = None,
    options: Annotated[Path | None, typer.Option(
        "--options", help="Options YAML (section dsm:).")] = None,
) -> None:
    """Grid LiDAR points into a DSM (highest return per cell) written as a COG."""
    from pipeline.ortho.dsm_stage import make_dsm

    r = make_dsm(las, out, crs=crs, las_crs=las_crs, cell_m=cell_m, options_path=options)
    rows = [
        ("points read / kept", f"{r.points_read} / {r.points_kept}"),
        ("LAS CRS -> working CRS", f"{r.las_crs} -> {r.crs}"),
        ("cells", f"{r.cols} x {r.rows} at {r.cell_m:g} m"),
        ("heights (m)", f"{r.height_range_m[0]:.2f} .. {r.height_range_m[1]:.2f}"),
        ("holes filled / nodata cells", f"{r.filled_cells} / {r.nodata_cells}"),
        ("time", f"{r.time_s:.2f} s"),
        *(("warning", w) for w in r.warnings),
        ("dsm", str(r.path)),
    ]
    _console().print(_table("seqat dsm", rows))


@app.command()
@_guarded
def ortho(
    out: Annotated[Path, typer.Argument(help="Output folder of seqat run.")],
    dsm: Annotated[Path | None, typer.Option("--dsm", help="DSM GeoTIFF.")] = None,
    eop: Annotated[str, typer.Option("--eop", help="seq-r or reference.")] = "seq-r",
    crs: Annotated[str | None, typer.Option(
        "--crs", help="CRS of the rasters (EPSG:XXXX); default: the run's.")] = None,
    options: Annotated[Path | None, typer.Option(
        "--options", help="Options YAML (sections ortho:, mosaic:).")] = None,
    progress: Annotated[bool, typer.Option(
        "--progress/--no-progress", help="Progress bar on a terminal.")] = True,
) -> None:
    """Orthorectify a run's images; write ortho/*.tif, mosaic.tif and cameras.gpkg."""
    from pipeline.ortho.stage import load_stage_options, orthorectify_run
    from seqat.errors import ConfigError

    if eop not in ("seq-r", "reference"):
        raise ConfigError(f"--eop: expected seq-r or reference, got {eop!r}")
    _, ortho_options, feather_px = load_stage_options(options)
    s = orthorectify_run(out, dsm_path=dsm, eop_source=eop,  # type: ignore[arg-type]
                         options=ortho_options, feather_px=feather_px, out_crs=crs,
                         progress=progress)
    rows = [
        ("EOP / DSM", f"{s.eop_source} / {s.dsm_source}"),
        ("images / skipped", f"{len(s.images)} / {len(s.skipped)}"),
        ("pixel", f"{s.pixel_m:g} m ({s.crs})"),
        ("ortho ms median / max", f"{s.compute_ms.median_ms:.0f} / {s.compute_ms.max_ms:.0f}"),
        ("mosaic update ms median / max", f"{s.mosaic_ms.median_ms:.0f} / "
                                          f"{s.mosaic_ms.max_ms:.0f}"),
        ("wall", f"{s.wall_s:.1f} s"),
        *(("warning", w) for w in s.warnings),
        ("mosaic", str(s.mosaic)),
        ("cameras", str(s.cameras_gpkg)),
    ]
    _console().print(_table(f"seqat ortho {s.out_dir}", rows))
