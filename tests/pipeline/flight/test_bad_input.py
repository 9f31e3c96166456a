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
