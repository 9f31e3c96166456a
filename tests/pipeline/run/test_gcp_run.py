"""Ground control end to end on the rendered Autzen sample (exact truth): 10 of its 36 check
points as GCPs (a gcp_list.txt written from checkpoints.csv + checkpoint_obs.csv), the other
26 reported apart, with a smaller bias than the run without control (issue 14)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from pipeline.report.html import render_html
from pipeline.report.model import build_report, checkpoint_report, find_checkpoints
from pipeline.run.runner import run_flight
from pipeline.run.store import read_run

from ..sample_runs import AUTZEN

#: Every 3.5th check point by name: spread over the block.
GCP_NAMES = ("c001", "c005", "c008", "c011", "c015", "c019", "c022", "c025", "c029", "c033")


def write_gcp_list(path: Path, names: tuple[str, ...] = GCP_NAMES) -> Path:
    """An ODM gcp_list.txt of the check points ``names`` (their exact coordinates and
    observed pixels; the sample's CRS)."""
    known = {r["point"]: r for r in csv.DictReader((AUTZEN / "checkpoints.csv").open())}
    lines = ["EPSG:32610"]
    for o in csv.DictReader((AUTZEN / "checkpoint_obs.csv").open()):
        if o["point"] in names:
            k = known[o["point"]]
            lines.append(f"{k['x_m']} {k['y_m']} {k['z_m']} {o['x_px']} {o['y_px']} "
                         f"{o['image']}.jpg {o['point']}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_gcps_reported_apart_and_the_bias_falls(autzen_run: Path, tmp_path: Path) -> None:
    gcp = write_gcp_list(tmp_path / "gcp_list.txt")
    out = tmp_path / "gcp_run"
    # the session's tie points (no tracking again); the GCP observations join the frames
    run_flight(AUTZEN, out, observations=autzen_run / "observations.csv", gcp=gcp,
               progress=False)
    control = json.loads((out / "run.json").read_text())["control"]
    assert control["count"] == control["adjusted"] == 10
    assert control["rmse_h_m"] < 0.01 and control["rmse_v_m"] < 0.01
    assert (out / "control.csv").is_file()
    assert "gcp:c001" in (out / "observations.csv").read_text()

    found = find_checkpoints(AUTZEN)
    assert found is not None
    names = frozenset(GCP_NAMES)
    base_run, gcp_run = read_run(autzen_run), read_run(out)
    base = checkpoint_report("seq-r", base_run.eop, base_run, *found, exclude=names)
    with_gcp = checkpoint_report("seq-r", gcp_run.eop, gcp_run, *found, exclude=names)
    assert with_gcp.table.count == base.table.count == 26
    assert with_gcp.excluded_control == tuple(sorted(names))
    bias = np.array([with_gcp.table.mean_x_m, with_gcp.table.mean_y_m, with_gcp.table.mean_z_m])
    bias0 = np.array([base.table.mean_x_m, base.table.mean_y_m, base.table.mean_z_m])
    assert abs(bias[2]) < abs(bias0[2])
    assert np.linalg.norm(bias) < np.linalg.norm(bias0)

    report, extras = build_report(out)
    assert report.control is not None and report.control["count"] == 10
    assert report.checkpoints is not None and report.checkpoints["count"] == 26
    assert report.checkpoints["excluded_as_control"] == sorted(names)
    assert [c.method for c in report.control_reports] == ["seq-r"]
    assert len(extras["control_xyz_m"]) == 10  # type: ignore[arg-type]
    page = render_html(report, extras, thumbnails=(None, None))
    assert "<h2>Ground control points</h2>" in page and "Control residuals of seq-r" in page
    assert "Left out as ground control points of the run: c001, c005" in page
