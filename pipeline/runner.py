"""``seqat run``: stream a flight folder through an estimator and store the results.

The stage: validate the whole input first (flight.yaml, CRS, nav, one pass over
observations.csv, truth) so bad input fails before any computation and nothing is written;
then feed frames one at a time in acquisition order to the estimator (Seq-R, Seq-F or Sim),
collect the per-image :class:`~seqat.types.ImageUpdate` records and publish ``eop.csv``,
``points.csv`` and ``run.json`` together (:func:`pipeline.store.write_run_outputs`).
"""

from __future__ import annotations

import dataclasses
import enum
import time
from dataclasses import dataclass
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from pipeline.accuracy import Accuracy, compare_with_truth
from pipeline.config import build_dataclass, load_yaml
from pipeline.flight import read_flight, read_truth
from pipeline.robustness import robustness_record
from pipeline.sources import ImageSource, ObservationSource
from pipeline.store import (
    RunRecord,
    RunTotals,
    TimingStats,
    eop_table,
    point_table,
    write_run_outputs,
)
from seqat.errors import ConfigError, InputDataError
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simultaneous import SimOptions, SimultaneousAT
from seqat.types import Frame, ImageUpdate, PinholeCamera, Solution


class Method(enum.StrEnum):
    """Estimation method of ``seqat run --method``."""

    SEQ_R = "seq-r"  # sequential, window cut by EOP correlation (seed 000 Seq-R)
    SEQ_F = "seq-f"  # sequential, full: every parameter stays in the update
    SIM = "sim"  # simultaneous adjustment of everything seen so far


@dataclass(frozen=True, kw_only=True)
class EstimatorConfig:
    """Estimator options file of ``seqat run --options FILE`` (all keys optional).

    ``sequential`` is used by ``seq-r`` and ``seq-f`` (its ``sim`` section configures the
    initial simultaneous stage); ``sim`` by ``--method sim``.
    """

    sequential: SequentialOptions = SequentialOptions()
    sim: SimOptions = SimOptions()


def load_estimator_config(path: Path | str) -> EstimatorConfig:
    """Read an estimator options file (strict: unknown keys and wrong types are errors)."""
    return build_dataclass(EstimatorConfig, load_yaml(path), str(path))


def estimator_options(method: Method, config: EstimatorConfig, *, threshold: float | None = None,
                      initial_images: int | None = None, final_only: bool = False) -> (
        SequentialOptions | SimOptions):
    """The options of the chosen estimator: the config file's, overridden by command flags.

    Parameters
    ----------
    method : Method
    config : EstimatorConfig
    threshold : float or None
        ``--threshold`` (Seq-R correlation threshold in [0, 1]); ``None``: not given.
    initial_images : int or None
        ``--initial-images`` (images of the initial simultaneous stage); ``None``: not given.
    final_only : bool
        ``--final-only`` (Sim only: adjust once at the end).

    Raises
    ------
    ConfigError
        A flag that does not apply to the method, or an invalid value.
    """
    if method is Method.SIM:
        for flag, value in (("--threshold", threshold), ("--initial-images", initial_images)):
            if value is not None:
                raise ConfigError(f"{flag} applies to the sequential methods, not --method sim")
        return config.sim
    if final_only:
        raise ConfigError(f"--final-only applies to --method sim, not --method {method.value}")
    opts = config.sequential
    if method is Method.SEQ_F:
        if threshold is not None:
            raise ConfigError("--threshold applies to --method seq-r (seq-f keeps every "
                              "parameter in the update)")
        opts = dataclasses.replace(opts, correlation_threshold=None)
    elif threshold is not None:
        opts = dataclasses.replace(opts, correlation_threshold=threshold)
    elif opts.correlation_threshold is None:
        raise ConfigError("--method seq-r needs a correlation threshold (sequential."
                          "correlation_threshold is null; use --method seq-f for no cut)")
    if initial_images is not None:
        opts = dataclasses.replace(opts, initial_images=initial_images)
    return opts


class ImageListener(Protocol):
    """Something that follows a run image by image (live ortho, journal, watch display).

    ``on_image`` is called after each update with the frame, its update record and the
    estimator (query ``window_solution()`` there: O(window)); ``on_finish`` once after the
    final solution, before the run folder is published.
    """

    def on_image(self, frame: Frame, update: ImageUpdate, estimator: Estimator) -> None: ...

    def on_finish(self, solution: Solution) -> None: ...


class Estimator(Protocol):
    """What the runner needs from an estimator (SequentialAT, SimultaneousAT)."""

    def add_frame(self, frame: Frame) -> ImageUpdate: ...

    def solution(self) -> Solution: ...


def make_estimator(method: Method, camera: PinholeCamera, options: SequentialOptions | SimOptions,
                   *, final_only: bool = False) -> Estimator:
    """Build the estimator of ``method`` with ``options`` (from :func:`estimator_options`)."""
    if method is Method.SIM:
        assert isinstance(options, SimOptions)
        return SimultaneousAT(camera, options, refit_every_frame=not final_only)
    assert isinstance(options, SequentialOptions)
    return SequentialAT(camera, options)


@dataclass(frozen=True, kw_only=True)
class RunSummary:
    """Typed result of :func:`run_flight` (what ``seqat run`` prints).

    Attributes
    ----------
    method : Method
    flight_dir, out_dir : Path
    files : tuple[Path, ...]
        ``eop.csv``, ``points.csv``, ``run.json``.
    n_images, n_points, n_observations : int
        Images adjusted, ground points estimated, image observations read.
    sigma0 : float
        A posteriori standard error of unit weight of the final solution.
    redundancy : int
    update_ms : TimingStats
        Per-image update times.
    wall_s : float
        Wall time of the whole stage (reading, estimating, writing).
    accuracy : Accuracy or None
        Against ``truth/`` when the flight has it (simulated flights).
    """

    method: Method
    flight_dir: Path
    out_dir: Path
    files: tuple[Path, ...]
    n_images: int
    n_points: int
    n_observations: int
    sigma0: float
    redundancy: int
    update_ms: TimingStats
    sequential_update_ms: TimingStats
    wall_s: float
    accuracy: Accuracy | None


def _progress(console: Console, enabled: bool) -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console,
                    transient=True, disable=not (enabled and console.is_terminal))


def run_flight(flight_dir: Path | str, out_dir: Path | str, *, method: Method = Method.SEQ_R,
               final_only: bool = False, options_path: Path | str | None = None,
               threshold: float | None = None, initial_images: int | None = None,
               progress: bool = True, observations: Path | str | None = None,
               listeners: Sequence[ImageListener] = ()) -> RunSummary:
    """Adjust a flight folder with one method and write the results to ``out_dir``.

    Parameters
    ----------
    flight_dir : Path or str
        Flight folder (docs/formats.md).
    out_dir : Path or str
        Output folder; created if absent, existing ``eop.csv``, ``points.csv`` and
        ``run.json`` are replaced only when the run succeeds.
    method : Method
    final_only : bool
        Sim only: buffer the frames and adjust once at the end.
    options_path : Path, str or None
        Estimator options file (:class:`EstimatorConfig`).
    threshold, initial_images : optional
        Command-line overrides (:func:`estimator_options`).
    progress : bool
        Show a transient progress bar on a terminal (stderr).
    observations : Path, str or None
        Image points (``observations.csv`` format) replacing the flight's own or, for an
        image flight, the tracker: replays the tie points of an earlier run
        (``OUT/observations.csv``) with another method.
    listeners : sequence of ImageListener
        Called after every image and once at the end (:class:`ImageListener`).

    Returns
    -------
    RunSummary

    Raises
    ------
    ConfigError, InputDataError
        Bad options or input, detected before anything is computed or written.
    EstimationError
        The adjustment failed; nothing is written.
    """
    t_start = time.perf_counter()
    method = Method(method)
    out = Path(out_dir)
    config = load_estimator_config(options_path) if options_path is not None else EstimatorConfig()
    options = estimator_options(method, config, threshold=threshold,
                                initial_images=initial_images, final_only=final_only)
    if out.exists() and not out.is_dir():
        raise InputDataError(f"{out}: exists and is not a folder")
    flight = read_flight(flight_dir)
    if observations is not None:
        obs_path = Path(observations)
        if not obs_path.is_file():
            raise InputDataError(f"{obs_path}: no such file (--observations)")
        flight = dataclasses.replace(flight, observations_path=obs_path)
    truth = read_truth(flight.path)
    source: ObservationSource | ImageSource
    if flight.kind == "observations":
        source = ObservationSource(flight)
    else:
        source = ImageSource(flight, flight.config.tracking)
    estimator = make_estimator(method, flight.camera, options, final_only=final_only)
    updates: list[ImageUpdate] = []
    console = Console(stderr=True)
    for warning in flight.warnings:
        console.print(f"seqat: warning: {warning}", highlight=False, markup=False)
    for skipped in flight.skipped:
        console.print(f"seqat: skipped: {skipped.reason}", highlight=False, markup=False)
    with _progress(console, progress) as bar:
        task = bar.add_task(method.value, total=len(flight.nav), info="")
        for frame in source:
            update = estimator.add_frame(frame)
            updates.append(update)
            source.feedback(update, estimator)
            for listener in listeners:
                listener.on_image(frame, update, estimator)
            bar.update(task, advance=1,
                       info=f"{update.update_ms:7.1f} ms  window {update.window_images}")
    finish = getattr(estimator, "finish", None)
    if finish is not None:
        finish()  # sequential: re-linearise the window at the final estimate
    solution = estimator.solution()
    for listener in listeners:
        listener.on_finish(solution)
    stats = source.stats()
    for skipped in source.skipped:  # GNSS dropouts that could not be bridged
        console.print(f"seqat: skipped: {skipped.reason}", highlight=False, markup=False)

    eops, points = eop_table(solution.eops), point_table(solution.points)
    accuracy = (compare_with_truth(eops, points, truth.eop, truth.points, flight.nav)
                if truth is not None else None)
    timing = TimingStats.from_samples([u.update_ms for u in updates])
    timing_seq = TimingStats.from_samples([u.update_ms for u in updates if u.stage == "sequential"])
    totals = RunTotals(images=len(solution.eops), points=len(solution.points),
                       observations=stats.n_observations, update_ms=timing,
                       sequential_update_ms=timing_seq,
                       wall_s=time.perf_counter() - t_start, sigma0=solution.sigma0,
                       redundancy=solution.redundancy, accuracy=accuracy)
    inputs = dataclasses.replace(flight.inputs(), skipped=flight.skipped + tuple(source.skipped))
    robustness = robustness_record(estimator, options, bridged=source.bridged,
                                   skipped=[s.image for s in source.skipped])
    record = RunRecord(method=method.value, flight=str(flight.path), inputs=inputs,
                       options=options, final_only=final_only, images=tuple(updates),
                       totals=totals, tracking_options=source.tracking_options,
                       tracking=source.tracking_stats, robustness=robustness)
    files = write_run_outputs(out, solution, record, source.observations_text())
    return RunSummary(method=method, flight_dir=flight.path, out_dir=out, files=files,
                      n_images=totals.images, n_points=totals.points,
                      n_observations=stats.n_observations, sigma0=solution.sigma0,
                      redundancy=solution.redundancy, update_ms=timing,
                      sequential_update_ms=timing_seq, wall_s=time.perf_counter() - t_start,
                      accuracy=accuracy)
