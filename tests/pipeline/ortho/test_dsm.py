"""DSM from LiDAR: CRS and units, outliers, highest return, holes, COG; bad input."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
import rasterio
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.ortho.dsm import (
    DSM_NODATA,
    Dsm,
    DsmOptions,
    build_dsm,
    flat_dsm,
    parse_las_crs,
    read_dsm,
    read_las,
)
from pipeline.ortho.raster import cog_problems
from seqat.errors import InputDataError

#: Working CRS of the synthetic clouds: UTM 10N (Oregon, where Autzen is).
UTM10 = pyproj.CRS.from_epsg(32610)
#: Oregon GIC Lambert, international feet (the Autzen CRS).
OREGON_FT = pyproj.CRS.from_epsg(2994)
#: Lower-left corner of the synthetic scene, UTM 10N metres.
E0_M, N0_M = 494000.0, 4877400.0
#: Ground plane of the scene: z = Z0 + slope * (x - E0).
Z0_M, SLOPE = 120.0, 0.1
#: Building: 10 x 10 m, 15 m above the ground, from (20, 20) m.
BUILDING = (20.0, 20.0, 30.0, 30.0, 15.0)
#: Point spacing of the synthetic cloud, metres (4 points per 1 m cell).
SPACING_M = 0.5
#: Autzen Stadium, Eugene, Oregon (degrees).
AUTZEN_LON, AUTZEN_LAT = -123.0686, 44.0584
#: Horizontal jitter of the points around the regular grid, metres.
JITTER_M = 0.2
#: A highest-return cell lies at most slope x cell above the plane at the cell centre.
HEIGHT_TOL_M = 0.1 + SLOPE * JITTER_M


def scene_points(hole: tuple[float, float, float, float] | None = None,
                 outliers: int = 0) -> np.ndarray:
    """Ground plane + building, 60 x 60 m, metres in UTM 10N; optional hole (w, s, e, n)."""
    g = np.arange(0.25, 60.0, SPACING_M)
    x, y = np.meshgrid(g, g)
    rng = np.random.default_rng(7)
    # Scanner-like irregular spacing (the filter's statistics need a spread of distances).
    x = x.ravel() + rng.uniform(-JITTER_M, JITTER_M, x.size)
    y = y.ravel() + rng.uniform(-JITTER_M, JITTER_M, y.size)
    z = Z0_M + SLOPE * x
    bw, bs, be, bn, bh = BUILDING
    z = np.where((x >= bw) & (x < be) & (y >= bs) & (y < bn), z + bh, z)
    keep = np.ones(x.shape, bool)
    if hole is not None:
        keep = ~((x >= hole[0]) & (x < hole[2]) & (y >= hole[1]) & (y < hole[3]))
    xyz = np.column_stack([x[keep] + E0_M, y[keep] + N0_M, z[keep]])
    if outliers:
        idx = rng.choice(len(xyz), outliers, replace=False)
        xyz[idx, 2] += 80.0  # birds / multipath far above the surface
    return xyz


def write_las(path: Path, xyz: np.ndarray, crs: pyproj.CRS | None) -> Path:
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    if crs is not None:
        header.add_crs(crs)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.write(path)
    return path


def to_feet(xyz_m: np.ndarray) -> np.ndarray:
    """UTM 10N metres -> Oregon Lambert feet (heights: metres -> feet)."""
    tr = pyproj.Transformer.from_crs(UTM10, OREGON_FT, always_xy=True)
    x, y = tr.transform(xyz_m[:, 0], xyz_m[:, 1])
    return np.column_stack([x, y, xyz_m[:, 2] / 0.3048])


def height_at(path: Path, x_m: float, y_m: float) -> float:
    with rasterio.open(path) as src:
        return float(next(src.sample([(x_m, y_m)]))[0])


def test_dsm_keeps_highest_return_and_writes_a_georeferenced_cog(tmp_path: Path) -> None:
    las = write_las(tmp_path / "scene.las", scene_points(outliers=30), UTM10)
    result = build_dsm([las], tmp_path / "dsm.tif", crs=UTM10, options=DsmOptions(cell_m=1.0))
    assert result.points_read == 120 * 120
    assert result.points_kept <= result.points_read - 30  # the 80 m outliers are gone
    assert result.warnings == ()
    assert cog_problems(result.path) == ()
    with rasterio.open(result.path) as src:
        assert src.crs.to_epsg() == 32610
        assert src.dtypes[0] == "float32" and src.nodata == DSM_NODATA
        # Grid aligned to whole metres, outer corner of the top-left cell (pixel-is-area).
        assert (src.transform.c, src.transform.f) == (E0_M, N0_M + 60.0)
        assert src.transform.a == 1.0 and src.transform.e == -1.0
        assert (src.width, src.height) == (60, 60)
    # Ground cell 5.5 m east: highest return = the plane at the cell's east points.
    assert height_at(result.path, E0_M + 5.5, N0_M + 5.5) == pytest.approx(
        Z0_M + SLOPE * 5.5, abs=HEIGHT_TOL_M)
    roof = height_at(result.path, E0_M + 25.5, N0_M + 25.5)
    assert roof == pytest.approx(Z0_M + SLOPE * 25.5 + BUILDING[4], abs=HEIGHT_TOL_M)
    assert result.height_range_m[1] < Z0_M + 60 * SLOPE + BUILDING[4] + 1.0  # no outlier left


def test_las_in_feet_is_converted_to_metres_in_the_working_crs(tmp_path: Path) -> None:
    xyz = scene_points()
    las = write_las(tmp_path / "feet.laz", to_feet(xyz), OREGON_FT)  # LAZ through lazrs
    result = build_dsm([las], tmp_path / "dsm.tif", crs=UTM10, options=DsmOptions(cell_m=1.0))
    assert any("no vertical datum" in w and "foot" in w for w in result.warnings)
    for de, dn in ((5.5, 5.5), (40.5, 12.5)):
        # Same heights as the metre scene, within a cell of slope (the grid is not aligned
        # with the rotated feet grid).
        assert height_at(result.path, E0_M + de, N0_M + dn) == pytest.approx(
            Z0_M + SLOPE * de, abs=3 * HEIGHT_TOL_M)
    assert height_at(result.path, E0_M + 25.5, N0_M + 25.5) > Z0_M + BUILDING[4]


def test_holes_are_interpolated_and_large_gaps_take_the_ground(tmp_path: Path) -> None:
    small = (50.0, 50.0, 52.0, 52.0)  # 4 m^2
    las = write_las(tmp_path / "a.las", scene_points(hole=small), UTM10)
    large = (5.0, 40.0, 15.0, 50.0)  # 100 m^2: its centre is 5 m from any return
    las2 = write_las(tmp_path / "b.las", scene_points(hole=large), UTM10)
    # Filter off: on this clean scene it only trims building corners (filled as holes too).
    opts = DsmOptions(cell_m=1.0, fill_distance_m=2.0, ground_cell_m=10.0, outlier_neighbors=0)
    filled = build_dsm([las], tmp_path / "a.tif", crs=UTM10, options=opts)
    assert (filled.interpolated_cells, filled.ground_cells, filled.nodata_cells) == (4, 0, 0)
    assert filled.warnings == ()
    assert height_at(filled.path, E0_M + 50.5, N0_M + 50.5) == pytest.approx(
        Z0_M + SLOPE * 50.5, abs=HEIGHT_TOL_M)
    gap = build_dsm([las2], tmp_path / "b.tif", crs=UTM10, options=opts)
    assert gap.nodata_cells == 0 and gap.interpolated_cells + gap.ground_cells == 100
    assert gap.ground_cells == 36  # the 6 x 6 cells more than 2 m from the rim
    assert any("ground fallback" in w and "coarser than the 1 m cell" in w
               for w in gap.warnings)
    with rasterio.open(gap.path) as src:
        assert src.tags()["SEQAT_GROUND_CELLS"] == "36"
        assert src.tags()["SEQAT_CELL_M"] == "1"
    # The lowest return of the 10 m ground cell under the gap's centre, on the 0.1 slope:
    # the plane within half a ground cell of slope.
    assert height_at(gap.path, E0_M + 10.5, N0_M + 45.5) == pytest.approx(
        Z0_M + SLOPE * 10.5, abs=SLOPE * 5.0 + HEIGHT_TOL_M)
    assert cog_problems(gap.path) == ()


def test_fill_gaps_interpolates_a_plane_exactly() -> None:
    """A synthetic gap in a tilted plane takes the plane's value (a TIN is exact on planes);
    cells beyond the data's outline stay nodata."""
    from rasterio.transform import from_origin

    from pipeline.ortho.dsm_fill import fill_gaps

    rows, cols = np.mgrid[0:40, 0:50]
    plane = (100.0 + 0.3 * cols - 0.2 * rows).astype(np.float32)
    heights = plane.copy()
    heights[10:14, 20:25] = np.nan  # the gap: 20 cells
    heights[:, 45:] = np.nan  # beyond the cloud's east edge
    transform = from_origin(0.0, 40.0, 1.0, 1.0)
    r, c = np.nonzero(np.isfinite(heights))
    xyz = np.column_stack([c + 0.5, 40.0 - r - 0.5, heights[r, c]])
    out, fill = fill_gaps(heights, transform, xyz, fill_distance_m=3.0, ground_cell_m=10.0)
    assert fill.interpolated_cells == 20 and fill.ground_cells == 0
    np.testing.assert_allclose(out[10:14, 20:25], plane[10:14, 20:25], atol=1e-4)
    assert np.all(np.isnan(out[:, 46:]))  # outside the outline (one cell closes the edge)
    assert fill.nodata_cells == int(np.isnan(out).sum())


def test_sparse_cloud_keeps_the_cell_asked_for(tmp_path: Path) -> None:
    """One point per 2 m^2 gridded at 0.5 m: the cell stays 0.5 m and every cell inside the
    cloud has a height (interpolated: 7 of 8 cells have no return)."""
    xyz = scene_points()[::4]  # every 4th point of each row: 2 m apart in x
    xyz = xyz[(np.floor((xyz[:, 1] - N0_M) / SPACING_M) % 2) == 0]  # every 2nd row: 1 m in y
    las = write_las(tmp_path / "sparse.las", xyz, UTM10)
    result = build_dsm([las], tmp_path / "sparse.tif", crs=UTM10,
                       options=DsmOptions(cell_m=0.5, outlier_neighbors=0))
    assert result.cell_m == 0.5 and result.ground_cells == 0
    with rasterio.open(result.path) as src:
        assert src.res == (0.5, 0.5)
        heights = src.read(1)
    occupied = result.rows * result.cols - result.interpolated_cells - result.nodata_cells
    assert occupied == len(xyz) and result.interpolated_cells > 6 * occupied
    assert np.count_nonzero(heights == DSM_NODATA) == result.nodata_cells
    assert result.nodata_cells < 0.03 * heights.size  # outside the hull of the ragged edge
    assert height_at(result.path, E0_M + 40.25, N0_M + 12.25) == pytest.approx(
        Z0_M + SLOPE * 40.25, abs=0.3)


def test_las_without_crs_needs_las_crs(tmp_path: Path) -> None:
    las = write_las(tmp_path / "nocrs.las", scene_points(), None)
    with pytest.raises(InputDataError, match="no CRS in the LAS file.*--las-crs"):
        build_dsm([las], tmp_path / "dsm.tif", crs=UTM10)
    assert not (tmp_path / "dsm.tif").exists()
    result = build_dsm([las], tmp_path / "dsm.tif", crs=UTM10, las_crs=UTM10)
    assert any("--las-crs" in w for w in result.warnings)


def test_empty_las_is_an_error(tmp_path: Path) -> None:
    las = write_las(tmp_path / "empty.las", np.zeros((0, 3)), UTM10)
    with pytest.raises(InputDataError, match="no points"):
        read_las(las)


def test_missing_and_corrupt_las_are_errors(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="no such LAS"):
        read_las(tmp_path / "none.las")
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"not a las file at all")
    with pytest.raises(InputDataError, match="cannot read LAS"):
        read_las(bad)


def test_cli_dsm_reports_a_missing_crs_in_one_line(tmp_path: Path) -> None:
    las = write_las(tmp_path / "nocrs.las", scene_points(), None)
    result = CliRunner().invoke(app, ["dsm", str(las), "--out", str(tmp_path / "d.tif"),
                                      "--crs", "EPSG:32610"])
    assert result.exit_code == 2
    assert "no CRS in the LAS file" in result.output
    wkt = tmp_path / "utm.wkt"
    wkt.write_text(UTM10.to_wkt())
    ok = CliRunner().invoke(app, ["dsm", str(las), "--out", str(tmp_path / "d.tif"),
                                  "--las-crs", str(wkt), "--cell-m", "2"])
    assert ok.exit_code == 0, ok.output
    with rasterio.open(tmp_path / "d.tif") as src:
        assert src.crs.to_epsg() == 32610 and src.transform.a == 2.0  # auto: UTM zone 10N


@pytest.mark.parametrize(("section", "message"), [
    ("dsm: {ground_cell_m: 0}", "ground_cell_m: expected a positive number of metres, got 0"),
    ("dsm: {fill_distance_m: -1}", "fill_distance_m: expected >= 0, got -1"),
    ("dsm: {fill_max_hole_m2: 25}", "dsm.fill_max_hole_m2: unknown key"),
])
def test_cli_dsm_bad_fill_options_are_one_line_exit_2(tmp_path: Path, section: str,
                                                      message: str) -> None:
    las = write_las(tmp_path / "a.las", scene_points(), UTM10)
    options = tmp_path / "o.yaml"
    options.write_text(section + "\n")
    result = CliRunner().invoke(app, ["dsm", str(las), "--out", str(tmp_path / "d.tif"),
                                      "--options", str(options)])
    assert result.exit_code == 2
    assert result.stderr.startswith("seqat: error: ") and result.stderr.count("\n") == 1
    assert message in result.stderr and str(options) in result.stderr
    assert sorted(tmp_path.iterdir()) == sorted([las, options])  # nothing written


def test_flight_lidar_is_gridded_at_the_cell_of_the_options(tmp_path: Path) -> None:
    """``seqat ortho`` / ``run --ortho`` grid the flight's LiDAR with the ``dsm:`` section
    (it was ignored: the live ortho always gridded at the default cell)."""
    from pipeline.ortho.stage import find_dsm

    autzen = Path(__file__).resolve().parents[3] / "sample_data" / "autzen_rendered"
    dsm, warnings = find_dsm(tmp_path, UTM10, None, autzen, DsmOptions(cell_m=0.5))
    assert dsm is not None and dsm.cell_m == (0.5, 0.5)
    with rasterio.open(tmp_path / "dsm.tif") as src:
        assert src.res == (0.5, 0.5) and src.tags()["SEQAT_CELL_M"] == "0.5"
        heights, ground = src.read(1), int(src.tags()["SEQAT_GROUND_CELLS"])
    # The sparse sample cloud (0.47 points/m^2) at 0.5 m: no hole inside, ground fallback in
    # well under 1 % of the cells, and said so.
    assert 0 < ground < 0.01 * heights.size
    assert any("ground fallback" in w for w in warnings)


def test_read_dsm_reprojects_a_feet_dsm(tmp_path: Path) -> None:
    las = write_las(tmp_path / "feet.las", to_feet(scene_points()), OREGON_FT)
    result = build_dsm([las], tmp_path / "dsm_ft.tif", crs=pyproj.CRS.from_epsg(32610),
                       options=DsmOptions(cell_m=1.0))
    dsm = read_dsm(result.path, UTM10)
    assert dsm.sample(np.array([E0_M + 5.5]), np.array([N0_M + 5.5]))[0] == pytest.approx(
        Z0_M + SLOPE * 5.5, abs=3 * HEIGHT_TOL_M)
    with pytest.raises(InputDataError, match="no such DSM"):
        read_dsm(tmp_path / "none.tif", UTM10)


def test_dsm_samples_bilinearly_and_flat_plane_is_flat() -> None:
    from rasterio.transform import from_origin

    heights = np.array([[0.0, 10.0], [20.0, 30.0]], np.float32)
    dsm = Dsm(heights_m=heights, transform=from_origin(0.0, 2.0, 1.0, 1.0), crs=UTM10,
              source="t")
    # Cell centres at (0.5, 1.5), (1.5, 1.5), (0.5, 0.5), (1.5, 0.5).
    z = dsm.sample(np.array([1.0, 0.5, 5.0]), np.array([1.0, 1.5, 5.0]))
    assert z[0] == pytest.approx(15.0) and z[1] == pytest.approx(0.0) and np.isnan(z[2])
    plane = flat_dsm(12.5, (100.0, 200.0, 300.0, 400.0), UTM10)
    w, s, e, n = plane.bounds
    assert w < 100 and s < 200 and e > 300 and n > 400
    assert plane.height_range((150.0, 250.0, 160.0, 260.0)) == (12.5, 12.5)


def test_flat_fallback_plane_is_not_moved_by_a_wild_tie_point(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without a DSM the plane lies at the median tie point height: one point that blunders
    sent 3 km under the ground (σ of hundreds of metres, published as estimated) must not
    drop it (the mean did, by 3000 / n metres)."""
    import pipeline.ortho.stage as stage
    from pipeline.common.tables import EopTable

    monkeypatch.setattr(stage, "find_dsm", lambda *a, **k: (None, ()))
    eops = EopTable(image_ids=("a", "b"), eop=np.array([[500000.0, 4100000.0, 220.0, 0, 0, 0],
                                                        [500050.0, 4100000.0, 220.0, 0, 0, 0]]),
                    sigma=np.full((2, 6), 0.01))
    z = np.array([100.0, 101.0, 99.0, 100.5, -2900.0])
    plane, (warning,) = stage.choose_dsm(tmp_path, UTM10, None, tmp_path, eops, z)
    assert plane.height_range((499990.0, 4099990.0, 500060.0, 4100010.0)) == (100.0, 100.0)
    assert "median tie point height 100.00 m" in warning


def test_parse_las_crs_reads_epsg_and_wkt_files(tmp_path: Path) -> None:
    assert parse_las_crs("EPSG:2994").equals(OREGON_FT)
    path = tmp_path / "crs.wkt"
    path.write_text(OREGON_FT.to_wkt())
    assert parse_las_crs(str(path)).equals(OREGON_FT)


@pytest.mark.shared
def test_autzen_las_gives_a_dsm_in_metres(shared_data: Path, tmp_path: Path) -> None:
    folder = shared_data / "autzen"
    wkt = pyproj.CRS.from_wkt((folder / "autzen-srs.wkt").read_text())
    # The WKT beside the data is EPSG:2994 (Oregon GIC Lambert, international feet).
    assert wkt.equals(OREGON_FT, ignore_axis_order=True)
    assert read_las(folder / "autzen_trim.las").crs.equals(OREGON_FT, ignore_axis_order=True)
    result = build_dsm([folder / "autzen_trim.las"], tmp_path / "dsm.tif", crs=UTM10,
                       options=DsmOptions(cell_m=1.0))
    assert result.points_read == 110000
    assert 0.9 * result.points_read < result.points_kept < result.points_read
    # Autzen stadium, Eugene OR: ground ~ 125 m above sea level, trees and stands above.
    assert 115.0 < result.height_range_m[0] < 135.0 < result.height_range_m[1] < 200.0
    assert cog_problems(result.path) == ()
    # Where it is: Autzen Stadium, Eugene, Oregon (44.058 N, 123.069 W), within 2 km.
    west, south, east, north = result.bounds
    to_geo = pyproj.Transformer.from_crs(UTM10, "EPSG:4326", always_xy=True)
    lon, lat = to_geo.transform((west + east) / 2, (south + north) / 2)
    stadium = pyproj.Geod(ellps="WGS84").inv(lon, lat, AUTZEN_LON, AUTZEN_LAT)[2]
    assert stadium < 2000.0
    with pytest.raises(InputDataError, match="no CRS"):
        read_las(folder / "autzen-thin.las")
    thin = build_dsm([folder / "autzen-thin.las"], tmp_path / "thin.tif", crs=UTM10,
                     las_crs=parse_las_crs(str(folder / "autzen-srs.wkt")),
                     options=DsmOptions(cell_m=5.0))
    assert thin.points_read == 10653


def test_truncated_las_says_so(tmp_path: Path) -> None:
    import laspy

    from pipeline.ortho.dsm import read_las
    from seqat.errors import InputDataError

    las = laspy.read("sample_data/autzen_rendered/lidar/surface.laz")
    path = tmp_path / "cut.las"
    las.write(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 1000 - 3])  # not a whole number of points
    n, size = len(las.points), las.header.point_format.size
    with pytest.raises(InputDataError) as err:
        read_las(path)
    assert str(err.value).startswith(
        f"{path}: truncated LAS file: the header announces {n} points ({n * size} bytes of "
        f"point data) but the file holds ")
    laz = tmp_path / "cut.laz"
    raw = Path("sample_data/autzen_rendered/lidar/surface.laz").read_bytes()
    laz.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputDataError, match="truncated or damaged LAZ file|cannot read"):
        read_las(laz)


@pytest.mark.parametrize(("offset", "value", "message"), [
    (147, 0.0, "damaged LAS header: scales"),          # z scale
    (131, float("nan"), "damaged LAS header: scales"),  # x scale
    (139, -0.01, "damaged LAS header: scales"),          # y scale < 0: a mirrored cloud
    (171, float("inf"), "damaged LAS header: scales"),  # z offset
    (171, 1e300, "are not plausible"),                  # z offset
    (147, 1e300, "are not plausible"),                  # z scale
])
def test_damaged_las_header_values_are_errors(tmp_path: Path, offset: int, value: float,
                                              message: str) -> None:
    """Found by seqat bench fuzz: such headers gave an all-nodata, flat or mirrored DSM,
    exit 0."""
    import struct

    las = write_las(tmp_path / "a.las", scene_points(), UTM10)
    data = bytearray(las.read_bytes())
    struct.pack_into("<d", data, offset, value)
    las.write_bytes(bytes(data))
    with pytest.raises(InputDataError, match=message):
        read_las(las)
