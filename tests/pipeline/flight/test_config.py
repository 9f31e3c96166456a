"""Strict YAML -> dataclass loader and the pipeline config classes."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pytest

from pipeline.common.strict_yaml import build_dataclass, load_yaml
from pipeline.flight.schema import CameraConfig, FlightConfig, load_flight_config
from pipeline.simulate.config import load_simulate_config
from seqat.errors import ConfigError
from seqat.simulate import StripSimConfig
from seqat.types import FloatArray

REPO_ROOT = Path(__file__).resolve().parents[3]


@dataclass(frozen=True, kw_only=True)
class Inner:
    size_m: float = 1.0
    count: int = 2


@dataclass(frozen=True, kw_only=True)
class Outer:
    name: str
    mode: Literal["fast", "exact"] = "fast"
    inner: Inner = Inner()
    weights: tuple[float, ...] = ()
    pair: tuple[int, int] = (0, 0)
    matrix: FloatArray = dataclasses.field(default_factory=lambda: np.eye(2))
    optional: float | None = None
    sigma: float | tuple[float, float, float] = 1.0


def write(tmp_path: Path, text: str, name: str = "x.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_nested_values_convert_to_annotated_types(tmp_path: Path) -> None:
    path = write(tmp_path, "name: a\nmode: exact\ninner: {size_m: 2, count: 5}\n"
                           "weights: [1, 2.5]\npair: [3, 4]\nmatrix: [[1, 2], [3, 4]]\n"
                           "optional: 1e-3\nsigma: [0.1, 0.2, 0.3]\n")
    cfg = build_dataclass(Outer, load_yaml(path), str(path))
    assert cfg.inner == Inner(size_m=2.0, count=5)
    assert isinstance(cfg.inner.size_m, float)
    assert cfg.weights == (1.0, 2.5) and cfg.pair == (3, 4)
    np.testing.assert_array_equal(cfg.matrix, [[1.0, 2.0], [3.0, 4.0]])
    assert cfg.optional == pytest.approx(1e-3)  # YAML 1.1 would read '1e-3' as a string
    assert cfg.sigma == (0.1, 0.2, 0.3)
    assert cfg.mode == "exact"


def test_defaults_fill_missing_keys(tmp_path: Path) -> None:
    cfg = build_dataclass(Outer, {"name": "b", "inner": None}, "x.yaml")
    assert cfg.inner == Inner() and cfg.optional is None and cfg.sigma == 1.0


@pytest.mark.parametrize(("text", "message"), [
    ("name: a\ninner: {size_mm: 2}\n",
     "x.yaml: inner.size_mm: unknown key (expected one of: count, size_m)"),
    ("name: a\ncolour: red\n", "x.yaml: colour: unknown key"),
    ("name: a\ninner: {count: many}\n", "x.yaml: inner.count: expected an integer, got 'many'"),
    ("name: a\ninner: {count: 2.5}\n", "x.yaml: inner.count: expected an integer, got 2.5"),
    ("name: a\ninner: {count: true}\n", "x.yaml: inner.count: expected an integer, got True"),
    ("name: a\ninner: {size_m: .nan}\n", "x.yaml: inner.size_m: expected a finite number"),
    ("name: 3\n", "x.yaml: name: expected a string, got 3"),
    ("inner: {}\n", "x.yaml: name: missing required key"),
    ("name: a\nmode: slow\n", "x.yaml: mode: expected one of 'fast', 'exact', got 'slow'"),
    ("name: a\npair: [1, 2, 3]\n", "x.yaml: pair: expected a list of 2 integers"),
    ("name: a\nweights: [1, x]\n", "x.yaml: weights[1]: expected a finite number, got 'x'"),
    ("name: a\nmatrix: [[1, 2], [3]]\n", "x.yaml: matrix: expected a (nested) list"),
    ("name: a\nsigma: [1, 2]\n", "x.yaml: sigma: expected a finite number or a list of 3"),
    ("name: a\ninner: 5\n", "x.yaml: inner: expected a mapping of keys, got 5"),
])
def test_bad_values_name_file_key_and_value(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        build_dataclass(Outer, load_yaml(path), "x.yaml")
    assert message in str(info.value)


@pytest.mark.parametrize(("text", "message"), [
    ("a: 1\na: 2\n", "x.yaml:2:1: invalid YAML: duplicate key 'a'"),
    ("a: [1, 2\n", "x.yaml:2:1: invalid YAML"),
    ("- 1\n- 2\n", "x.yaml: expected a mapping of keys at the top level"),
])
def test_load_yaml_rejects_bad_documents(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_yaml(path)
    assert str(info.value).startswith(str(tmp_path))
    assert message in str(info.value)


def test_missing_file_is_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="nope.yaml: cannot read"):
        load_yaml(tmp_path / "nope.yaml")


def test_dataclass_validation_errors_carry_file_and_section(tmp_path: Path) -> None:
    path = write(tmp_path, "kind: observations\ncrs: EPSG:32652\nsimulation: {n_images: 1}\n",
                 "s.yaml")
    with pytest.raises(ConfigError) as info:
        load_simulate_config(path)
    assert str(info.value) == (f"{path}: simulation.n_images: expected at least 2, got 1")


def test_unknown_simulation_key_is_named(tmp_path: Path) -> None:
    path = write(tmp_path, "kind: observations\ncrs: EPSG:32652\nsimulation: {n_imagse: 5}\n")
    with pytest.raises(ConfigError, match=r"x\.yaml: simulation\.n_imagse: unknown key "
                                          r"\(expected one of: attitude_wander_deg, "):
        load_simulate_config(path)


@pytest.mark.parametrize("name", ["paper_sim.yaml", "demo_sim.yaml"])
def test_shipped_simulation_configs_load(name: str) -> None:
    cfg = load_simulate_config(REPO_ROOT / "configs" / name)
    assert cfg.kind == "observations" and cfg.crs == "EPSG:32652"
    if name == "paper_sim.yaml":
        assert cfg.simulation == StripSimConfig()  # the paper strip = the defaults


def camera(**overrides: object) -> dict[str, object]:
    base: dict[str, object] = {"model": "PINHOLE", "width_px": 640, "height_px": 480,
                               "fx_px": 1000.0, "fy_px": 1000.0, "cx_px": 319.5, "cy_px": 239.5}
    return {**base, **overrides}


def flight_mapping(**camera_overrides: object) -> dict[str, object]:
    return {"crs": "EPSG:32652", "camera": camera(**camera_overrides),
            "nav": {"sigma_position_m": 0.3, "sigma_attitude_deg": [0.1, 0.1, 0.2]}}


def test_flight_config_nav_sigmas_in_metres_and_radians() -> None:
    cfg = build_dataclass(FlightConfig, flight_mapping(), "flight.yaml")
    np.testing.assert_allclose(cfg.nav.sigma_eop, [0.3, 0.3, 0.3, *np.radians([0.1, 0.1, 0.2])],
                               rtol=0, atol=1e-15)
    assert cfg.sigma_image_px == 1.0 and cfg.nav.file == "nav.csv"


@pytest.mark.parametrize(("overrides", "message"), [
    ({"fy_px": 1001.0}, "camera.fy_px: a PINHOLE camera has square pixels"),
    ({"k1": -0.1}, "camera: a PINHOLE camera has no distortion"),
    ({"model": "FISHEYE"}, "camera.model: expected one of 'PINHOLE', 'OPENCV'"),
    ({"width_px": 0}, "camera.width_px: expected a positive integer, got 0"),
])
def test_bad_camera_is_config_error(overrides: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        build_dataclass(FlightConfig, flight_mapping(**overrides), "flight.yaml")
    assert str(info.value).startswith("flight.yaml: ")
    assert message in str(info.value)


def test_opencv_camera_keeps_distortion() -> None:
    cfg = build_dataclass(CameraConfig, camera(model="OPENCV", fy_px=1010.0, k1=-0.1, p2=1e-4),
                          "flight.yaml", key="camera")
    np.testing.assert_array_equal(cfg.distortion, [-0.1, 0.0, 0.0, 1e-4, 0.0])


def test_nav_sigma_must_be_positive(tmp_path: Path) -> None:
    mapping = flight_mapping()
    mapping["nav"] = {"sigma_position_m": [0.3, 0.0, 0.3], "sigma_attitude_deg": 0.1}
    with pytest.raises(ConfigError, match="flight.yaml: nav.sigma_position_m: expected a "
                                          "positive number"):
        build_dataclass(FlightConfig, mapping, "flight.yaml")


def test_load_flight_config_reads_file(make_flight: Callable[..., Path]) -> None:
    cfg = load_flight_config(make_flight() / "flight.yaml")
    assert cfg.observations == "observations.csv" and cfg.sigma_image_px == 1.5
    assert cfg.nav.sigma_attitude_deg == (0.1, 0.1, 0.2)


def test_choices_in_any_case(tmp_path: Path) -> None:
    """A Literal or Enum choice in any case, as the command line's choice options (issue 14);
    the value is the choice as declared."""
    path = write(tmp_path, "name: a\nmode: Exact\n")
    assert build_dataclass(Outer, load_yaml(path), str(path)).mode == "exact"
    path = write(tmp_path, "name: a\nmode: quick\n")
    with pytest.raises(ConfigError, match="x.yaml: mode: expected one of 'fast', 'exact', "
                                          "got 'quick'"):
        build_dataclass(Outer, load_yaml(path), str(path))
    path = write(tmp_path, "model: pinhole\nwidth_px: 10\nheight_px: 8\nfx_px: 5\n"
                           "fy_px: 5\ncx_px: 5\ncy_px: 4\n")
    assert build_dataclass(CameraConfig, load_yaml(path), str(path)).model == "PINHOLE"
