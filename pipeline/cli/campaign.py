"""``seqat process FLIGHT... --out OUT`` with several flights, a campaign folder,
``--scheduler`` or ``--workers``: the campaign on Dask (:mod:`pipeline.campaign.job`)."""

from __future__ import annotations

from pathlib import Path

from pipeline.cli.common import console
from pipeline.cli.run import parse_method
from seqat.errors import ConfigError, InputDataError


def wants_campaign(flights: list[Path], scheduler: str | None, workers: int | None) -> bool:
    """Several flights, a campaign folder, or a cluster asked for."""
    from pipeline.campaign.flights import is_campaign_folder

    return (len(flights) > 1 or scheduler is not None or workers is not None
            or is_campaign_folder(flights[0]))


def process_campaign_command(flights: list[Path], out: Path, *, scheduler: str | None,
                             workers: int | None, method: str, ortho: bool | None,
                             ortho_options: Path | None, reference: bool, report: bool,
                             progress: bool, single_flight_options: dict[str, object]) -> None:
    """Check the options, run the campaign, print where its products are; exit 2 when a
    flight failed (the others' products are complete)."""
    from pipeline.campaign.flights import find_flights
    from pipeline.campaign.job import CampaignOptions, campaign_client, process_campaign
    from pipeline.ortho.stage import load_stage_options

    given = [name for name, value in single_flight_options.items() if value is not None]
    if given:
        raise ConfigError(f"{given[0]}: only with one flight (not with several flights, a "
                          "campaign folder, --scheduler or --workers)")
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers: expected >= 1, got {workers}")
    if scheduler is not None and workers is not None:
        raise ConfigError("--workers sizes the local cluster; not with --scheduler")
    method = parse_method(method).value
    found = find_flights(flights)
    dsm_options, ortho_opts, feather_px = load_stage_options(ortho_options)
    options = CampaignOptions(method=method, ortho=ortho, reference=reference, report=report,
                              ortho_options=ortho_opts, feather_px=feather_px,
                              dsm_options=dsm_options)
    con = console()
    con.rule(f"[bold]seqat process: {len(found)} flights on Dask "
             f"({scheduler or 'local cluster'})", align="left")
    with campaign_client(scheduler, workers) as client:
        summary = process_campaign(found, out, client=client, options=options,
                                   progress=progress)
    con.print(f"[bold]seqat process: {len(found) - len(summary.failed)} of {len(found)} "
              f"flights done[/bold] ({summary.tasks} tasks on {summary.workers} workers, "
              f"{summary.wall_s:.1f} s)")
    for f in summary.flights:
        state = f"failed: {f.error}" if f.error else ", ".join(f.stages)
        con.print(f"  {f.name + ':':<24}{f.run_dir}  ({state})", highlight=False,
                  soft_wrap=True, markup=False)
    if summary.mosaic:
        con.print(f"  {'campaign mosaic:':<24}{summary.mosaic} ({summary.tiles} tiles in "
                  f"{Path(summary.mosaic).parent / 'tiles'}, {summary.pixel_m:g} m, "
                  f"{summary.crs})", highlight=False, soft_wrap=True, markup=False)
    con.print(f"  {'summary:':<24}{out / 'campaign.json'}", highlight=False, soft_wrap=True,
              markup=False)
    if summary.failed:
        names = ", ".join(f.name for f in summary.failed)
        raise InputDataError(f"{len(summary.failed)} of {len(found)} flights failed ({names}); "
                             f"the others are complete; see {out / 'campaign.json'}")
