"""The flight report: ASPRS table, precision plateau, report.json values, CLI errors."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.common.columns import CHECKPOINT_OBS_FILE, CHECKPOINTS_FILE
from pipeline.flight.camera import pinhole_camera
from pipeline.flight.folder import read_truth
from pipeline.reference.stage import run_reference
from pipeline.report.asprs import ASPRS_MIN_CHECKPOINTS, asprs_table
from pipeline.report.model import (
    REPORT_HTML,
    REPORT_JSON,
    camera_estimate_text,
    precision_plateau,
)
from pipeline.report.stage import make_report
from pipeline.run.budget import MIN_WINDOW_CAP
from pipeline.run.runner import Method, run_flight
from pipeline.run.store import read_eop_csv, read_run
from seqat.departures import DEFAULT_MAX_WINDOW_IMAGES
from seqat.geometry import depth, project

#: Check point residuals are recovered exactly (pixels projected from the adjusted EOPs).
CHECKPOINT_M = 1e-6
#: Check point offsets of the hand-computed case: RMSE x 3 cm, y 4 cm (H 5 cm), z 10 cm.
OFFSETS_M = np.array([[0.03, 0.04, 0.10], [-0.03, -0.04, -0.10]])


def test_asprs_table_on_known_residuals() -> None:
    d = np.tile(OFFSETS_M, (2, 1))  # 4 points
    table = asprs_table(d)
    assert table.count == 4
    assert table.rmse_x_m == pytest.approx(0.03)
    assert table.rmse_y_m == pytest.approx(0.04)
    assert table.rmse_h_m == pytest.approx(0.05)  # sqrt(3^2 + 4^2) cm
    assert table.rmse_v_m == pytest.approx(0.10)
    assert table.horizontal_class_cm == 5.0 and table.vertical_class_cm == 10.0
    assert table.warning is not None and "30" in table.warning
    many = asprs_table(np.tile(OFFSETS_M * 1.1, (ASPRS_MIN_CHECKPOINTS // 2, 1)))
    assert many.warning is None
    assert many.horizontal_class_cm == 7.5  # 5.5 cm
    assert asprs_table(np.zeros((0, 3))).horizontal_class_cm is None


def test_precision_plateau() -> None:
    g = np.array([np.nan, 5.0, 2.0, 1.2, 1.08, 1.02, 1.0, 1.01, 0.99, 1.0, 1.0, 1.0])
    # final level 1.0; 1.08 (index 4) is the last value above 1.05: the plateau starts at 5.
    assert precision_plateau(g) == 5
    assert precision_plateau(np.full(5, np.nan)) is None


def _add_checkpoints(flight: Path, out: Path) -> int:
    """Check points whose pixels are exact projections at the run's EOPs, known coordinates
    moved by OFFSETS_M: the residuals are exactly OFFSETS_M (alternating)."""
    run = read_run(out)
    truth = read_truth(flight)
    assert truth is not None
    eops = read_eop_csv(out / "eop.csv")
    cam = run.camera
    pinhole = pinhole_camera(cam)
    rows, obs = ["point,x_m,y_m,z_m\n"], ["image,point,x_px,y_px\n"]
    n = 0
    for j in range(0, len(truth.points), max(1, len(truth.points) // 6)):
        X = truth.points.xyz_m[j] + np.array([0.0, 0.0, 0.5])
        uv = project(eops.eop, np.repeat(X[None], len(eops), 0), pinhole)
        inside = ((uv[:, 0] > 0) & (uv[:, 0] < cam.width_px - 1) & (uv[:, 1] > 0)
                  & (uv[:, 1] < cam.height_px - 1)
                  & (depth(eops.eop, np.repeat(X[None], len(eops), 0)) > 0))
        if np.count_nonzero(inside) < 2:
            continue
        known = X - OFFSETS_M[n % 2]
        rows.append(f"cp{n},{float(known[0])!r},{float(known[1])!r},{float(known[2])!r}\n")
        for i in np.flatnonzero(inside):
            obs.append(f"{eops.image_ids[i]},cp{n},{float(uv[i, 0])!r},{float(uv[i, 1])!r}\n")
        n += 1
    (flight / CHECKPOINTS_FILE).write_text("".join(rows))
    (flight / CHECKPOINT_OBS_FILE).write_text("".join(obs))
    return n


@pytest.fixture(scope="module")
def sim_flight(small_sim_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("report") / "flight"
    shutil.copytree(small_sim_dir, folder)
    return folder


def test_report_json_values_against_truth_and_checkpoints(sim_flight: Path,
                                                          tmp_path: Path) -> None:
    out = tmp_path / "sim"
    run_flight(sim_flight, out, method=Method.SIM, final_only=True, progress=False)
    n_cp = _add_checkpoints(sim_flight, out)
    assert n_cp >= 4
    try:
        make_report(out)
    finally:
        (sim_flight / CHECKPOINTS_FILE).unlink()
        (sim_flight / CHECKPOINT_OBS_FILE).unlink()
    doc = json.loads((out / REPORT_JSON).read_text())
    run_doc = json.loads((out / "run.json").read_text())
    acc = doc["accuracy"]
    assert set(acc) == {"direct", "sim"}  # no reference yet
    for method in acc.values():
        assert {"pos_rmse_m", "att_rmse_deg", "gp_rmse_m"} <= set(method)
    # Sim against truth: the same numbers run.json holds.
    np.testing.assert_allclose(acc["sim"]["pos_rmse_m"], run_doc["totals"]["accuracy"]
                               ["pos_rmse_m"], rtol=1e-12)
    np.testing.assert_allclose(acc["sim"]["gp_rmse_m"], run_doc["totals"]["accuracy"]
                               ["gp_rmse_m"], rtol=1e-12)
    # Direct georeferencing: the nav against truth, by hand.
    truth = read_truth(sim_flight)
    nav = read_run(out).nav
    assert truth is not None
    d = nav.eop - truth.eop.eop
    np.testing.assert_allclose(acc["direct"]["pos_rmse_m"], np.sqrt(np.mean(d[:, :3] ** 2, 0)),
                               rtol=1e-12)
    np.testing.assert_allclose(acc["direct"]["att_rmse_deg"],
                               np.degrees(np.sqrt(np.mean(d[:, 3:] ** 2, 0))), rtol=1e-9)
    assert acc["direct"]["pos_rmse_h_m"] == pytest.approx(
        np.hypot(*acc["direct"]["pos_rmse_m"][:2]))
    # Check points of the run: residuals are the offsets.
    cp = doc["checkpoints"]
    assert cp["method"] == "sim" and cp["count"] == n_cp
    assert cp["rmse_x_m"] == pytest.approx(0.03, abs=CHECKPOINT_M)
    assert cp["rmse_y_m"] == pytest.approx(0.04, abs=CHECKPOINT_M)
    assert cp["rmse_h_m"] == pytest.approx(0.05, abs=CHECKPOINT_M)
    assert cp["rmse_v_m"] == pytest.approx(0.10, abs=CHECKPOINT_M)
    # Mean and sigma per axis of the same residuals; the table sorted largest first.
    res = next(c for c in doc["checkpoint_reports"] if c["method"] == "sim")["residuals"]
    d = np.array([[r["dx_m"], r["dy_m"], r["dz_m"]] for r in res])
    for k, axis in enumerate("xyz"):
        assert cp[f"mean_{axis}_m"] == pytest.approx(d[:, k].mean(), abs=1e-12)
        assert cp[f"std_{axis}_m"] == pytest.approx(d[:, k].std(ddof=1), abs=1e-12)
    lengths = np.linalg.norm(d, axis=1)
    assert np.all(np.diff(lengths) <= 1e-12)
    # Title, verdict and warnings; the PDF has its pages (verdict, map, 2 tables).
    assert doc["title"]["flight_name"] == "flight" and doc["title"]["method"] == "sim"
    assert doc["verdict"][0].startswith(f"{n_cp} check points")
    assert any(w["stage"] == "report" and "no COLMAP reference" in w["message"]
               for w in doc["warnings"])
    pdf = (out / "report.pdf").read_bytes()
    assert pdf.startswith(b"%PDF") and len(re.findall(rb"/Type\s*/Page\b(?!s)", pdf)) >= 4
    # Real-time block and the HTML: self-contained, figures inline.
    assert doc["realtime"][0]["method"] == "sim"
    page = (out / REPORT_HTML).read_text()
    assert page.count("data:image/png;base64,") >= 4  # map, residuals, errors, internals
    assert page.index("Verdict") < page.index("Warnings") < page.index("<h2>Map")
    assert page.index("<h2>Map") < page.index("Check points (ASPRS") < page.index("Appendix")
    assert page.index("Appendix") < page.index("Real-time behaviour")
    assert 'src="http' not in page and "fewer" not in page
    assert "ASPRS (2023) asks for at least 30" in page


def test_report_without_truth_is_against_the_reference(sim_flight: Path,
                                                       tmp_path: Path) -> None:
    flight = tmp_path / "flight"
    shutil.copytree(sim_flight, flight)
    shutil.rmtree(flight / "truth")
    out = tmp_path / "sim"
    run_flight(flight, out, method=Method.SIM, final_only=True, progress=False)
    run_reference(out)
    doc = make_report(out).report
    assert doc.accuracy_against == "reference"
    assert "colmap" not in doc.accuracy and "colmap" in doc.methods
    # Sim and the COLMAP reference: the same model and the same loss core (the run's robust
    # loss; COLMAP's Huber tail differs beyond 3 sigma: docs/algorithm.md, *Robust loss*)
    assert doc.accuracy["sim"].pos_rmse_3d_m < 1e-2
    assert doc.accuracy["direct"].pos_rmse_3d_m > 0.1
    assert doc.checkpoints is None
    assert any("no check points" in n for n in doc.notes)
    page = (out / REPORT_HTML).read_text()
    assert "<h2>Agreement with the COLMAP reference</h2>" in page
    assert "Accuracy against" not in page and "No check points" in page


def test_cli_report_bad_input_is_exit_2(tmp_path: Path, small_sim_dir: Path) -> None:
    result = CliRunner().invoke(app, ["report", str(tmp_path / "absent")])
    assert result.exit_code == 2
    assert result.stderr.startswith("seqat: error: ") and result.stderr.count("\n") == 1
    # A --compare run of another flight.
    a, b = tmp_path / "a", tmp_path / "b"
    run_flight(small_sim_dir, a, method=Method.SIM, final_only=True, progress=False)
    other = tmp_path / "other"
    shutil.copytree(small_sim_dir, other)
    nav = (other / "nav.csv").read_text().replace("img_", "im_")
    (other / "nav.csv").write_text(nav)
    obs = (other / "observations.csv").read_text().replace("img_", "im_")
    (other / "observations.csv").write_text(obs)
    shutil.rmtree(other / "truth")
    run_flight(other, b, method=Method.SIM, final_only=True, progress=False)
    result = CliRunner().invoke(app, ["report", str(a), "--compare", str(b)])
    assert result.exit_code == 2
    assert "not of the same flight" in result.stderr and result.stderr.count("\n") == 1
    assert not (a / REPORT_JSON).exists()


def test_report_shows_the_latency_budget_changes(small_sim_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    run_flight(small_sim_dir, out, progress=False, budget_ms=1e-6)  # every image is over
    make_report(out)
    live = json.loads((out / "report.json").read_text())["live"]
    assert live["mode"] == "run" and live["budget_ms"] == 1e-6
    assert live["images_over_budget"] == 24 and live["final_threshold"] == 0.8
    changes = [(c["image"], c["old_threshold"], c["new_threshold"])
               for c in live["threshold_changes"]]
    assert changes[:3] == [("img_0011", 0.1, 0.2), ("img_0012", 0.2, 0.4),
                           ("img_0013", 0.4, 0.8)]
    # then, the threshold at its cap, the window is capped: 0.75 x the window, down to 4
    caps = [c["new_window_cap"] for c in live["threshold_changes"][3:]]
    assert caps and caps == sorted(caps, reverse=True) and caps[-1] == MIN_WINDOW_CAP
    assert all(c["new_threshold"] == 0.8 for c in live["threshold_changes"][3:])
    html_text = (out / "report.html").read_text()
    assert "<h3>Live operation</h3>" in html_text and "0.1 → 0.2" in html_text
    # from the configured cap (the default, the budget's base) down
    assert f"{DEFAULT_MAX_WINDOW_IMAGES} → {caps[0]}" in html_text
def test_latency_table_adds_the_live_ortho_to_the_end_to_end_time() -> None:
    from pipeline.run.latency import latency_table

    tracking = {"read_ms": 2.0, "detect_ms": 50.0, "match_ms": 30.0, "total_ms": 90.0}
    record = {"images": [{"image_id": f"i{k}", "update_ms": 10.0 + k, "tracking": tracking}
                         for k in range(3)]}
    ortho = {"live": {}, "images": [
        {"image": f"i{k}", "queue_ms": 1.0, "read_ms": 3.0, "compute_ms": 20.0, "write_ms": 0.0,
         "mosaic_ms": 5.0, "latency_ms": 30.0 + k, "reortho_ms": None} for k in range(2)]}
    table = latency_table(record, ortho)
    stages = {s.stage: s for s in table.stages}
    assert table.ortho == "live" and "ortho again at the end (not live)" not in stages
    assert stages["AT update"].median_ms == 11.0 and stages["AT update"].images == 3
    assert stages["ortho: AT update -> mosaic"].images == 2  # i2 was not orthorectified
    end = stages["end to end"]
    assert end.images == 2 and end.max_ms == 2.0 + 90.0 + 11.0 + 31.0
    post = latency_table(record, {"images": ortho["images"]})
    names = [s.stage for s in post.stages]
    assert post.ortho == "after the run" and "ortho: AT update -> mosaic" not in names
    assert {s.stage: s for s in post.stages}["end to end"].max_ms == 2.0 + 90.0 + 12.0
    assert latency_table(record, None).ortho == "none"
    assert not any(s.stage.startswith("second start") for s in table.stages)


def test_latency_table_lists_second_starts_beside_the_update() -> None:
    """A second start runs once the image's estimate is out: listed, not end to end."""
    from pipeline.run.latency import latency_table

    record = {"images": [{"image_id": f"i{k}", "update_ms": 10.0,
                          "second_start_ms": 500.0 if k == 1 else None} for k in range(3)]}
    stages = {s.stage: s for s in latency_table(record, None).stages}
    trial = stages["second start (after the AT update)"]
    assert trial.images == 1 and trial.max_ms == 500.0
    assert stages["end to end"].max_ms == 10.0


def test_check_points_without_observations_make_a_report(sim_flight: Path,
                                                         tmp_path: Path) -> None:
    """Found by seqat bench fuzz: a checkpoint_obs.csv with its header only was an
    IndexError (exit 1)."""
    out = tmp_path / "sim"
    run_flight(sim_flight, out, method=Method.SIM, final_only=True, progress=False)
    _add_checkpoints(sim_flight, out)
    obs = sim_flight / CHECKPOINT_OBS_FILE
    obs.write_text(obs.read_text().splitlines()[0] + "\n")
    try:
        make_report(out)
    finally:
        (sim_flight / CHECKPOINTS_FILE).unlink()
        obs.unlink()
    doc = json.loads((out / REPORT_JSON).read_text())
    assert doc["checkpoints"]["count"] == 0


def test_check_point_pixel_outside_the_image_is_an_error(sim_flight: Path,
                                                         tmp_path: Path) -> None:
    """A check point observed outside its image cannot have been measured there: exit-2
    error naming the point and the image (it used to be intersected as if it were)."""
    from seqat.errors import InputDataError

    out = tmp_path / "sim"
    run_flight(sim_flight, out, method=Method.SIM, final_only=True, progress=False)
    _add_checkpoints(sim_flight, out)
    obs = sim_flight / CHECKPOINT_OBS_FILE
    lines = obs.read_text().splitlines()
    image, point, _, y = lines[1].split(",")
    lines[1] = f"{image},{point},-40.0,{y}"
    obs.write_text("\n".join(lines) + "\n")
    try:
        with pytest.raises(InputDataError, match=rf"check point '{point}' in image "
                                                 rf"'{image}': pixel \(-40, .* lies outside"):
            make_report(out)
    finally:
        (sim_flight / CHECKPOINTS_FILE).unlink()
        obs.unlink()


def test_camera_estimate_text_names_what_was_estimated_and_what_held() -> None:
    """The report's camera line: the estimated parameters with sigma and prior, those held;
    every parameter held reads as such (it read "self-calibrated: ; held ...")."""
    from types import SimpleNamespace

    def text(free: list[str], held: list[str]) -> str:
        names = free + held
        est = {"free": free, "held": held, "values": dict.fromkeys(names, 1000.0),
               "sigma": dict.fromkeys(names, 2.0), "prior": dict.fromkeys(names, 999.0)}
        return camera_estimate_text(SimpleNamespace(record={"camera_estimate": est}))  # type: ignore[arg-type]

    assert text(["f_px"], ["k1"]) == ("self-calibrated: f_px 1000 ± 2 (prior 999); held at "
                                      "the prior (not determined, or not significant): k1")
    assert text(["f_px"], []) == "self-calibrated: f_px 1000 ± 2 (prior 999)"
    assert text([], ["f_px", "k1"]) == ("self-calibration: every parameter held at the prior "
                                        "(not determined, or not significant): f_px, k1")
    assert camera_estimate_text(SimpleNamespace(record={})) == ""  # type: ignore[arg-type]
