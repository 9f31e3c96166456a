"""``seqat watch`` and ``seqat feed``: a growing flight folder adjusted as a batch run would.

Flights are fed by :func:`pipeline.run.feed.feed_flight` in a thread (fast, the partial-file
convention) while :func:`pipeline.run.watch.watch_flight` runs; the published results must equal
``seqat run``'s bit for bit. Completeness rules are tested on their own with explicit clocks.
"""

from __future__ import annotations

import io
import json
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from pipeline.common.columns import FLIGHT_YAML, NAV_GEODETIC_COLUMNS
from pipeline.common.csvio import CsvTail
from pipeline.flight.schema import load_flight_config
from pipeline.run.feed import feed_flight
from pipeline.run.session import ImageLive
from pipeline.run.watch import Arrival, GrowingFlight, ImageWatcher, WatchOptions, watch_flight
from seqat.errors import InputDataError
from seqat.types import ImageUpdate

from ..sample_runs import AUTZEN, MINI, STRIP, assert_same_results, resize_images

#: Feeding rate of the tests (images per second): faster than real time.
FAST_RATE_HZ = 100.0
#: Watch options of the tests: short polls, stop one second after the last input.
QUICK = WatchOptions(idle_timeout_s=1.0, poll_s=0.01, wait_timeout_s=5.0)
#: The budget of the tests that compare a watch with a run: none. Equal results are a
#: property of the watch without a budget; keep-up (the default) follows the timing of the
#: arrivals, and the feeder thread shares the GIL with the watch: on a loaded machine its
#: rows can arrive at the watch's own pace, over the keep-up's batch limit.
NO_BUDGET = None
#: Images of seneca_mini kept where its first ones tell what a test checks.
WATCHED_MINI_IMAGES = 8
#: A moment long after any wait timeout of QUICK (monotonic seconds).
LATER_S = 100.0


def _feed_in_background(src: Path, dst: Path, rate_hz: float = FAST_RATE_HZ) -> threading.Thread:
    """Start feeding; returns once flight.yaml is written (the watch needs it)."""
    started = threading.Event()
    thread = threading.Thread(target=feed_flight, args=(src, dst),
                              kwargs={"rate_hz": rate_hz, "delay_s": 0.3,
                                      "on_start": started.set}, daemon=True)
    thread.start()
    assert started.wait(30)
    return thread


def _quiet() -> Console:
    return Console(file=io.StringIO(), width=200)


def test_watch_of_a_fed_observations_flight_equals_the_run(strip_run: Path,
                                                           tmp_path: Path) -> None:
    flight, out = tmp_path / "flight", tmp_path / "out"
    feeder = _feed_in_background(STRIP, flight)
    console = _quiet()
    summary = watch_flight(flight, out, watch=QUICK, console=console, budget_ms=NO_BUDGET)
    feeder.join()
    assert summary.stopped == "idle" and summary.n_images == 60 and not summary.skipped
    assert_same_results(strip_run, out)
    doc = json.loads((out / "run.json").read_text())
    assert doc["mode"] == "watch"
    assert all(im["live"]["latency_ms"] > 0 for im in doc["images"])
    lines = console.file.getvalue().splitlines()  # type: ignore[attr-defined]
    assert len([line for line in lines if line.startswith("img_")]) == 60
    assert "latency" in lines[0] and "window" in lines[0] and "σ0" in lines[0]


def test_watch_of_a_fed_image_flight_equals_the_run(autzen_run: Path, tmp_path: Path) -> None:
    flight, out = tmp_path / "flight", tmp_path / "out"
    feeder = _feed_in_background(AUTZEN, flight)
    summary = watch_flight(flight, out, watch=QUICK, console=_quiet(), budget_ms=NO_BUDGET)
    feeder.join()
    assert summary.n_images == 12 and summary.latency_ms is not None
    assert_same_results(autzen_run, out)


def test_a_stopped_watch_publishes_and_resumes(strip_run: Path, tmp_path: Path) -> None:
    flight, out = tmp_path / "flight", tmp_path / "out"
    feeder = _feed_in_background(STRIP, flight)
    stop = threading.Event()

    def stop_after_20(live: ImageLive, update: ImageUpdate) -> None:
        if update.index == 19:
            stop.set()  # as Ctrl-C: the image in flight finishes, the results are published

    first = watch_flight(flight, out, watch=QUICK, console=_quiet(), budget_ms=NO_BUDGET,
                         stop=stop, on_image=stop_after_20)
    feeder.join()
    assert first.stopped == "interrupted" and first.n_images == 20
    assert len((out / "eop.csv").read_text().splitlines()) == 21
    second = watch_flight(flight, out, watch=QUICK, console=_quiet(), budget_ms=NO_BUDGET,
                          resume=True)
    assert second.replayed == 20 and second.n_images == 60
    assert_same_results(strip_run, out)


def test_feed_writes_the_partial_file_convention(tmp_path: Path) -> None:
    seen: list[tuple[str, list[str]]] = []
    dst = tmp_path / "flight"

    def look(image: str) -> None:
        seen.append((image, sorted(p.name for p in (dst / "images").iterdir())))

    feed_flight(AUTZEN, dst, rate_hz=FAST_RATE_HZ, limit=3, on_image=look)
    assert [s[0] for s in seen] == ["img_0001", "img_0002", "img_0003"]
    assert seen[2][1] == ["img_0001.jpg", "img_0002.jpg", "img_0003.jpg"]  # no .part left
    nav = (dst / "nav.csv").read_text().splitlines()
    assert nav == (AUTZEN / "nav.csv").read_text().splitlines()[:4]
    assert (dst / FLIGHT_YAML).read_text() == (AUTZEN / FLIGHT_YAML).read_text()
    assert (dst / "truth" / "eop.csv").is_file()
    assert (dst / "lidar" / "surface.laz").is_file()  # lidar: is there before the flight


def test_partial_and_truncated_images_wait(tmp_path: Path) -> None:
    data = (AUTZEN / "images" / "img_0001.jpg").read_bytes()
    (tmp_path / "a.jpg.part").write_bytes(data)
    (tmp_path / ".b.jpg").write_bytes(data)
    (tmp_path / "c.jpg").write_bytes(data[: len(data) // 2])
    watcher = ImageWatcher(tmp_path, set(), wait_timeout_s=5.0)
    assert watcher.poll(0.0) == ([], [])
    (tmp_path / "a.jpg.part").rename(tmp_path / "a.jpg")
    with (tmp_path / "c.jpg").open("ab") as handle:
        handle.write(data[len(data) // 2:])
    ready, skipped = watcher.poll(1.0)
    assert [r[0] for r in ready] == ["a", "c"] and not skipped
    (tmp_path / "d.jpg").write_bytes(data[:1000])  # truncated for good
    assert watcher.poll(2.0) == ([], [])
    ready, skipped = watcher.poll(2.0 + LATER_S)
    assert not ready and [s.image for s in skipped] == ["d"]
    assert "truncated JPEG" in skipped[0].reason and "after 5 s" in skipped[0].reason


def test_csv_lines_count_once_they_end_with_a_newline(tmp_path: Path) -> None:
    path = tmp_path / "nav.csv"
    tail = CsvTail(path, NAV_GEODETIC_COLUMNS)
    assert tail.poll() == []  # not there yet
    header = ",".join(NAV_GEODETIC_COLUMNS) + "\n"
    path.write_text(header + "img_1,0.0,44.0,-123.0,100")
    assert tail.poll() == []
    with path.open("a") as handle:
        handle.write(",0,0,90\nimg_2,1.0")
    rows = tail.poll()
    assert [(r.line, r.values["image"], r.values["yaw_deg"]) for r in rows] == [(2, "img_1", "90")]
    path.write_text(header)
    with pytest.raises(InputDataError, match="shrank"):
        tail.poll()


def _image_flight(tmp_path: Path, nav_images: list[str], files: list[str]) -> Path:
    """Autzen's flight.yaml with the given nav rows and image files."""
    folder = tmp_path / "flight"
    (folder / "images").mkdir(parents=True)
    shutil.copy(AUTZEN / FLIGHT_YAML, folder / FLIGHT_YAML)
    rows = {line.split(",")[0]: line for line in
            (AUTZEN / "nav.csv").read_text().splitlines(keepends=True)}
    (folder / "nav.csv").write_text(rows["image"] + "".join(rows[i] for i in nav_images))
    for name in files:
        shutil.copy(AUTZEN / "images" / f"{name}.jpg", folder / "images")
    return folder


def test_images_wait_for_their_nav_rows_and_rows_for_their_images(tmp_path: Path) -> None:
    folder = _image_flight(tmp_path, ["img_0001", "img_0002", "img_0003"],
                           ["img_0001", "img_0003", "img_0004"])
    grow = GrowingFlight(folder, load_flight_config(folder / FLIGHT_YAML), set(), 5.0)
    items, activity = grow.poll(0.0)
    assert activity and [i.image for i in items] == ["img_0001"]  # img_0003 waits for img_0002
    assert isinstance(items[0], Arrival) and grow.flight is not None
    items, _ = grow.poll(1.0)
    assert items == []
    items, _ = grow.poll(LATER_S)
    assert [(type(i).__name__, i.image) for i in items] == [
        ("SkippedImage", "img_0002"), ("Arrival", "img_0003"), ("SkippedImage", "img_0004")]
    assert "listed in nav.csv but no complete image" in items[0].reason  # type: ignore[union-attr]
    assert "img_0004.jpg: no row in nav.csv after 5 s" == items[2].reason  # type: ignore[union-attr]


def test_observation_rows_after_their_nav_row_are_an_error(tmp_path: Path) -> None:
    folder = tmp_path / "flight"
    folder.mkdir()
    shutil.copy(STRIP / FLIGHT_YAML, folder / FLIGHT_YAML)
    nav = (STRIP / "nav.csv").read_text().splitlines(keepends=True)
    obs = (STRIP / "observations.csv").read_text().splitlines(keepends=True)
    first = [line for line in obs[1:] if line.startswith("img_0001,")]
    (folder / "nav.csv").write_text("".join(nav[:2]))
    (folder / "observations.csv").write_text(obs[0] + "".join(first[:-1]))
    grow = GrowingFlight(folder, load_flight_config(folder / FLIGHT_YAML), set(), 5.0)
    items, _ = grow.poll(0.0)
    assert isinstance(items[0], Arrival) and len(items[0].point_ids) == len(first) - 1
    np.testing.assert_array_equal(items[0].nav_eop[:3], [float(v) for v in
                                                         nav[1].split(",")[2:5]])
    with (folder / "observations.csv").open("a") as handle:
        handle.write(first[-1])
    with pytest.raises(InputDataError, match=r"observations.csv:\d+: rows of image 'img_0001' "
                       "are not contiguous or arrive after its nav row"):
        grow.poll(1.0)


def test_watch_without_flight_yaml_is_exit_2(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    result = CliRunner().invoke(app, ["watch", str(tmp_path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert result.stderr == (f"seqat: error: {tmp_path / FLIGHT_YAML}: no such file (seqat "
                             "watch needs flight.yaml from the start)\n")


def _late_observations_flight(autzen_run: Path, tmp_path: Path) -> Path:
    """The rendered flight as an observations flight: the tracked run's observations.csv,
    whose ``frame`` column carries late observations of earlier images."""
    flight = tmp_path / "late_flight"
    flight.mkdir()
    yaml = [line for line in (AUTZEN / FLIGHT_YAML).read_text().splitlines()
            if not line.startswith(("images:", "lidar:", "checkpoints:"))]
    (flight / FLIGHT_YAML).write_text("\n".join([*yaml, "observations: observations.csv"]) + "\n")
    shutil.copy(AUTZEN / "nav.csv", flight / "nav.csv")
    shutil.copy(autzen_run / "observations.csv", flight / "observations.csv")
    return flight


def test_watch_of_a_fed_flight_with_late_observations_equals_the_run(autzen_run: Path,
                                                                     tmp_path: Path) -> None:
    """seqat feed copies each frame's rows, its late ones included, before its nav row;
    seqat watch reads the frame column as seqat run does: the same results."""
    from pipeline.run.runner import run_flight

    flight = _late_observations_flight(autzen_run, tmp_path)
    ref = tmp_path / "run"
    run_flight(flight, ref, progress=False)
    late = json.loads((ref / "run.json").read_text())["totals"]["late"]["observations"]
    assert late > 0
    fed, out = tmp_path / "fed", tmp_path / "out"
    feeder = _feed_in_background(flight, fed)
    summary = watch_flight(fed, out, watch=QUICK, console=_quiet(), budget_ms=NO_BUDGET)
    feeder.join()
    assert summary.n_images == 12 and not summary.skipped
    assert (fed / "observations.csv").read_bytes() == (flight / "observations.csv").read_bytes()
    assert json.loads((out / "run.json").read_text())["totals"]["late"]["observations"] == late
    assert_same_results(ref, out)


@pytest.mark.parametrize("frame_nav_in", [False, True])
def test_a_late_row_before_its_image_nav_row_is_an_error(autzen_run: Path, tmp_path: Path,
                                                          frame_nav_in: bool) -> None:
    """A late row of img_0003 in frame img_0002 (not acquired yet). Without the frame's nav
    row the row waits for the next reading of nav.csv (a writer may be between the reads);
    with it (a file written at once) the error comes before the frame can arrive."""
    flight = _late_observations_flight(autzen_run, tmp_path)
    nav = (flight / "nav.csv").read_text().splitlines(keepends=True)
    obs = (flight / "observations.csv").read_text().splitlines(keepends=True)
    first = [line for line in obs[1:] if line.endswith(",img_0001\n")]
    late = "img_0003,t9999999,100.0,100.0,img_0002\n"
    (flight / "nav.csv").write_text("".join(nav[:3 if frame_nav_in else 2]))
    (flight / "observations.csv").write_text(obs[0] + "".join(first) + late)
    grow = GrowingFlight(flight, load_flight_config(flight / FLIGHT_YAML), set(), 5.0)
    if not frame_nav_in:
        assert grow.poll(0.0)[0][0].image == "img_0001"  # type: ignore[union-attr]
    with pytest.raises(InputDataError, match=r"^[^\n]*observations.csv:\d+: field 'image': "
                       r"late observation of image 'img_0003' in frame 'img_0002'[^\n]*$"):
        grow.poll(1.0)


def test_rows_written_between_the_two_files_reads_are_taken_in_order(
        autzen_run: Path, tmp_path: Path) -> None:
    """A fast feeder writes the next frames (rows, then nav row, each) while the watch is
    between reading nav.csv and observations.csv: a late row of img_0002 in frame img_0003
    is checked against the nav rows read after it (img_0002's was written first), and each
    frame still arrives with its rows. Checked at once, it failed here on a loaded machine
    (CI, 2026-12-03)."""
    flight = _late_observations_flight(autzen_run, tmp_path)
    nav = (flight / "nav.csv").read_text().splitlines(keepends=True)
    obs = (flight / "observations.csv").read_text().splitlines(keepends=True)

    def frame(name: str) -> list[str]:
        return [line for line in obs[1:] if line.endswith(f",{name}\n")]

    (flight / "nav.csv").write_text("".join(nav[:2]))
    (flight / "observations.csv").write_text(obs[0] + "".join(frame("img_0001")))
    grow = GrowingFlight(flight, load_flight_config(flight / FLIGHT_YAML), set(), 5.0)
    tail = grow._nav
    assert tail is not None
    read = tail.poll
    fed: list[bool] = []

    def read_then_feed() -> object:
        rows = read()
        if not fed:  # the feeder, right after this read: frame 2, nav 2, frame 3, nav 3
            fed.append(True)
            late = "img_0002,t9999998,100.0,100.0,img_0003\n"
            with (flight / "observations.csv").open("a") as f:
                f.write("".join(frame("img_0002")))
            with (flight / "nav.csv").open("a") as f:
                f.write(nav[2])
            with (flight / "observations.csv").open("a") as f:
                f.write("".join(frame("img_0003")) + late)
            with (flight / "nav.csv").open("a") as f:
                f.write(nav[3])
        return rows

    tail.poll = read_then_feed  # type: ignore[method-assign]
    arrived = [a for t in (0.0, 1.0, 2.0) for a in grow.poll(t)[0] if isinstance(a, Arrival)]
    assert [a.image for a in arrived] == ["img_0001", "img_0002", "img_0003"]
    assert all(len(a.point_ids) > 0 for a in arrived)  # each frame with its rows
    assert "img_0002" in arrived[2].late_image_ids


def test_rows_appended_during_a_backlog_keep_their_own_ready_times(
        autzen_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Images 1-4 are there at the start; while the watch works through them, image 5 is
    appended after image 1 is adjusted, 6 after 2, 7 after 3. Each is read right after the
    image during which it arrived, so its ready time is nav.csv's mtime just after its own
    append, not after the last one: the latency the watch reports (and the keep-up budget's
    backlog test reads) is not understated in a backlog. Read once per backlog, 5-7 all got
    the time of the last append (docs/benchmarks.md, *An Intel host*)."""
    import time

    import pipeline.run.watch as watch_module

    flight = _late_observations_flight(autzen_run, tmp_path)
    nav = (flight / "nav.csv").read_text().splitlines(keepends=True)
    obs = (flight / "observations.csv").read_text().splitlines(keepends=True)

    def append(k: int) -> float:  # as the feeder writes: the frame's rows, then its nav row
        with (flight / "observations.csv").open("a") as f:
            f.write("".join(line for line in obs[1:] if line.endswith(f",img_{k:04d}\n")))
        with (flight / "nav.csv").open("a") as f:
            f.write(nav[k])
        return (flight / "nav.csv").stat().st_mtime

    (flight / "nav.csv").write_text(nav[0])
    (flight / "observations.csv").write_text(obs[0])
    for k in range(1, 5):
        append(k)
    appended: dict[str, float] = {}
    ready: dict[str, float] = {}
    prepare = watch_module._prepare

    def record(source: object, item: Arrival, grow: GrowingFlight) -> object:
        ready[item.image] = item.ready_s
        return prepare(source, item, grow)  # type: ignore[arg-type]

    def feed(live: ImageLive, update: ImageUpdate) -> None:
        k = update.index + 5  # image 1 adjusted: append image 5, ...
        if k <= 7:
            time.sleep(0.02)  # a distinct mtime per append
            appended[f"img_{k:04d}"] = append(k)
        elif k == 8:
            for j in range(8, len(nav)):
                append(j)

    monkeypatch.setattr(watch_module, "_prepare", record)
    summary = watch_flight(flight, tmp_path / "out", watch=QUICK, console=_quiet(),
                           budget_ms=NO_BUDGET, on_image=feed)
    assert summary.n_images == 12 and not summary.skipped
    assert len(appended) == 3
    assert {image: ready[image] for image in appended} == appended


def test_feed_of_a_bad_frame_field_is_exit_2(autzen_run: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    flight = _late_observations_flight(autzen_run, tmp_path)
    path = flight / "observations.csv"
    lines = path.read_text().splitlines(keepends=True)
    k = next(k for k, line in enumerate(lines) if line.endswith(",img_0002\n")
             and line.startswith("img_0001,"))
    lines[k] = lines[k].replace(",img_0002\n", ",img 0002\n")
    path.write_text("".join(lines))
    result = CliRunner().invoke(app, ["feed", str(flight), "--out", str(tmp_path / "fed")])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert f"observations.csv:{k + 1}: field 'frame'" in result.stderr


def test_a_resumed_watch_takes_late_observations_of_journaled_images(autzen_run: Path,
                                                                      tmp_path: Path) -> None:
    """Stopped after img_0004: the late rows that img_0006 and img_0007 carry of images 2-4
    (journaled by the first watch) are taken by the resumed one."""
    from pipeline.run.runner import run_flight

    flight = _late_observations_flight(autzen_run, tmp_path)
    ref = tmp_path / "run"
    run_flight(flight, ref, progress=False)
    fed, out = tmp_path / "fed", tmp_path / "out"
    feeder = _feed_in_background(flight, fed)
    stop = threading.Event()

    def stop_after_4(live: ImageLive, update: ImageUpdate) -> None:
        if update.index == 3:
            stop.set()

    first = watch_flight(fed, out, watch=QUICK, console=_quiet(), budget_ms=NO_BUDGET,
                         stop=stop, on_image=stop_after_4)
    feeder.join()
    assert first.n_images == 4
    second = watch_flight(fed, out, watch=QUICK, console=_quiet(), budget_ms=NO_BUDGET,
                          resume=True)
    assert second.replayed == 4 and second.n_images == 12
    assert_same_results(ref, out)


def test_watch_of_a_bad_frame_field_is_exit_2(autzen_run: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    flight = _late_observations_flight(autzen_run, tmp_path)
    nav = (flight / "nav.csv").read_text().splitlines(keepends=True)
    obs = (flight / "observations.csv").read_text().splitlines(keepends=True)
    first = [line for line in obs[1:] if line.endswith(",img_0001\n")]
    (flight / "nav.csv").write_text("".join(nav[:2]))
    (flight / "observations.csv").write_text(
        obs[0] + "".join(first) + "img_0001,t9999999,100.0,100.0,img 0002\n")
    result = CliRunner().invoke(app, ["watch", str(flight), "--out", str(tmp_path / "o"),
                                      "--idle-timeout-s", "1"])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert f"observations.csv:{len(first) + 2}: field 'frame'" in result.stderr


class _SlowListener:
    """A listener that takes ``seconds`` per sequential image (a slow machine)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def on_image(self, frame: object, update: ImageUpdate, estimator: object) -> None:
        if update.stage == "sequential":
            threading.Event().wait(self.seconds)

    def on_finish(self, solution: object) -> None:
        pass


def test_a_watch_that_falls_behind_tightens_the_window_to_keep_up(tmp_path: Path) -> None:
    """Keep-up (the default budget): images every 125 ms, each sequential image takes
    longer; the backlog tightens the threshold, named in run.json as keep-up events."""
    flight, out = tmp_path / "flight", tmp_path / "out"
    feeder = _feed_in_background(STRIP, flight, rate_hz=8.0)
    watch_flight(flight, out, watch=QUICK, console=_quiet(), listeners=[_SlowListener(0.2)])
    feeder.join()
    doc = json.loads((out / "run.json").read_text())
    budget = doc["latency_budget"]
    assert budget["mode"] == "keep-up" and 90.0 < budget["budget_ms"] < 250.0
    assert budget["base_features"] is None  # an observations flight: no tracker
    assert budget["events"] and budget["events"][0]["reason"] in ("over budget", "backlog")
    thresholds = [im["live"]["threshold"] for im in doc["images"]]
    assert max(thresholds) > thresholds[0] == 0.1
    assert budget["final_threshold"] == thresholds[-1] or budget["events"][-1]["image"] == \
        doc["images"][-1]["image_id"]


@pytest.mark.parametrize("budget", [None, "off", "400"])
def test_watch_cli_summary_names_the_budget(tmp_path: Path, budget: str | None) -> None:
    """A folder written before the watch is a batch: keep-up has no rate and changes nothing;
    ``off`` has no budget; a fixed one is named with its milliseconds."""
    from typer.testing import CliRunner

    from pipeline.cli import app

    flight = tmp_path / "flight"
    feed_flight(STRIP, flight, rate_hz=FAST_RATE_HZ)
    args = ["watch", str(flight), "--out", str(tmp_path / "o"), "--idle-timeout-s", "0.5",
            "--poll-s", "0.01", *([] if budget is None else ["--budget-ms", budget])]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    budget_doc = json.loads((tmp_path / "o" / "run.json").read_text())["latency_budget"]
    if budget == "off":
        assert budget_doc is None and "budget" not in result.stdout
    elif budget is None:
        assert budget_doc["mode"] == "keep-up" and budget_doc["budget_ms"] is None
        assert "budget (keep-up)" in result.stdout and "batch" in result.stdout
        assert not budget_doc["events"] and budget_doc["images_over_budget"] == 0
    else:
        assert budget_doc["mode"] == "fixed" and budget_doc["budget_ms"] == 400.0
        assert "budget (fixed)" in result.stdout and "400 ms" in result.stdout


def test_watch_names_images_of_another_size_once_per_size(tmp_path: Path) -> None:
    """Images of another size than the camera's (the first image's) are resampled as in
    ``seqat run``, and run.json names them in one warning per size, not one per image."""
    flight, out = tmp_path / "flight", tmp_path / "out"
    shutil.copytree(MINI, flight)
    (flight / FLIGHT_YAML).write_text("images: images\nnav:\n  source: images\n",
                                      encoding="utf-8")
    images = sorted((flight / "images").glob("*.jpg"))
    for path in images[WATCHED_MINI_IMAGES:]:  # the first ones are enough to tell
        path.unlink()
    resize_images(images[1:3], [(900, 675)] * 2)
    summary = watch_flight(flight, out, watch=QUICK, console=_quiet(), budget_ms=NO_BUDGET)
    assert summary.n_images == WATCHED_MINI_IMAGES
    warnings = json.loads((out / "run.json").read_text(encoding="utf-8"))["warnings"]
    assert [w for w in warnings if "resampled" in w] == [
        "2 images of 900 x 675 px (IMG_0461.jpg, IMG_0462.jpg) differ from the camera's "
        "1000 x 750 px; resampled to it (same aspect ratio)"]
