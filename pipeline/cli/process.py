"""``seqat process FLIGHT --out OUT``: the common job in one command.

The stages, in order, each the function its own command calls (nothing is copied):

1. ``seqat run`` (:func:`pipeline.cli.run.adjust_flight`), with the live ortho (``--ortho``)
   when a surface is known for the flight: ``--dsm``, or the flight's ``lidar:``
   (:func:`pipeline.ortho.stage.flight_lidar`), as ``seqat run --ortho`` finds it;
2. ``seqat reference`` (:func:`pipeline.reference.stage.run_reference`);
3. ``seqat report`` (:func:`pipeline.report.stage.make_report`).

Bad input is found before anything is written where it can be (options, method, the flight's
``flight.yaml``, its check point files); each stage publishes its files whole, so a later
stage that fails leaves the earlier stages' complete results and no part of its own
(docs/formats.md, *seqat process*).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, TypeVar

import typer

from pipeline.cli.common import METRE_FORMAT, console, fmt, guarded
from pipeline.cli.run import (
    EstimatorOptionsFile,
    GcpOption,
    GcpSigmaOption,
    MethodOption,
    adjust_flight,
    parse_method,
)
from seqat.errors import ConfigError, SeqatError

app = typer.Typer()
T = TypeVar("T")


class StageError(SeqatError):
    """A later stage of ``seqat process`` refused its input (the earlier results stand)."""


@dataclass(frozen=True, kw_only=True)
class ProcessPlan:
    """The stages ``seqat process`` runs (decided before anything is written)."""

    ortho: bool
    ortho_why: str
    reference: bool
    report: bool

    def stages(self) -> tuple[str, ...]:
        return ("run" + (" + live ortho" if self.ortho else ""),
                *(("reference",) if self.reference else ()), *(("report",) if self.report
                                                              else ()))


def plan_process(flight: Path, *, ortho: bool | None, dsm: Path | None,
                 ortho_options: Path | None, reference: bool, report: bool,
                 method: str) -> ProcessPlan:
    """Check what can be checked before the run and decide the stages.

    Raises
    ------
    ConfigError, InputDataError
        A bad method, ``--dsm`` / ``--ortho-options`` with ``--no-ortho``, a malformed
        ``flight.yaml``, check points without their observations or malformed.
    """
    from pipeline.flight.nav_files import read_ground_points
    from pipeline.ortho.stage import flight_lidar
    from pipeline.report.model import find_checkpoints

    parse_method(method)
    if ortho is False and (dsm is not None or ortho_options is not None):
        raise ConfigError("--dsm and --ortho-options need the ortho (drop --no-ortho)")
    lidar = flight_lidar(flight)
    if ortho is None:
        ortho = dsm is not None or bool(lidar)
        why = ("surface: --dsm" if dsm is not None else "surface: the flight's lidar" if lidar
               else "no ortho: no DSM or lidar known; --dsm D or --ortho")
    else:
        why = "--ortho" if ortho else "--no-ortho"
    if report and flight.is_dir():
        found = find_checkpoints(flight)
        if found is not None:
            read_ground_points(found[0])
    return ProcessPlan(ortho=ortho, ortho_why=why, reference=reference, report=report)


@app.command()
@guarded
def process(
    flights: Annotated[list[Path], typer.Argument(
        help="Flight folder; several, or a campaign folder of flights: on Dask.",
        metavar="FLIGHT...")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    method: MethodOption = "seq-r",
    self_calibration: Annotated[bool | None, typer.Option(
        "--self-calibration/--fixed-camera", help="As seqat run (default: flight.yaml "
        "self_calibration:, on for a camera from EXIF).", show_default=False)] = None,
    options: EstimatorOptionsFile = None,
    observations: Annotated[Path | None, typer.Option(
        "--observations", help="As seqat run: image points instead of the flight's own or of "
        "tracking (e.g. OUT/observations.csv of an earlier run).")] = None,
    ortho: Annotated[bool | None, typer.Option(
        "--ortho/--no-ortho", help="Live ortho, mosaic.tif and cameras.gpkg (default: when "
        "--dsm is given or the flight has lidar:).", show_default=False)] = None,
    dsm: Annotated[Path | None, typer.Option(
        "--dsm", help="DSM GeoTIFF for the ortho (default: the flight's lidar).")] = None,
    ortho_options: Annotated[Path | None, typer.Option(
        "--ortho-options", help="Ortho options YAML (sections ortho:, mosaic:, live:).")]
    = None,
    reference: Annotated[bool, typer.Option(
        "--reference/--no-reference", help="COLMAP reference (OUT/reference/).")] = True,
    report: Annotated[bool, typer.Option(
        "--report/--no-report", help="OUT/report.html, report.pdf, report.json.")] = True,
    progress: Annotated[bool, typer.Option(
        "--progress/--no-progress", help="Progress bar on a terminal.")] = True,
    gcp: GcpOption = None,
    gcp_sigma_m: GcpSigmaOption = None,
    scheduler: Annotated[str | None, typer.Option(
        "--scheduler", help="Dask scheduler address (tcp://host:8786) of an existing cluster "
        "(default: a local cluster).")] = None,
    workers: Annotated[int | None, typer.Option(
        "--workers", help="Workers of the local cluster (default: one per CPU).")] = None,
) -> None:
    """Run, COLMAP reference and report of a flight in one command; prints where the map
    (mosaic.tif, cameras.gpkg) and the report are. Several flights (or a campaign folder):
    each in OUT/<flight>, as Dask tasks, plus one campaign mosaic (docs/campaigns.md)."""
    from pipeline.cli.campaign import process_campaign_command, wants_campaign

    if wants_campaign(flights, scheduler, workers):
        process_campaign_command(flights, out, scheduler=scheduler, workers=workers,
                                 method=method, ortho=ortho, ortho_options=ortho_options,
                                 reference=reference, report=report, progress=progress,
                                 single_flight_options={
                                     "--self-calibration": self_calibration,
                                     "--options": options, "--observations": observations,
                                     "--dsm": dsm, "--gcp": gcp,
                                     "--gcp-sigma-m": gcp_sigma_m})
        return
    flight = flights[0]
    method = parse_method(method).value  # any case: SEQ-R, Sim
    plan = plan_process(flight, ortho=ortho, dsm=dsm, ortho_options=ortho_options,
                        reference=reference, report=report, method=method)
    con = console()
    stages = plan.stages()
    step = iter(range(1, len(stages) + 1))

    def rule(text: str) -> None:
        con.rule(f"[bold]seqat process {next(step)}/{len(stages)}: {text}", align="left")

    rule(f"{stages[0]} ({plan.ortho_why})")
    summary = adjust_flight(flight, out, method=method, options=options, progress=progress,
                            observations=observations, ortho=plan.ortho, dsm=dsm,
                            ortho_options=ortho_options, self_calibration=self_calibration,
                            gcp=gcp, gcp_sigma_m=gcp_sigma_m)
    out = summary.out_dir
    rows: list[tuple[str, str]] = []
    if plan.reference:
        from pipeline.reference.stage import run_reference

        rule("COLMAP reference")
        rec = _later_stage("seqat reference", out, lambda: run_reference(out)).record
        con.print(f"reference: {rec.n_images_adjusted} images, sigma0 {rec.sigma0:.4f}, "
                  f"rms {rec.rms_px:.3f} px, {rec.termination} in {rec.ba_s:.1f} s")
        rows.append(("COLMAP reference", str(out / "reference")))
    if plan.report:
        from pipeline.report.stage import make_report

        rule("report")
        rep = _later_stage("seqat report", out, lambda: make_report(out))
        cp = rep.report.checkpoints
        rows.append(("check points", "none (precision and agreement only)" if cp is None else
                     f"{cp['count']}: RMSE_H {fmt(cp['rmse_h_m'], METRE_FORMAT)} m, "
                     f"RMSE_V {fmt(cp['rmse_v_m'], METRE_FORMAT)} m"))
        rows += [("report", str(f)) for f in rep.files if f.suffix in (".html", ".pdf")]
    # plain lines, never cut: the paths are what the user came for
    con.print(f"[bold]seqat process {flight}: done[/bold]")
    for what, where in _map_rows(out) + rows:
        con.print(f"  {what + ':':<38}{where}", highlight=False, soft_wrap=True, markup=False)


def _later_stage(name: str, out: Path, stage: Callable[[], T]) -> T:
    """Call a stage after the run; its refusal names the stage and keeps the run's results."""
    try:
        return stage()
    except SeqatError as err:
        raise StageError(f"{name} {out}: {err} (the run's results in {out} are complete; "
                         f"rerun `{name} {out}` after fixing it)") from err


def _map_rows(out: Path) -> list[tuple[str, str]]:
    from pipeline.ortho.stage import CAMERAS_GPKG, DSM_FILE, MOSAIC_FILE

    rows = [("map: " + what, str(out / name)) for what, name in (
        ("mosaic", MOSAIC_FILE), ("cameras, footprints, tie points", CAMERAS_GPKG),
        ("DSM", DSM_FILE)) if (out / name).is_file()]
    return rows or [("map", f"no mosaic; cameras and tie points in {out} (eop.csv, "
                            "points.csv)")]
