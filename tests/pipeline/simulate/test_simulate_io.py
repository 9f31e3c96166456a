"""Simulated flights written as flight folders: exact round trip, all-or-nothing writes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipeline.flight.folder import read_flight
from pipeline.flight.schema import load_flight_config
from pipeline.simulate import folder as simulate_io
from pipeline.simulate.folder import write_simulated_flight
from pipeline.simulate.stage import simulate_to_folder
from seqat.errors import InputDataError
from seqat.simulate import SimulatedFlight

from ..sample_flight import SIM_CRS

#: Tolerance of angles after degrees <-> radians (radians) and of sigmas in flight.yaml.
ANGLE_TOL_RAD = 1e-15
SIGMA_RTOL = 1e-11


def test_frames_read_back_equal_simulated_frames(small_sim: SimulatedFlight,
                                                 small_sim_dir: Path) -> None:
    flight = read_flight(small_sim_dir)
    assert flight.camera == small_sim.camera
    assert flight.nav.image_ids == small_sim.image_ids
    np.testing.assert_array_equal(flight.nav.times_s, small_sim.times_s)
    got, want = list(flight.frames()), list(small_sim.frames())
    assert len(got) == len(want) == len(small_sim.image_ids)
    for g, w in zip(got, want, strict=True):
        assert g.image_id == w.image_id and g.point_ids == w.point_ids
        np.testing.assert_array_equal(g.uv_px, w.uv_px)
        np.testing.assert_array_equal(g.nav_eop[:3], w.nav_eop[:3])
        np.testing.assert_allclose(g.nav_eop[3:], w.nav_eop[3:], rtol=0, atol=ANGLE_TOL_RAD)
        np.testing.assert_allclose(g.nav_sigma, w.nav_sigma, rtol=SIGMA_RTOL)
        assert g.sigma_px == w.sigma_px


def test_flight_yaml_describes_the_simulation(small_sim: SimulatedFlight,
                                              small_sim_dir: Path) -> None:
    cfg = load_flight_config(small_sim_dir / "flight.yaml")
    assert cfg.crs == SIM_CRS and cfg.camera.model == "PINHOLE"
    assert cfg.camera.fx_px == cfg.camera.fy_px == small_sim.camera.f_px
    assert cfg.nav.frame == "projected" and cfg.observations == "observations.csv"
    assert sorted(p.name for p in small_sim_dir.iterdir()) == [
        "flight.yaml", "nav.csv", "observations.csv", "truth"]


def test_observations_are_grouped_by_image(small_sim: SimulatedFlight, tmp_path: Path) -> None:
    order = np.random.default_rng(5).permutation(small_sim.obs_image.size)
    shuffled = dataclasses.replace(small_sim, obs_image=small_sim.obs_image[order],
                                   obs_point=small_sim.obs_point[order],
                                   obs_uv=small_sim.obs_uv[order])
    out = write_simulated_flight(shuffled, SIM_CRS, tmp_path / "flight")
    frames = list(read_flight(out).frames())  # would raise on non-contiguous rows
    want = {f.image_id: dict(zip(f.point_ids, map(tuple, f.uv_px), strict=True))
            for f in small_sim.frames()}
    for frame in frames:
        assert dict(zip(frame.point_ids, map(tuple, frame.uv_px), strict=True)) == \
            want[frame.image_id]


def test_refuses_to_replace_a_folder_that_is_not_a_flight(small_sim: SimulatedFlight,
                                                          tmp_path: Path) -> None:
    target = tmp_path / "precious"
    target.mkdir()
    (target / "thesis.tex").write_text("do not delete")
    with pytest.raises(InputDataError, match="is not a flight folder"):
        write_simulated_flight(small_sim, SIM_CRS, target)
    assert (target / "thesis.tex").read_text() == "do not delete"


def test_replaces_an_earlier_flight_without_leftovers(small_sim: SimulatedFlight,
                                                      tmp_path: Path) -> None:
    out = tmp_path / "flight"
    write_simulated_flight(small_sim, SIM_CRS, out)
    (out / "stale.txt").write_text("from the old flight")
    write_simulated_flight(small_sim, "EPSG:32633", out)
    assert not (out / "stale.txt").exists()
    assert load_flight_config(out / "flight.yaml").crs == "EPSG:32633"
    assert [p.name for p in tmp_path.iterdir()] == ["flight"]  # no temp or old folders


def test_failure_midway_keeps_previous_flight(small_sim: SimulatedFlight, tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "flight"
    write_simulated_flight(small_sim, SIM_CRS, out)
    before = (out / "observations.csv").read_text()
    real_write = simulate_io.write_synced

    def failing_write(path: Path, text: str) -> None:
        if path.name == "points.csv":
            raise OSError(28, "No space left on device")
        real_write(path, text)

    monkeypatch.setattr(simulate_io, "write_synced", failing_write)
    with pytest.raises(OSError, match="No space left"):
        write_simulated_flight(small_sim, "EPSG:32633", out)
    assert (out / "observations.csv").read_text() == before
    assert load_flight_config(out / "flight.yaml").crs == SIM_CRS
    assert [p.name for p in tmp_path.iterdir()] == ["flight"]
    with pytest.raises(OSError):
        write_simulated_flight(small_sim, SIM_CRS, tmp_path / "fresh")
    assert not (tmp_path / "fresh").exists()


def test_simulate_to_folder_is_seeded(tmp_path: Path) -> None:
    config = tmp_path / "sim.yaml"
    config.write_text("kind: observations\ncrs: EPSG:32652\n"
                      "simulation: {n_images: 8, n_points: 12}\n")
    a = simulate_to_folder(config, tmp_path / "a", seed=3)
    simulate_to_folder(config, tmp_path / "b", seed=3)
    simulate_to_folder(config, tmp_path / "c", seed=4)
    assert a.n_images == 8 and a.n_observations > 0 and a.duration_s == pytest.approx(3.5)
    text = {d: (tmp_path / d / "observations.csv").read_text() for d in "abc"}
    assert text["a"] == text["b"] != text["c"]


def test_simulate_rejects_geographic_crs_before_writing(tmp_path: Path) -> None:
    config = tmp_path / "sim.yaml"
    config.write_text("kind: observations\ncrs: EPSG:4326\n")
    with pytest.raises(InputDataError, match=r"sim\.yaml: crs: 'EPSG:4326' .* not a projected"):
        simulate_to_folder(config, tmp_path / "flight", seed=1)
    assert not (tmp_path / "flight").exists()
