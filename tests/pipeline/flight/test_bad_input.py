"""Issue 13: bad input files are accepted when harmless and reported precisely otherwise."""

from __future__ import annotations

import pytest

from pipeline.common.csvio import CsvTail
from pipeline.flight.folder import read_flight
from seqat.errors import InputDataError

from ..sample_flight import NAV_CSV, OBSERVATIONS_CSV, FlightMaker


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


def test_watched_csv_accepts_a_bom(tmp_path) -> None:
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
