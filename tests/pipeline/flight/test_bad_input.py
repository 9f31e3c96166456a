"""Issue 13: bad input files are accepted when harmless and reported precisely otherwise."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from pipeline.common.csvio import CsvTail
from pipeline.flight.folder import read_flight
from seqat.errors import ConfigError, InputDataError

from ..sample_flight import FLIGHT_YAML, NAV_CSV, OBSERVATIONS_CSV, FlightMaker


def test_nav_and_observations_with_a_utf8_bom_are_read(make_flight: FlightMaker) -> None:
    flight = read_flight(make_flight(**{"nav.csv": "\ufeff" + NAV_CSV,
                                        "observations.csv": "\ufeff" + OBSERVATIONS_CSV}))
    assert flight.nav.image_ids == ("img_1", "img_2", "img_3", "img_4")
    assert [f.image_id for f in flight.frames()][0] == "img_1"


def test_latin1_byte_is_reported_at_its_line(make_flight: FlightMaker) -> None:
    folder = make_flight()
    lines = [f"img_{k},{k * 0.5},{500000 + k},4090000.0,300.0,0.5,-0.25,90.0\n"
             for k in range(1, 400)]  # far beyond the text decoder's first chunk
    text = "image,time_s,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg\n" + "".join(lines)
    raw = text.encode() + "img_caf\u00e9,999.0,1,2,3,4,5,6\n".encode("latin-1")
    (folder / "nav.csv").write_bytes(raw)
    with pytest.raises(InputDataError) as err:
        read_flight(folder)
    assert str(err.value) == (f"{folder / 'nav.csv'}:401: not UTF-8: byte 0xe9 at column 8 "
                              "(save the file as UTF-8)")


def test_watched_csv_accepts_a_bom(tmp_path: Path) -> None:
    path = tmp_path / "nav.csv"
    path.write_bytes(b"\xef\xbb\xbf" + NAV_CSV.encode())
    rows = CsvTail(path, NAV_CSV.splitlines()[0].split(",")).poll()
    assert [r.values["image"] for r in rows] == ["img_1", "img_2", "img_3", "img_4"]


def test_observations_a_hair_outside_are_kept(make_flight: FlightMaker) -> None:
    obs = OBSERVATIONS_CSV.replace("img_4,p4,10.0,11.0", "img_4,p4,-1.93,11.0")
    frames = list(read_flight(make_flight(**{"observations.csv": obs})).frames())
    assert frames[3].point_ids == ("p3", "p4")


def test_observations_far_outside_are_dropped_with_a_warning(make_flight: FlightMaker) -> None:
    obs = OBSERVATIONS_CSV.replace("img_4,p4,10.0,11.0", "img_4,p4,700.0,11.0")
    obs = obs.replace("img_2,p3,500.0,100.0", "img_2,p3,500.0,-30.0")
    folder = make_flight(**{"observations.csv": obs})
    flight = read_flight(folder)
    stats = flight.frames().validate()
    assert stats.n_observations == 5
    assert stats.warnings == (
        f"{folder / 'observations.csv'}: 2 of 7 observation(s) lie more than 5 sigma_image_px "
        f"outside the image and were left out (first: {folder / 'observations.csv'}:6: pixel "
        "(500.0, -30.0) of point 'p3' lies outside the 640 x 480 px image)",)
    frames = list(flight.frames())
    assert frames[1].point_ids == ("p1", "p2") and frames[3].point_ids == ("p3",)


MINI = Path("sample_data/seneca_mini/images")


def _mini_copy(tmp_path: Path, n: int) -> list[Path]:
    (tmp_path / "images").mkdir()
    return [Path(shutil.copy(p, tmp_path / "images" / p.name))
            for p in sorted(MINI.glob("*.jpg"))[:n]]


def test_the_same_photo_twice_is_skipped_naming_both(tmp_path: Path) -> None:
    paths = _mini_copy(tmp_path, 3)
    shutil.copy(paths[1], tmp_path / "images" / "IMG_0461_copy.jpg")
    flight = read_flight(tmp_path)
    reasons = [s.reason for s in flight.skipped]
    assert reasons == ["IMG_0461_copy.jpg: a duplicate of IMG_0461.jpg (an identical file); "
                       "left out"]
    assert flight.nav.image_ids == ("IMG_0460", "IMG_0461", "IMG_0462")


def test_a_camera_change_mid_flight_is_refused(tmp_path: Path) -> None:
    paths = _mini_copy(tmp_path, 4)
    data = paths[2].read_bytes()
    paths[2].write_bytes(data.replace(b"PowerShot ELPH 300 HS", b"PowerShot ELPH 999 HS", 1))
    with pytest.raises(InputDataError) as err:
        read_flight(tmp_path)
    assert str(err.value) == (
        "IMG_0462.jpg: taken with another camera (Canon PowerShot ELPH 999 HS, 4.3 mm) "
        "than IMG_0460.jpg (Canon PowerShot ELPH 300 HS, 4.3 mm); one camera per "
        "flight is supported (split the flight by camera)")


def test_a_flight_outside_the_crs_area_of_use_is_warned_about(make_flight: FlightMaker) -> None:
    yaml = FLIGHT_YAML.replace("EPSG:32652", "EPSG:2154")  # Lambert-93: France, not Korea
    folder = make_flight(**{"flight.yaml": yaml})
    flight = read_flight(folder)
    assert len(flight.warnings) == 1
    assert flight.warnings[0].startswith(f"{folder / 'flight.yaml'}: crs: the flight's centre (")
    assert "lies outside the area of use of 'RGF93 v1 / Lambert-93' (" in flight.warnings[0]


# --- found by seqat bench fuzz ----------------------------------------------------------------

@pytest.mark.parametrize(("field", "value", "message"), [
    ("x_m", "1e300", "field 'x_m': '1e300' is not a plausible coordinate"),
    ("z_m", "-9e15", "field 'z_m': '-9e15' is not a plausible height"),
    ("kappa_deg", "1e12", "field 'kappa_deg': '1e12' is not a plausible angle"),
    ("time_s", "1e300", "field 'time_s': '1e300' is not a plausible time"),
    ("x_m", "1_000", "field 'x_m': expected a finite number, got '1_000'"),
    ("y_m", "\uff11\uff12", "field 'y_m': expected a finite number, got '\uff11\uff12'"),
])
def test_implausible_and_non_ascii_numbers_are_refused(make_flight: FlightMaker, field: str,
                                                       value: str, message: str) -> None:
    lines = NAV_CSV.splitlines()
    header = lines[0].split(",")
    row = lines[2].split(",")
    row[header.index(field)] = value
    lines[2] = ",".join(row)
    folder = make_flight(**{"nav.csv": "\n".join(lines) + "\n"})
    with pytest.raises(InputDataError) as err:
        read_flight(folder)
    assert str(err.value).startswith(f"{folder / 'nav.csv'}:3: {message}")


def test_a_pixel_far_beyond_the_image_is_left_out_not_refused(make_flight: FlightMaker) -> None:
    """Pixels are measured against the frame, not a magnitude bound: one corrupt value is
    left out with a warning like any observation far outside."""
    obs = OBSERVATIONS_CSV.replace("img_4,p4,10.0,11.0", "img_4,p4,-9e15,11.0")
    frames = list(read_flight(make_flight(**{"observations.csv": obs})).frames())
    assert frames[3].point_ids == ("p3",)


@pytest.mark.parametrize(("old", "new", "message"), [
    ("sigma_image_px: 1.5", "sigma_image_px: 1e12", "sigma_image_px: expected a number in"),
    ("fx_px: 1000.0", "fx_px: 1e300", "camera.fx_px: expected a number in"),
    ("cx_px: 319.5", "cx_px: 1e12", "camera.cx_px: expected a number in"),
    ("sigma_attitude_deg: [0.1, 0.1, 0.2]", "sigma_attitude_deg: 1e300",
     r"nav.sigma_attitude_deg: expected sigmas in \[1e-05, 180\]"),
    ("sigma_position_m: 0.3", "sigma_position_m: [0.3, 0.3, 1e9]",
     "nav.sigma_position_m: expected sigmas in"),
    ("sigma_image_px: 1.5", "sigma_image_px: 1e-300", "sigma_image_px: expected a number in"),
    ("sigma_position_m: 0.3", "sigma_position_m: 1e-300", "nav.sigma_position_m: expected"),
])
def test_implausible_flight_yaml_numbers_name_the_key(make_flight: FlightMaker, old: str,
                                                      new: str, message: str) -> None:
    assert old in FLIGHT_YAML, old
    folder = make_flight(**{"flight.yaml": FLIGHT_YAML.replace(old, new)})
    with pytest.raises(ConfigError, match=message):
        read_flight(folder)


@pytest.mark.parametrize("name", ["flight.yaml", "observations.csv"])
def test_a_folder_where_a_file_is_expected_is_named(make_flight: FlightMaker, name: str) -> None:
    folder = make_flight()
    (folder / name).unlink()
    (folder / name).mkdir()
    with pytest.raises(InputDataError, match=f"{name}: is a folder, expected a file"):
        read_flight(folder)


def test_a_looping_symlink_is_named(make_flight: FlightMaker) -> None:
    folder = make_flight()
    (folder / "observations.csv").unlink()
    (folder / "observations.csv").symlink_to("observations.csv")
    with pytest.raises(InputDataError, match="is a broken or looping symbolic link"):
        read_flight(folder)


def test_two_files_with_one_image_id_keep_the_first(tmp_path: Path) -> None:
    """Found by seqat bench fuzz: IMG_0462.jpg beside IMG_0462.JPEG was a KeyError (exit 1)."""
    src = Path(__file__).resolve().parents[3] / "sample_data" / "seneca_mini" / "images"
    folder = tmp_path / "flight"
    folder.mkdir()
    for p in sorted(src.glob("*.jpg"))[:3]:
        shutil.copy2(p, folder / p.name)
    first = sorted(folder.glob("*.jpg"))[1]
    shutil.copy2(first, first.with_suffix(".JPEG"))
    flight = read_flight(folder)
    assert len(flight.nav) == 3
    assert [s.image for s in flight.skipped] == [first.name]
    assert f"same image id {first.stem!r} as {first.stem}.JPEG" in flight.skipped[0].reason


def test_truth_that_is_a_file_is_an_error(tmp_path: Path) -> None:
    """Found by seqat bench fuzz: a file named truth was silently taken for no truth."""
    from pipeline.flight.folder import read_truth

    (tmp_path / "truth").write_text("not a folder\n")
    with pytest.raises(InputDataError, match=r"truth: is a file, expected a folder"):
        read_truth(tmp_path)
    (tmp_path / "truth").unlink()
    assert read_truth(tmp_path) is None
