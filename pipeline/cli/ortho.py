"""``seqat dsm`` and ``seqat ortho``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.common import choice, console, guarded, table

app = typer.Typer()


@app.command()
@guarded
def dsm(
    las: Annotated[list[Path], typer.Argument(help="LAS or LAZ files.")],
    out: Annotated[Path, typer.Option("--out", help="DSM COG to write.")],
    crs: Annotated[str | None, typer.Option(
        "--crs", help="CRS of the outputs: the DSM is gridded and written in it (EPSG:XXXX, "
                      "projected, metres; default or auto: the UTM zone of the first file).")]
    = None,
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
        ("cells interpolated / ground fallback / nodata",
         f"{r.interpolated_cells} / {r.ground_cells} / {r.nodata_cells}"),
        ("time", f"{r.time_s:.2f} s"),
        *(("warning", w) for w in r.warnings),
        ("dsm", str(r.path)),
    ]
    console().print(table("seqat dsm", rows))


@app.command()
@guarded
def ortho(
    out: Annotated[Path, typer.Argument(help="Output folder of seqat run.")],
    dsm: Annotated[Path | None, typer.Option("--dsm", help="DSM GeoTIFF.")] = None,
    eop: Annotated[str, typer.Option(
        "--eop", help="run: OUT/eop.csv, the estimates of the run's own method (its name, e.g. "
                      "seq-r, is accepted too); reference: OUT/reference/eop.csv (after seqat "
                      "reference OUT).")] = "run",
    crs: Annotated[str | None, typer.Option(
        "--crs", help="CRS of the outputs: the orthos and the mosaic are warped to it "
                      "(EPSG:XXXX; default: the run's working CRS; cameras.gpkg stays in the "
                      "working CRS).")] = None,
    options: Annotated[Path | None, typer.Option(
        "--options", help="Options YAML (sections ortho:, mosaic:, dsm:).")] = None,
    progress: Annotated[bool, typer.Option(
        "--progress/--no-progress", help="Progress bar on a terminal.")] = True,
) -> None:
    """Orthorectify a run's images; write ortho/*.tif, mosaic.tif and cameras.gpkg."""
    from pipeline.ortho.stage import EOP_SOURCES, load_stage_options, orthorectify_run

    eop = choice("--eop", eop, EOP_SOURCES)
    dsm_options, ortho_options, feather_px = load_stage_options(options)
    s = orthorectify_run(out, dsm_path=dsm, eop_source=eop,  # type: ignore[arg-type]
                         options=ortho_options, feather_px=feather_px, out_crs=crs,
                         progress=progress, dsm_options=dsm_options)
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
    console().print(table(f"seqat ortho {s.out_dir}", rows))
