"""``seqat reference OUT --sfm``: an independent SfM of the flight's images, and how each method
agrees with it after a similarity. Written to ``OUT/reference/sfm/`` (docs/formats.md).

COLMAP's own structure from motion (:mod:`pipeline.reference.sfm`) sees only the images (and
the nav positions, to pick the pairs it matches); its model, in its own datum, is aligned to
the EOPs of every method the run folder holds by a 7-parameter similarity on the camera
centres (:mod:`pipeline.reference.similarity`): the run's own method (``eop.csv``), the runs
given with ``compare``, the COLMAP reference (``OUT/reference/eop.csv``, label ``colmap``) and
the nav itself (direct georeferencing, label ``direct``). What remains after the similarity is
an *agreement* between two estimates of the same poses, not an accuracy: the SfM has errors
of its own, and a similarity absorbs any datum error they share.

The folder is published whole (:func:`~pipeline.common.atomic.building_folder`): ``sfm.json``,
``images.csv``, ``residuals.png`` and ``model/`` (the SfM model, COLMAP binary, its own frame).
COLMAP's scratch files (feature database, mapper output) live inside the folder being built
and are removed before it is published.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from pipeline.common.atomic import atomic_write_text, building_folder
from pipeline.common.columns import EOP_FILE, REFERENCE_DIR, SFM_DIR
from pipeline.common.csvio import format_csv_line
from pipeline.common.outdir import output_errors
from pipeline.common.text import first_few
from pipeline.flight.navigation import image_files
from pipeline.flight.schema import CameraConfig
from pipeline.reference.sfm import (
    SfmInput,
    SfmModel,
    SfmOptions,
    model_from_reconstruction,
    run_sfm,
)
from pipeline.reference.similarity import (
    AgreementStats,
    PoseAgreement,
    agreement_stats,
    pose_agreement,
)
from pipeline.run.store import JSON_INDENT, RunFolder, fmt, read_eop_csv, read_run, to_jsonable
from seqat.errors import EstimationError, InputDataError
from seqat.types import FloatArray

#: The files of ``OUT/reference/sfm/``.
SFM_JSON = "sfm.json"
SFM_IMAGES_CSV = "images.csv"
SFM_PLOT = "residuals.png"
SFM_MODEL_DIR = "model"
WORK_DIR = ".work"
SFM_JSON_VERSION = 1
#: Columns of ``images.csv``: one row per (method, registered image).
SFM_IMAGE_COLUMNS = ("method", "image", "inlier", "x_m", "y_m", "z_m", "dx_m", "dy_m", "dz_m",
                     "d_m", "domega_deg", "dphi_deg", "dkappa_deg", "dangle_deg")
#: Labels shared with the report (pipeline/report/model.py): the nav and the COLMAP reference.
DIRECT = "direct"
REFERENCE = "colmap"
#: What the numbers are (sfm.json ``note``, the report).
AGREEMENT_NOTE = ("Agreement, not accuracy: the differences between each method and an "
                  "independent COLMAP structure from motion of the same images after a "
                  "7-parameter similarity; both have errors, and any error they share, or "
                  "that a similarity absorbs, does not show.")
PLOT_DPI = 110


@dataclass(frozen=True, kw_only=True, eq=False)
class MethodPoses:
    """One method's EOPs to compare with the SfM."""

    label: str
    source: str  # the file they came from
    image_ids: tuple[str, ...]
    eop: FloatArray  # (n, 6) metres, radians


@dataclass(frozen=True, kw_only=True, eq=False)
class MethodAgreement:
    """The SfM aligned to one method."""

    label: str
    source: str
    image_ids: tuple[str, ...]
    centres_m: FloatArray  # (n, 3) the method's camera centres (world)
    agreement: PoseAgreement
    stats: AgreementStats


@dataclass(frozen=True, kw_only=True)
class SfmSummary:
    """Typed result of :func:`run_sfm_check` (what ``seqat reference --sfm`` prints)."""

    out_dir: Path
    sfm_dir: Path
    n_images: int
    n_registered: int
    n_points: int
    mean_reprojection_px: float
    mean_track_length: float
    camera: CameraConfig
    run_camera: CameraConfig
    methods: tuple[tuple[str, AgreementStats], ...]
    wall_s: float


def sfm_input(run: RunFolder, images_dir: Path | None = None) -> SfmInput:
    """The run's images (every image of its nav), found in the run's (or the given) folder.

    Raises
    ------
    InputDataError
        The run has no images (an observations flight), the folder or an image is missing.
    """
    folder = images_dir if images_dir is not None else run.images_dir
    if folder is None:
        raise InputDataError(f"{run.path}: the run has no images (an observations flight); "
                             "an SfM check needs the flight's images")
    if not folder.is_dir():
        raise InputDataError(f"{folder}: no such image folder (recorded in "
                             f"{run.path / 'run.json'}; give another with --images)")
    files = {p.stem: p for p in image_files(folder)}
    ids = run.nav.image_ids
    missing = [i for i in ids if i not in files]
    if missing:
        raise InputDataError(f"{folder}: {len(missing)} of the run's {len(ids)} images are "
                             f"missing: {first_few(missing)}")
    z = run.points.xyz_m[:, 2]
    z = z[np.isfinite(z)]
    return SfmInput(image_dir=folder, image_ids=tuple(ids),
                    file_names=tuple(files[i].name for i in ids),
                    positions=np.asarray(run.nav.eop[:, :3], dtype=np.float64),
                    camera=run.camera, ground_z_m=float(np.median(z)) if z.size else np.nan)


def methods_of(run: RunFolder, compare: Sequence[RunFolder] = ()) -> list[MethodPoses]:
    """The EOPs the SfM is compared with: the run, the compared runs, colmap, direct."""
    methods: list[MethodPoses] = []
    labels: set[str] = set()
    for r in (run, *compare):
        label = r.method if r.method not in labels else f"{r.method} ({r.path.name})"
        labels.add(label)
        methods.append(MethodPoses(label=label, source=str(r.path / EOP_FILE),
                                   image_ids=r.eop.image_ids, eop=r.eop.eop))
    ref_eop = run.path / REFERENCE_DIR / EOP_FILE
    if ref_eop.is_file():
        ref = read_eop_csv(ref_eop)
        methods.append(MethodPoses(label=REFERENCE, source=str(ref_eop),
                                   image_ids=ref.image_ids, eop=ref.eop))
    methods.append(MethodPoses(label=DIRECT, source=str(run.path / "nav.csv"),
                               image_ids=run.nav.image_ids, eop=run.nav.eop))
    return methods


def align(model: SfmModel, method: MethodPoses) -> MethodAgreement:
    """The SfM aligned to one method on the images both have (finite EOPs)."""
    index = {iid: i for i, iid in enumerate(method.image_ids)}
    rows = [(k, index[iid]) for k, iid in enumerate(model.image_ids)
            if iid in index and np.all(np.isfinite(method.eop[index[iid]]))]
    k = np.array([r[0] for r in rows], dtype=np.int64)
    m = np.array([r[1] for r in rows], dtype=np.int64)
    try:
        agreement = pose_agreement(model.centres[k], model.R_cam_from_world[k], method.eop[m])
    except EstimationError as err:
        raise EstimationError(f"SfM vs {method.label}: {err}") from err
    return MethodAgreement(label=method.label, source=method.source,
                           image_ids=tuple(model.image_ids[i] for i in k),
                           centres_m=method.eop[m, :3], agreement=agreement,
                           stats=agreement_stats(agreement))


def format_images_csv(results: Sequence[MethodAgreement]) -> str:
    """Text of ``images.csv``."""
    lines = [format_csv_line(SFM_IMAGE_COLUMNS)]
    for r in results:
        a = r.agreement
        deg = np.degrees(a.d_angles_rad)
        for i, iid in enumerate(r.image_ids):
            values = [*r.centres_m[i], *a.d_xyz_m[i], a.d_position_m[i], *deg[i],
                      np.degrees(a.d_rotation_rad[i])]
            lines.append(format_csv_line([r.label, iid, "1" if a.inlier[i] else "0",
                                          *(fmt(v) for v in values)]))
    return "".join(lines)


def plot_residuals(results: Sequence[MethodAgreement], path: Path) -> None:
    """One map per method: camera centres, horizontal residual vectors (arrows, scaled) and
    the height residual (colour)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    cols = min(n, 2)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6.0 * cols, 5.0 * rows), squeeze=False)
    origin = np.round(results[0].centres_m.mean(axis=0))
    extent = float(np.ptp(results[0].centres_m[:, :2], axis=0).max()) or 1.0
    for ax, r in zip(axes.flat, results, strict=False):
        c = r.centres_m - origin
        d = r.agreement.d_xyz_m
        h = np.linalg.norm(d[:, :2], axis=1)
        scale = 0.15 * extent / max(float(h.max()), 1e-9)  # longest arrow: 15 % of the block
        lim = max(float(np.abs(d[:, 2]).max()), 1e-9)
        sc = ax.scatter(c[:, 0], c[:, 1], c=d[:, 2], cmap="coolwarm", vmin=-lim, vmax=lim,
                        s=24, edgecolors=np.where(r.agreement.inlier, "k", "m"), zorder=3)
        ax.quiver(c[:, 0], c[:, 1], d[:, 0] * scale, d[:, 1] * scale, angles="xy",
                  scale_units="xy", scale=1.0, width=0.004, zorder=2)
        s = r.stats
        ax.set_title(f"{r.label}: {s.position_rms_m:.3g} m rms, {s.attitude_rms_deg:.3g}° rms\n"
                     f"arrows: horizontal x{scale:.3g} (max {h.max():.3g} m)", fontsize=9)
        ax.set_xlabel(f"x - {origin[0]:.0f} (m)")
        ax.set_ylabel(f"y - {origin[1]:.0f} (m)")
        ax.set_aspect("equal", adjustable="datalim")
        fig.colorbar(sc, ax=ax, label="dz (m)", shrink=0.8)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    fig.suptitle("SfM minus method after a similarity (magenta edge: left out of the fit)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=PLOT_DPI)
    plt.close(fig)


def sfm_record(run: RunFolder, data: SfmInput, model: SfmModel, options: SfmOptions,
               results: Sequence[MethodAgreement], wall_s: float,
               realigned: bool = False) -> dict[str, object]:
    """``sfm.json`` (docs/formats.md, *SfM check*)."""
    import pycolmap

    registered = set(model.image_ids)
    methods = []
    for r in results:
        sim = r.agreement.similarity
        methods.append({
            "label": r.label, "source": r.source, **to_jsonable(r.stats),
            "similarity": {"scale": sim.scale, "rotation": sim.rotation,
                           "translation_m": sim.translation}})
    return {
        "version": SFM_JSON_VERSION, "run": str(run.path), "method_of_run": run.method,
        "images_dir": str(data.image_dir), "note": AGREEMENT_NOTE, "options": options,
        "n_images": model.n_images, "n_registered": len(model.image_ids),
        "unregistered": [i for i in data.image_ids if i not in registered],
        "n_models": model.n_models, "n_matched_pairs": model.n_matched_pairs,
        "spatial_max_distance_m": model.spatial_max_distance_m, "n_points": model.n_points,
        "n_observations": model.n_observations,
        "mean_reprojection_px": model.mean_reprojection_px,
        "mean_track_length": model.mean_track_length, "camera_model": "OPENCV",
        "camera": model.camera, "run_camera": run.camera,
        "run_camera_approximate": run.inputs.camera_approximate,
        "seconds": model.seconds if realigned else {**model.seconds, "total": wall_s},
        "realigned": realigned, "methods": methods,
        "pycolmap_version": str(pycolmap.__version__)}


def load_model(folder: Path, data: SfmInput) -> tuple[SfmModel, SfmOptions]:
    """The SfM model of an earlier check (``--realign``) and the options it was made with.

    Raises
    ------
    InputDataError
        No earlier check in ``folder``, or an unreadable one.
    """
    import pycolmap

    from pipeline.common.strict_yaml import build_dataclass
    from pipeline.run.store import read_json_object
    from seqat.errors import ConfigError

    record = folder / SFM_JSON
    if not record.is_file() or not (folder / SFM_MODEL_DIR).is_dir():
        raise InputDataError(f"{folder}: no earlier SfM check to realign (run `seqat reference "
                             "OUT --sfm` first)")
    doc = read_json_object(record)
    try:
        options = build_dataclass(SfmOptions, doc["options"], str(record), key="options")
        rec = pycolmap.Reconstruction(str(folder / SFM_MODEL_DIR))
        seconds = {k: float(v) for k, v in doc["seconds"].items()}
        model = model_from_reconstruction(
            rec, data, n_models=int(doc["n_models"]), n_pairs=int(doc["n_matched_pairs"]),
            distance=doc["spatial_max_distance_m"], seconds=seconds)
    except (KeyError, TypeError, ValueError, AttributeError, ConfigError,
            EstimationError) as err:
        raise InputDataError(f"{record}: cannot realign: {err}") from err
    return model, options


def _progress_bar(console: Console, enabled: bool) -> Progress:
    return Progress(TextColumn("[bold]sfm {task.description}"), BarColumn(),
                    MofNCompleteColumn(), TimeElapsedColumn(), console=console,
                    transient=True, disable=not (enabled and console.is_terminal))


@contextlib.contextmanager
def _remove_if_created_empty(folder: Path):  # type: ignore[no-untyped-def]
    """``OUT/reference/`` made only to hold ``sfm/`` goes again when that fails."""
    existed = folder.exists()
    try:
        yield
    except BaseException:
        if not existed:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def run_sfm_check(out_dir: Path | str, options: SfmOptions | None = None, *,
                  compare: Sequence[Path | str] = (), images_dir: Path | str | None = None,
                  realign: bool = False, progress: bool = True) -> SfmSummary:
    """SfM of a run's images, aligned to each method; publishes ``OUT/reference/sfm/``.

    Parameters
    ----------
    out_dir : Path or str
        A run folder (``seqat run FLIGHT --out OUT``) of an image flight.
    options : SfmOptions
    compare : sequence of run folders
        Further runs of the same flight (one method each) to compare with the SfM.
    images_dir : Path or str, optional
        Where the images are, if not where ``run.json`` says.
    realign : bool
        Keep the SfM model of an earlier check (and its options) and only align it again, to
        the methods there are now (``compare``, a new ``OUT/reference/``); no images are read
        but the folder must still hold them.
    progress : bool
        Transient progress bars on a terminal (stderr).

    Raises
    ------
    InputDataError
        Not a run folder, no images, images missing (nothing is written).
    EstimationError
        The SfM registered too few images, or no similarity fits (nothing is written).
    """
    t0 = time.perf_counter()
    options = options if options is not None else SfmOptions()
    out = Path(out_dir)
    run = read_run(out)
    others = [read_run(Path(c)) for c in compare]
    data = sfm_input(run, None if images_dir is None else Path(images_dir))
    methods = methods_of(run, others)
    console = Console(stderr=True, soft_wrap=True)
    target = out / REFERENCE_DIR / SFM_DIR
    earlier: SfmModel | None = None
    if realign:
        earlier, options = load_model(target, data)
    with _remove_if_created_empty(out / REFERENCE_DIR), building_folder(target) as tmp:
        if earlier is not None:
            model = earlier
        else:
            work = tmp / WORK_DIR
            work.mkdir()
            with _progress_bar(console, progress) as bar:
                tasks: dict[str, int] = {}

                def report(stage: str, done: int, total: int) -> None:
                    if stage not in tasks:
                        tasks[stage] = bar.add_task(stage, total=total)
                    bar.update(tasks[stage], completed=done, total=total)

                model = run_sfm(data, work, options, report)
            shutil.rmtree(work)
        results = [align(model, m) for m in methods]
        with output_errors(target):
            (tmp / SFM_MODEL_DIR).mkdir()
            model.reconstruction.write_binary(str(tmp / SFM_MODEL_DIR))
            plot_residuals(results, tmp / SFM_PLOT)
        wall = time.perf_counter() - t0
        record = sfm_record(run, data, model, options, results, wall, realigned=realign)
        atomic_write_text(tmp / SFM_IMAGES_CSV, format_images_csv(results))
        atomic_write_text(tmp / SFM_JSON, json.dumps(to_jsonable(record), indent=JSON_INDENT,
                                                     allow_nan=False) + "\n")
    return SfmSummary(out_dir=out, sfm_dir=target, n_images=model.n_images,
                      n_registered=len(model.image_ids), n_points=model.n_points,
                      mean_reprojection_px=model.mean_reprojection_px,
                      mean_track_length=model.mean_track_length, camera=model.camera,
                      run_camera=run.camera,
                      methods=tuple((r.label, r.stats) for r in results),
                      wall_s=time.perf_counter() - t0)
