"""Late observations through the pipeline: ``observations.csv``'s ``frame`` column, replay,
the journal, ``run.json`` counts (docs/formats.md)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.common.csvio import read_csv
from pipeline.flight.folder import read_flight
from pipeline.run.journal import encode_record, read_journal
from pipeline.run.runner import Method, run_flight
from seqat.errors import InputDataError

from ..sample_runs import AUTZEN, STRIP, assert_same_results


def _rows(path: Path) -> list[dict[str, str]]:
    return [r.values for r in read_csv(path, ("image", "point", "x_px", "y_px"), ("frame",))]


def test_image_run_reports_and_writes_its_late_observations(autzen_run: Path) -> None:
    doc = json.loads((autzen_run / "run.json").read_text())
    late = doc["totals"]["late"]
    rows = _rows(autzen_run / "observations.csv")
    late_rows = [r for r in rows if r["frame"] != r["image"]]
    assert late["observations"] == len(late_rows) > 0
    assert late["images"] == len({r["image"] for r in late_rows})
    assert isinstance(late["images_tied_only_by_late"], list)
    assert doc["totals"]["observations"] == len(rows)
    assert sum(int(im["tracking"]["late"]) for im in doc["images"]) == len(late_rows)
    # the frame's rows are contiguous, its late rows first, of earlier images
    order = {iid: k for k, iid in enumerate(read_flight(AUTZEN).nav.image_ids)}
    frames = [r["frame"] for r in rows]
    assert frames == sorted(frames, key=order.__getitem__)
    assert all(order[r["image"]] < order[r["frame"]] for r in late_rows)
    # the journal holds them as the estimator received them
    contents = read_journal(autzen_run)
    assert contents is not None
    assert sum(rec.frame.n_late for rec in contents.images) == len(late_rows)


@pytest.mark.parametrize("method", ["seq-r", "sim"])
def test_replay_of_a_tracked_run_reproduces_it(autzen_run: Path, tmp_path: Path,
                                               method: str) -> None:
    """``--observations OUT/observations.csv``: the late rows arrive with the same frames,
    so a replay with the same method gives the live run's results."""
    out = tmp_path / "replay"
    run_flight(AUTZEN, out, progress=False, observations=autzen_run / "observations.csv",
               method=Method(method))
    doc = json.loads((out / "run.json").read_text())
    assert doc["totals"]["late"]["observations"] > 0
    if method == "seq-r":
        assert_same_results(autzen_run, out)
    assert (out / "observations.csv").read_bytes() == (
        autzen_run / "observations.csv").read_bytes()


def test_old_observations_file_without_frame_column_reads(tmp_path: Path) -> None:
    """A file without ``frame``: every row arrived with its own image (as before)."""
    flight = tmp_path / "strip"
    shutil.copytree(STRIP, flight)
    frames = list(read_flight(flight).frames())
    assert frames and all(fr.n_late == 0 for fr in frames)
    header = (flight / "observations.csv").read_text().splitlines()[0]
    assert "frame" not in header


def test_frame_column_checks(tmp_path: Path) -> None:
    flight = tmp_path / "strip"
    shutil.copytree(STRIP, flight)
    path = flight / "observations.csv"
    lines = path.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    images = list(dict.fromkeys(r[0] for r in rows))
    # a late row: image 0's first observation arrives with image 2
    moved = next(r for r in rows if r[0] == images[0])
    body = [",".join([*r, r[0]]) for r in rows if r is not moved]
    at = next(k for k, line in enumerate(body) if line.split(",")[0] == images[2])
    body.insert(at, ",".join([*moved, images[2]]))
    path.write_text("\n".join([lines[0] + ",frame", *body]) + "\n")
    frames = list(read_flight(flight).frames())
    assert frames[2].late_image_ids == (images[0],)
    assert frames[2].late_point_ids == (moved[1],)
    assert moved[1] not in frames[0].point_ids
    # a late row of a later image than its frame is refused
    bad = [line for line in body]
    k = next(k for k, line in enumerate(bad) if line.split(",")[0] == images[1])
    f = bad[k].split(",")
    bad[k] = ",".join([images[3], *f[1:4], images[1]])
    path.write_text("\n".join([lines[0] + ",frame", *bad]) + "\n")
    with pytest.raises(InputDataError, match="not acquired after it"):
        list(read_flight(flight).frames())


def test_resume_after_late_observations_equals_uninterrupted(autzen_run: Path,
                                                             tmp_path: Path) -> None:
    """Killed right after the first image that carried late observations (the tracker's
    late emissions must come back from the journal): resumed == uninterrupted."""
    contents = read_journal(autzen_run)
    assert contents is not None
    first = next(k for k, rec in enumerate(contents.images) if rec.frame.n_late)
    from .test_resume import _crash_and_resume

    out = tmp_path / "out"
    _crash_and_resume(AUTZEN, out, first + 2, np.random.default_rng(first))
    assert_same_results(autzen_run, out)


def test_a_version_1_journal_still_reads(autzen_run: Path, tmp_path: Path) -> None:
    """Journals of the previous layout (no late observations) are read: frames without
    late observations, the tracker state without late emissions."""
    out = tmp_path / "old"
    shutil.copytree(autzen_run, out)
    path = out / "journal" / "journal.log"
    lines = []
    for line in path.read_bytes().splitlines(keepends=True):
        doc = json.loads(line.split(b" ", 3)[3])
        if doc["kind"] == "header":
            doc["version"] = 1
        for key in ("late_images", "late_points", "late_uv_px", "late_observed_px"):
            doc.pop(key, None)
        lines.append(encode_record(doc))
    path.write_bytes(b"".join(lines))
    contents = read_journal(out)
    assert contents is not None and contents.images
    assert all(rec.frame.n_late == 0 and rec.late_observed_px.shape == (0, 2)
               for rec in contents.images)


def test_late_observations_fit_the_true_cameras(autzen_run: Path) -> None:
    """Each late ray is of its image and its point (the rendered flight's truth): every track
    intersected from the true cameras, its late rays reproject as closely as its own ones
    (docs/benchmarks.md, *Rendered check points after late observations*)."""
    from pipeline.flight.camera import PixelCorrector, pinhole_camera
    from pipeline.flight.folder import read_truth
    from seqat.geometry import intersect_rays, project

    flight = read_flight(AUTZEN)
    truth = read_truth(AUTZEN)
    assert truth is not None
    eop = dict(zip(truth.eop.image_ids, truth.eop.eop, strict=True))
    rows = _rows(autzen_run / "observations.csv")
    points = {p: k for k, p in enumerate(dict.fromkeys(r["point"] for r in rows))}
    pt = np.array([points[r["point"]] for r in rows])
    ideal = PixelCorrector(camera=flight.camera_config).ideal_pixels(
        np.array([[float(r["x_px"]), float(r["y_px"])] for r in rows]))
    E = np.array([eop[r["image"]] for r in rows])
    cam = pinhole_camera(flight.camera_config)
    X, _ = intersect_rays(E, ideal, pt, len(points), cam)
    residual = np.linalg.norm(project(E, X[pt], cam) - ideal, axis=1)
    late = np.array([r["frame"] != r["image"] for r in rows])
    assert late.sum() > 0 and np.isfinite(residual[late]).all()
    assert np.median(residual[late]) < 0.3 and residual[late].max() < 2.0
