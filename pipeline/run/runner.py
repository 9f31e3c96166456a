"""``seqat run``: stream a flight folder through an estimator and store the results.

The stage: validate the whole input first (flight.yaml, CRS, nav, one pass over
observations.csv, truth) so bad input fails before any computation and nothing is written;
then feed frames one at a time in acquisition order to the estimator (Seq-R, Seq-F or Sim)
through a :class:`~pipeline.run.session.RunSession` (the per-image path ``seqat watch`` shares:
update, feedback, listeners, latency budget, journal), and publish ``eop.csv``,
``points.csv`` and ``run.json`` together (:func:`pipeline.run.store.write_run_outputs`).
``--resume`` replays the journal of an interrupted run first (:mod:`pipeline.run.journal`).
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import math
import time
from collections.abc import Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from pipeline.common.columns import FLIGHT_YAML
from pipeline.common.outdir import claim_output_folder, output_errors, release_output_folder
from pipeline.common.paths import file_problem
from pipeline.common.strict_yaml import build_dataclass, load_yaml
from pipeline.flight.folder import (
    Flight,
    Truth,
    read_flight,
    read_truth,
    with_self_calibration,
)
from pipeline.flight.gcp import GroundControl
from pipeline.flight.inputs import RunInputs, SkippedImage
from pipeline.run.accuracy import Accuracy, compare_with_truth
from pipeline.run.budget import BudgetReport, LatencyBudget
from pipeline.run.control import control_record, format_control_csv
from pipeline.run.journal import (
    Journal,
    JournalContents,
    check_fingerprint,
    read_journal,
    replay_checks,
)
from pipeline.run.nav_agreement import nav_disagreement_warning, nav_fault_warnings
from pipeline.run.robustness import RobustnessRecord, robustness_record
from pipeline.run.session import Estimator, ImageListener, RunSession
from pipeline.run.sources import ImageSource, ObservationSource
from pipeline.run.store import (
    RunRecord,
    RunTotals,
    TimingStats,
    eop_table,
    point_table,
    to_jsonable,
    write_run_outputs,
)
from pipeline.tracking.options import TrackerOptions
from seqat.calibration import SelfCalibration
from seqat.errors import ConfigError, InputDataError, SeqatError
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simultaneous import SimOptions, SimultaneousAT
from seqat.types import PinholeCamera, Solution

__all__ = ["Estimator", "EstimatorConfig", "ImageListener", "Method", "RunSummary",
           "estimator_options", "flight_inputs", "load_journal", "make_estimator", "run_flight",
           "start_journal", "with_calibration"]


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
    #: Adjust the flight once more from its GPS/INS when the run is finished, and publish
    #: that if the run stopped in a wrong minimum (:mod:`pipeline.run.final_check`).
    final_check: bool = True


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


def with_calibration(options: SequentialOptions | SimOptions,
                     calibration: SelfCalibration | None) -> SequentialOptions | SimOptions:
    """``options`` with the flight's self-calibration (``flight.yaml`` ``self_calibration:``,
    on by default for a camera from EXIF).

    Raises
    ------
    ConfigError
        The estimator options file set ``calibration`` itself (it belongs to the flight).
    """
    if options.calibration is not None and options.calibration != calibration:
        raise ConfigError("calibration: the self-calibration is set in flight.yaml "
                          "(self_calibration:) or with --self-calibration/--fixed-camera, "
                          "not in the estimator options")
    return dataclasses.replace(options, calibration=calibration)


def make_estimator(method: Method, camera: PinholeCamera, options: SequentialOptions | SimOptions,
                   *, final_only: bool = False,
                   control: GroundControl | None = None) -> Estimator:
    """Build the estimator of ``method`` with ``options`` (from :func:`estimator_options`)
    and the flight's ground control points (``seqat.types.ControlPoint``)."""
    extra: dict[str, object] = {}
    if control is not None and control.points:
        from seqat.types import ControlPoint

        extra["control"] = tuple(ControlPoint(point_id=p.point_id, xyz_m=p.xyz_m,
                                              sigma_m=p.sigma_m) for p in control.points)
    if method is Method.SIM:
        assert isinstance(options, SimOptions)
        return SimultaneousAT(camera, options, refit_every_frame=not final_only, **extra)  # type: ignore[arg-type]
    assert isinstance(options, SequentialOptions)
    return SequentialAT(camera, options, **extra)  # type: ignore[arg-type]


@dataclass(frozen=True, kw_only=True)
class RunSummary:
    """Typed result of :func:`run_flight` and :func:`pipeline.run.watch.watch_flight`.

    Attributes
    ----------
    method : Method
    flight_dir, out_dir : Path
    files : tuple[Path, ...]
        ``eop.csv``, ``points.csv``, ``run.json``, ``nav.csv``, ``observations.csv``.
    n_images, n_points, n_observations : int
        Images adjusted, ground points estimated, image observations used.
    sigma0 : float
        A posteriori standard error of unit weight of the final solution.
    redundancy : int
    update_ms, sequential_update_ms : TimingStats
        Per-image update times (all images; the sequential stage only).
    wall_s : float
        Wall time of the whole stage (reading, estimating, writing).
    accuracy : Accuracy or None
        Against ``truth/`` when the flight has it (simulated flights).
    replayed : int
        Images replayed from the journal (``--resume``).
    latency_ms : TimingStats or None
        End-to-end latency per image (watch mode).
    budget : BudgetReport or None
        The latency budget and its threshold changes (``--budget-ms``).
    skipped : tuple[SkippedImage, ...]
        Images left out.
    stopped : str
        Why a watch stopped (``idle``, ``interrupted``); empty for a run.
    second_start_ms : TimingStats or None
        Second starts tried after updates (Seq-R, ``ImageUpdate.second_start``): their
        times; None when none was tried.
    sequential_refine_ms : TimingStats or None
        Seq-R / Seq-F: the refinements run after the sequential updates, once each image's
        estimate was out (``ImageUpdate.refine_ms``: drift check, re-linearisation, second
        start; not in the update times); None when none ran.
    second_starts_tried, second_starts_kept : int
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
    replayed: int = 0
    latency_ms: TimingStats | None = None
    budget: BudgetReport | None = None
    skipped: tuple[SkippedImage, ...] = ()
    stopped: str = ""
    second_start_ms: TimingStats | None = None
    sequential_refine_ms: TimingStats | None = None
    second_starts_tried: int = 0
    second_starts_kept: int = 0


def _finishing(console: Console, enabled: bool) -> AbstractContextManager[object]:
    """A spinner while the run finishes (final re-linearisation, final check)."""
    if not enabled:
        return nullcontext()
    return console.status("finishing: final adjustment and its check from the GPS/INS")


def _progress(console: Console, enabled: bool) -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console,
                    transient=True, disable=not (enabled and console.is_terminal))


#: ``budget_ms`` of :func:`make_budget`: keep up with the arrivals (``seqat watch``'s default).
KEEP_UP = "keep-up"


def make_budget(budget_ms: float | str | None, method: Method,
                options: SequentialOptions | SimOptions) -> LatencyBudget | None:
    """The latency budget (:mod:`pipeline.run.budget`): ``--budget-ms`` N (Seq-R only),
    :data:`KEEP_UP` (Seq-R; other methods have no dial to turn: none), or None.

    Raises
    ------
    ConfigError
        ``--budget-ms`` N with another method than seq-r, or not positive.
    """
    if budget_ms is None:
        return None
    seq_r = method is Method.SEQ_R and isinstance(options, SequentialOptions)
    if budget_ms == KEEP_UP:
        if not seq_r:
            return None
        budget_ms = None
    elif not seq_r:
        raise ConfigError(f"--budget-ms applies to --method seq-r (it tightens the window "
                          f"threshold), not --method {method.value}")
    assert isinstance(options, SequentialOptions) and options.correlation_threshold is not None
    return LatencyBudget(None if budget_ms is None else float(budget_ms),
                         options.correlation_threshold,
                         base_window_cap=options.max_window_images)


#: What the journal's frames hold (fingerprint ``frame_pixels``): the observed pixels, with
#: the lens distortion in seqat's camera (:func:`pipeline.flight.camera.seqat_camera`); the
#: journals of earlier versions held ideal pixels and are not resumed.
FRAME_PIXELS = "observed"


def run_fingerprint(flight_dir: Path, method: Method, options: SequentialOptions | SimOptions,
                    final_only: bool, observations: Path | None,
                    control: GroundControl | None = None) -> dict[str, object]:
    """What a journal must have been written with to be resumed (flight and options; the
    ground control file and its points, when the flight has GCPs; what its frames' pixels
    are)."""
    yaml_path = flight_dir / FLIGHT_YAML
    digest = (hashlib.sha256(yaml_path.read_bytes()).hexdigest() if yaml_path.is_file()
              else None)
    extra: dict[str, object] = {}
    if control is not None:
        extra["gcp"] = {"file": str(control.path.resolve()),
                        "sha256": hashlib.sha256(control.path.read_bytes()).hexdigest(),
                        "sigma_m": [repr(p.sigma_m.tolist()) for p in control.points]}
    return {**extra, "flight": str(flight_dir.resolve()), "flight_yaml_sha256": digest,
            "frame_pixels": FRAME_PIXELS,
            "method": method.value, "options": to_jsonable(options), "final_only": final_only,
            "observations": None if observations is None else str(observations.resolve())}


def open_journal(out: Path, fingerprint: dict[str, object], resume: bool,
                 console: Console) -> tuple[Journal, JournalContents | None]:
    """A new journal, or with ``resume`` the existing one checked against ``fingerprint``.

    Raises
    ------
    ConfigError
        The journal was written for another flight or other options.
    InputDataError
        The journal is damaged (other than a torn last record, which is dropped).
    """
    contents = load_journal(out, fingerprint, resume, console)
    return start_journal(out, fingerprint, contents), contents


def load_journal(out: Path, fingerprint: dict[str, object], resume: bool,
                 console: Console) -> JournalContents | None:
    """With ``resume``, the journal in ``out`` checked against ``fingerprint`` (None: none,
    or not resuming). Reads only: nothing in ``out`` changes."""
    contents = read_journal(out) if resume else None
    if contents is None:
        if resume:
            console.print(f"seqat: no journal in {out}: starting from the first image",
                          highlight=False, markup=False)
        return None
    check_fingerprint(contents, fingerprint, out)
    if contents.dropped is not None:
        console.print(f"seqat: journal: dropped the torn last record ({contents.dropped})",
                      highlight=False, markup=False)
    return contents


def start_journal(out: Path, fingerprint: dict[str, object],
                  contents: JournalContents | None) -> Journal:
    """A new journal (``contents`` None: an earlier one is replaced), or the one read."""
    if contents is None:
        return Journal.create(out, fingerprint)
    return Journal.resume(out, contents)


def replay_journal(session: RunSession, source: ObservationSource | ImageSource,
                   journal: Journal, contents: JournalContents | None) -> None:
    """Replay the journaled frames and restore the tracker after the last one."""
    if contents is None or not contents.images:
        return
    last = contents.images[-1]
    if isinstance(source, ImageSource):
        if not last.tracker_state:
            raise InputDataError(f"{journal.folder}: the last image has no tracker state; "
                                 "rerun without --resume")
        source.restore_tracker(journal.load_tracker_state(last.seq))
    for record in contents.images:
        session.replay(record)


def publish_run(out: Path, session: RunSession, solution: Solution, *, method: Method,
                flight: str, inputs: RunInputs, options: SequentialOptions | SimOptions,
                final_only: bool, tracking_options: TrackerOptions | None,
                truth: Truth | None, t_start: float, mode: str = "run",
                stopped: str = "", robustness: RobustnessRecord | None = None,
                control: GroundControl | None = None, echo_warnings: bool = True) -> RunSummary:
    """Write the run folder (atomically, all files or none) and summarise the run."""
    eops, points = eop_table(solution.eops), point_table(solution.points)
    extra = session.tie_point_warnings(solution) + session.check_warnings()
    disagreement = nav_disagreement_warning(
        eops, inputs.nav, inputs.nav_sigma,
        camera_fixed=options.calibration is None)
    if disagreement is not None:
        extra.append(disagreement)
    else:  # the odd fix the tie points overruled
        extra += nav_fault_warnings(eops, inputs.nav, inputs.nav_sigma)
    if extra and echo_warnings:
        console = Console(stderr=True, soft_wrap=True)
        for warning in extra:
            console.print(f"seqat: warning: {warning}", highlight=False, markup=False)
    if extra:
        inputs = dataclasses.replace(inputs, warnings=(*inputs.warnings, *extra))
    accuracy = (compare_with_truth(eops, points, truth.eop, truth.points, inputs.nav)
                if truth is not None else None)
    updates = session.updates
    timing = TimingStats.from_samples([u.update_ms for u in updates])
    timing_seq = TimingStats.from_samples([u.update_ms for u in updates if u.stage == "sequential"])
    latencies = [x.latency_ms for x in session.live if x.latency_ms is not None]
    latency = TimingStats.from_samples(latencies) if latencies else None
    trials = [u for u in updates if u.second_start]
    trial_ms = TimingStats.from_samples([u.second_start_ms for u in trials]) if trials else None
    refine = [u.refine_ms for u in updates
              if u.stage == "sequential" and math.isfinite(u.refine_ms)]
    refine_ms = TimingStats.from_samples(refine) if refine else None
    budget = session.budget.report() if session.budget is not None else None
    totals = RunTotals(images=len(solution.eops), points=len(solution.points),
                       observations=session.n_observations, update_ms=timing,
                       sequential_update_ms=timing_seq,
                       wall_s=time.perf_counter() - t_start, sigma0=solution.sigma0,
                       redundancy=solution.redundancy, accuracy=accuracy, latency_ms=latency,
                       journal_ms=TimingStats.from_samples(session.journal_ms),
                       late=session.late_summary(solution), second_start_ms=trial_ms,
                       sequential_refine_ms=refine_ms)
    record = RunRecord(method=method.value, flight=flight, inputs=inputs, options=options,
                       final_only=final_only, images=tuple(updates), totals=totals,
                       tracking_options=tracking_options, tracking=tuple(session.tracking),
                       live=tuple(session.live), latency_budget=budget, mode=mode,
                       replayed=session.replayed, robustness=robustness,
                       camera_estimate=solution.camera,
                       control=control_record(control, solution) if control is not None
                       else None,
                       control_csv=format_control_csv(control) if control is not None
                       else None)
    with output_errors(out):
        files = write_run_outputs(out, solution, record, session.observations_text())
    return RunSummary(method=method, flight_dir=Path(flight), out_dir=out, files=files,
                      n_images=totals.images, n_points=totals.points,
                      n_observations=session.n_observations, sigma0=solution.sigma0,
                      redundancy=solution.redundancy, update_ms=timing,
                      sequential_update_ms=timing_seq, wall_s=time.perf_counter() - t_start,
                      accuracy=accuracy, replayed=session.replayed, latency_ms=latency,
                      budget=budget, skipped=inputs.skipped, stopped=stopped,
                      second_start_ms=trial_ms, sequential_refine_ms=refine_ms,
                      second_starts_tried=len(trials),
                      second_starts_kept=sum(u.second_start == "kept" for u in trials))


def flight_inputs(flight: Flight) -> list[Path]:
    """The paths a run reads (an output folder must stay clear of them)."""
    paths = [flight.path]
    if flight.images_dir is not None:
        paths.append(flight.images_dir)
    if flight.observations_path is not None:
        paths.append(flight.observations_path)
    if flight.config.nav.source == "file":
        paths.append(flight.path / flight.config.nav.file)
    if flight.control is not None:
        paths.append(flight.control.path)
    return paths


def run_flight(flight_dir: Path | str, out_dir: Path | str, *, method: Method = Method.SEQ_R,
               final_only: bool = False, options_path: Path | str | None = None,
               threshold: float | None = None, initial_images: int | None = None,
               progress: bool = True, observations: Path | str | None = None,
               listeners: Sequence[ImageListener] = (), resume: bool = False,
               budget_ms: float | None = None,
               self_calibration: bool | None = None, gcp: Path | str | None = None,
               gcp_sigma_m: tuple[float, float] | None = None,
               echo_warnings: bool = True) -> RunSummary:
    """Adjust a flight folder with one method and write the results to ``out_dir``.

    Parameters
    ----------
    flight_dir : Path or str
        Flight folder (docs/formats.md).
    out_dir : Path or str
        Output folder; created if absent, existing ``eop.csv``, ``points.csv`` and
        ``run.json`` are replaced only when the run succeeds. ``OUT/journal/`` records every
        image as it is adjusted (:mod:`pipeline.run.journal`).
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
    resume : bool
        Continue from ``OUT/journal/`` (written by an interrupted run of the same flight and
        options): its frames are replayed, the tracker restored, the rest adjusted; the
        results equal an uninterrupted run's. Without a journal the run starts afresh.
    budget_ms : float or None
        Latency budget per image (Seq-R): over it, the window threshold tightens
        (:class:`pipeline.run.budget.LatencyBudget`).
    self_calibration : bool or None
        Estimate the camera's interior parameters (``True``) or keep the camera fixed
        (``False``); ``None``: as ``flight.yaml`` says (by default on for a camera from EXIF).
    gcp : Path, str or None
        Ground control points (``--gcp``: ODM ``gcp_list.txt`` or a Metashape markers XML)
        in place of the flight's own (``flight.yaml`` ``gcp:``, or ``gcp_list.txt`` in it).
    gcp_sigma_m : (float, float) or None
        Default σ (horizontal, vertical, metres) of the GCPs (``--gcp-sigma-m``).
    echo_warnings : bool
        Print the flight's warnings and skipped images on stderr (``False``: a benchmark's
        further runs of a flight it has run once); ``run.json`` records them either way.

    Returns
    -------
    RunSummary

    Raises
    ------
    ConfigError, InputDataError
        Bad options or input, detected before anything is computed or written; a journal of
        another flight or other options with ``resume``.
    EstimationError
        The adjustment failed; nothing is written (the journal is removed).
    """
    t_start = time.perf_counter()
    method = Method(method)
    out = Path(out_dir)
    config = load_estimator_config(options_path) if options_path is not None else EstimatorConfig()
    options = estimator_options(method, config, threshold=threshold,
                                initial_images=initial_images, final_only=final_only)
    budget = make_budget(budget_ms, method, options)
    if out.exists() and not out.is_dir():
        raise InputDataError(f"{out}: exists and is not a folder")
    flight = with_self_calibration(read_flight(flight_dir, gcp_file=gcp,
                                               gcp_sigma_m=gcp_sigma_m), self_calibration)
    options = with_calibration(options, flight.calibration)
    obs_path = None
    if observations is not None:
        obs_path = Path(observations)
        if not obs_path.is_file():
            raise InputDataError(f"{obs_path}: {file_problem(obs_path)} (--observations)")
        flight = dataclasses.replace(flight, observations_path=obs_path)
    truth = read_truth(flight.path)
    source: ObservationSource | ImageSource
    if flight.kind == "observations":
        source = ObservationSource(flight)
        stats = source.validate()
        if stats.warnings:  # observations outside the image, left out
            flight = dataclasses.replace(flight, warnings=flight.warnings + stats.warnings)
    else:
        source = ImageSource(flight, flight.config.tracking)
    console = Console(stderr=True, soft_wrap=True)
    fingerprint = run_fingerprint(flight.path, method, options, final_only, obs_path,
                                  flight.control)
    created = claim_output_folder(out, [*flight_inputs(flight), options_path])
    try:
        with output_errors(out):
            journal, contents = open_journal(out, fingerprint, resume, console)
    except BaseException:
        release_output_folder(out, created)
        raise
    skipped = list(contents.skips) if contents is not None else []  # dropouts not bridged
    try:
        if contents is not None:
            replay_checks(contents, flight.nav.image_ids, flight.nav.eop, out)
        session = RunSession(estimator=make_estimator(method, flight.camera, options,
                                                      final_only=final_only,
                                                      control=flight.control),
                             source=source, listeners=listeners, journal=journal, budget=budget,
                             final_check=config.final_check)
        replay_journal(session, source, journal, contents)
        if echo_warnings:  # run.json records them either way
            for warning in flight.warnings:
                console.print(f"seqat: warning: {warning}", highlight=False, markup=False)
            for skip in flight.skipped:
                console.print(f"seqat: skipped: {skip.reason}", highlight=False, markup=False)
        with _progress(console, progress) as bar:
            done = session.images + len(skipped)
            task = bar.add_task(method.value, total=len(flight.nav), completed=done, info="")
            for prepared in source.frames(start=done):
                if isinstance(prepared, SkippedImage):  # a GNSS dropout that was not bridged
                    journal.append_skip(prepared)
                    skipped.append(prepared)
                    if echo_warnings:
                        console.print(f"seqat: skipped: {prepared.reason}", highlight=False,
                                      markup=False)
                    bar.update(task, advance=1)
                    continue
                live = session.add(prepared)
                bar.update(task, advance=1,
                           info=f"{live.update_ms:7.1f} ms  window {live.window_images}")
        with _finishing(console, progress):
            solution = session.finish()
    except SeqatError:
        journal.discard()  # deterministic: a resume would fail the same way
        release_output_folder(out, created)
        raise
    finally:
        journal.close()
    done_ids = {u.image_id for u in session.updates}
    bridged = [iid for row, iid in enumerate(flight.nav.image_ids)
               if iid in done_ids and flight.is_dropout(row)]
    dropouts = {iid for row, iid in enumerate(flight.nav.image_ids) if flight.is_dropout(row)}
    robustness = robustness_record(session.estimator, options, bridged=bridged,
                                   skipped=[s.image for s in skipped if s.image in dropouts],
                                   off_surface=session.off_surface,
                                   final_check=session.final_check, flown=session.flown)
    inputs = dataclasses.replace(flight.inputs(), skipped=flight.skipped + tuple(skipped))
    return publish_run(out, session, solution, method=method, flight=str(flight.path),
                       inputs=inputs, options=options, final_only=final_only,
                       tracking_options=source.tracking_options, truth=truth, t_start=t_start,
                       robustness=robustness, control=flight.control,
                       echo_warnings=echo_warnings)
