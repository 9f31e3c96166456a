"""The ``seqat dsm`` stage: LAS/LAZ files in, a DSM COG out (CRS options, stage options)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import pyproj

from pipeline.common.outdir import check_not_input
from pipeline.flight.navigation import resolve_projected_crs, utm_epsg
from pipeline.ortho.dsm import DsmResult, build_dsm, parse_las_crs, read_las
from pipeline.ortho.stage import load_stage_options
from seqat.errors import InputDataError


def working_crs_for_las(crs: str | None, las_paths: Sequence[Path | str],
                        las_crs: pyproj.CRS | None) -> pyproj.CRS:
    """``--crs`` of ``seqat dsm``: as given (projected, metres), or ``auto`` / None = the WGS 84
    UTM zone of the first file's centre."""
    if crs is not None and crs.strip().lower() != "auto":
        return resolve_projected_crs(crs, "--crs")
    cloud = read_las(las_paths[0], las_crs)
    centre = cloud.xyz[:, :2].mean(axis=0)
    to_geo = pyproj.Transformer.from_crs(cloud.crs, "EPSG:4326", always_xy=True)
    lon, lat = to_geo.transform(centre[0], centre[1])
    return pyproj.CRS.from_epsg(utm_epsg(lon, lat))


def make_dsm(las_paths: Sequence[Path | str], out_path: Path | str, *, crs: str | None = None,
             las_crs: str | None = None, cell_m: float | None = None,
             options_path: Path | str | None = None) -> DsmResult:
    """``seqat dsm``: parse the CRS options and build the DSM COG."""
    check_not_input(out_path, [*las_paths, options_path])
    if Path(out_path).is_dir():
        raise InputDataError(f"{out_path}: is a folder; --out names the DSM file to write "
                             "(e.g. dsm.tif)")
    options, _, _ = load_stage_options(options_path)
    if cell_m is not None:
        options = dataclasses.replace(options, cell_m=cell_m)
    source_crs = parse_las_crs(las_crs) if las_crs is not None else None
    if not las_paths:
        raise InputDataError("dsm: no LAS/LAZ file given")
    working = working_crs_for_las(crs, las_paths, source_crs)
    return build_dsm(las_paths, out_path, crs=working, las_crs=source_crs, options=options)
