"""The shipped sample flight is what the simulator writes, and it adjusts as documented."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.flight.folder import read_flight, read_truth
from pipeline.simulate.stage import simulate_to_folder

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_data" / "strip_demo"


def test_sample_flight_matches_its_recipe(tmp_path: Path) -> None:
    out = tmp_path / "flight"
    simulate_to_folder(ROOT / "configs" / "demo_sim.yaml", out, seed=1)
    for name in ("nav.csv", "observations.csv", "truth/eop.csv", "truth/points.csv"):
        a = (SAMPLE / name).read_text().splitlines()
        b = (out / name).read_text().splitlines()
        assert a[0] == b[0] and len(a) == len(b), name
        for la, lb in zip(a[1:], b[1:], strict=True):
            fa, fb = la.split(","), lb.split(",")
            assert fa[:1] == fb[:1]
            na = [float(v) for v in fa if _is_number(v)]
            nb = [float(v) for v in fb if _is_number(v)]
            np.testing.assert_allclose(na, nb, rtol=1e-12, atol=1e-9)


def _is_number(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def test_sample_flight_reads_and_has_truth() -> None:
    flight = read_flight(SAMPLE)
    frames = list(flight.frames())
    assert len(frames) == 60
    assert read_truth(SAMPLE) is not None


RENDERED = ROOT / "sample_data" / "autzen_rendered"


def test_rendered_sample_reads_with_nav_near_truth() -> None:
    flight = read_flight(RENDERED)
    truth = read_truth(RENDERED)
    assert flight.kind == "images" and not flight.skipped and len(flight.nav) == 12
    assert truth is not None and truth.eop.image_ids == flight.nav.image_ids
    d = np.linalg.norm(flight.nav.eop[:, :3] - truth.eop.eop[:, :3], axis=1)
    assert 0.0 < d.max() < 0.5  # configured noise: 0.05 m white + 0.01 m/sqrt(s) drift
    assert len(truth.points.point_ids) >= 30
    assert sum(p.stat().st_size for p in RENDERED.rglob("*") if p.is_file()) < 3_000_000
