"""``seqat bench FLIGHT``: the real-flight benchmark of an image flight (issue 3).

One Seq-R run tracks the images; Sim and Seq-F then replay the *same* tie points
(``--observations``), so the three estimators are compared on one set of observations; Sim
and Seq-R once more with the other camera model (fixed if the flight self-calibrates, else
self-calibrated), for what self-calibration changes (issue 17); the COLMAP reference
(``seqat reference`` of the Sim run) on the same tie points.
Reported: tracks (count, lengths), image residuals, σ0, per-image latency (read, detect,
match, AT) and the differences Seq-R − Sim and Seq-F − Sim of the camera positions and
attitudes. Written to ``OUT/bench_flight.json`` and ``OUT/latency.png``; the numbers go to
docs/benchmarks.md by hand (with the machine and the date, as every benchmark there).
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.bench.common import load_average, machine  # noqa: E402
from pipeline.bench.report import Machine  # noqa: E402
from pipeline.common.atomic import atomic_write_text
from pipeline.common.columns import EOP_FILE, OBS_COLUMNS, OBS_FRAME_COLUMN
from pipeline.common.csvio import read_csv  # noqa: E402
from pipeline.common.tables import EopTable, NavTable
from pipeline.report.model import image_residuals_px  # noqa: E402
from pipeline.run.accuracy import eop_differences
from pipeline.run.runner import Method, run_flight  # noqa: E402
from pipeline.run.store import read_eop_csv, read_run, to_jsonable  # noqa: E402
from seqat.types import FloatArray  # noqa: E402


@dataclass(frozen=True, kw_only=True)
class Stats:
    """Median, 95th and 99th percentiles and maximum of a per-image quantity."""

    median: float
    p95: float
    max: float
    p99: float = math.nan

    @classmethod
    def of(cls, values: list[float] | FloatArray) -> Stats:
        v = np.asarray(values, dtype=np.float64)
        v = v[np.isfinite(v)]
        if v.size == 0:
            return cls(median=math.nan, p95=math.nan, max=math.nan)
        return cls(median=float(np.median(v)), p95=float(np.percentile(v, 95)),
                   p99=float(np.percentile(v, 99)), max=float(v.max()))


@dataclass(frozen=True, kw_only=True)
class Difference:
    """RMS and maximum per component of ``a - b`` over the common images."""

    pos_rms_m: tuple[float, float, float]
    pos_max_m: tuple[float, float, float]
    att_rms_deg: tuple[float, float, float]
    att_max_deg: tuple[float, float, float]


@dataclass(frozen=True, kw_only=True)
class FlightBench:
    """Everything ``bench_flight.json`` holds."""

    flight: str
    date: str
    machine: Machine
    images: int
    images_with_verified_pair: int
    skipped: int
    tracks: int  # tie points with >= 2 rays
    track_length_median: float
    track_length_mean: float
    track_length_histogram: dict[int, int]
    observations: int
    working_width_px: int
    image_width_px: int
    rms_residual_px: dict[str, float]  # full resolution, per method, every observation
    median_residual_px: dict[str, float]  # of the point's image distance
    sigma0: dict[str, float]
    read_ms: Stats
    detect_ms: Stats
    match_ms: Stats
    tracking_ms: Stats  # detect + match + resection bookkeeping
    at_ms: Stats  # Seq-R update (its image's estimate out)
    #: Seq-R update and the refinement after it (re-linearisation, second start): the
    #: image's whole AT processing
    at_refine_ms: Stats
    latency_ms: Stats  # read + tracking + AT, per image
    seq_r_minus_sim: Difference
    seq_f_minus_sim: Difference
    nav_minus_sim: Difference
    #: The runs above as the flight configures them (a camera from EXIF: self-calibrated);
    #: run.json ``camera_estimate`` of each method (None: camera fixed).
    camera_estimate: dict[str, object]
    #: Sim and Seq-R again on the same tie points with the camera held fixed (or, when the
    #: runs above kept it fixed, self-calibrated): sigma0, Seq-R - Sim, Seq-R update time.
    other_camera: dict[str, object]
    #: The COLMAP reference (``seqat reference`` of the Sim run: the same tie points, the
    #: run's loss): its record's sigma0, loss, iterations and time, or the error it met.
    colmap: dict[str, object]
    colmap_minus_sim: Difference | None
    seq_r_minus_colmap: Difference | None


def _difference(a: EopTable | NavTable, b: EopTable | NavTable) -> Difference:
    """``a - b`` over the images both hold, matched by id
    (:func:`pipeline.run.accuracy.eop_differences`)."""
    _, d_pos, d_att = eop_differences(a.image_ids, a.eop, b.image_ids, b.eop)
    d = np.hstack([d_pos, d_att])
    rms = np.sqrt(np.mean(d**2, axis=0))
    mx = np.max(np.abs(d), axis=0)
    return Difference(pos_rms_m=tuple(rms[:3]), pos_max_m=tuple(mx[:3]),  # type: ignore[arg-type]
                      att_rms_deg=tuple(rms[3:]), att_max_deg=tuple(mx[3:]))  # type: ignore[arg-type]


def _colmap(sim_run: Path) -> tuple[dict[str, object], EopTable | None]:
    """``seqat reference`` of the Sim run: its record and estimates, or the error."""
    from pipeline.reference.stage import run_reference
    from seqat.errors import SeqatError

    try:
        summary = run_reference(sim_run)
    except SeqatError as err:
        return {"error": str(err)}, None
    rec = summary.record
    return ({"sigma0": rec.sigma0, "loss": str(rec.options.robust_loss),
             "loss_scale_sigmas": rec.options.loss_scale_sigmas, "iterations": rec.iterations,
             "ba_s": rec.ba_s, "converged": rec.converged},
            read_eop_csv(summary.reference_dir / EOP_FILE))


def _tracks(obs_path: Path) -> tuple[Counter[str], int]:
    counts: Counter[str] = Counter()
    n = 0
    for row in read_csv(obs_path, OBS_COLUMNS, (OBS_FRAME_COLUMN,)):
        counts[row.ident("point")] += 1
        n += 1
    return counts, n


def _residuals(out: Path) -> tuple[float, float]:
    """RMS and median image residual (px, full resolution) of a run
    (:func:`pipeline.report.model.image_residuals_px`)."""
    res = image_residuals_px(read_run(out))
    if res.size == 0:
        return math.nan, math.nan
    return float(np.sqrt(np.mean(res**2))), float(np.median(np.hypot(res[:, 0], res[:, 1])))


def _plot(path: Path, ids: list[str], parts: dict[str, list[float]]) -> None:
    fig, ax = plt.subplots(figsize=(9, 3.5))
    bottom = np.zeros(len(ids))
    for label, values in parts.items():
        v = np.asarray(values, dtype=np.float64)
        ax.bar(np.arange(len(ids)), v, bottom=bottom, label=label)
        bottom += v
    ax.set_xlabel("image (acquisition order)")
    ax.set_ylabel("ms")
    ax.set_title("Per-image latency: read + detect + match + AT (Seq-R)")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


def run_flight_bench(flight: Path | str, out: Path | str) -> FlightBench:
    """Run the real-flight benchmark (Seq-R tracking, Sim and Seq-F replays) into ``out``."""
    flight, out = Path(flight), Path(out)
    load = load_average()
    runs = {m: out / m.value for m in (Method.SEQ_R, Method.SIM, Method.SEQ_F)}
    run_flight(flight, runs[Method.SEQ_R], method=Method.SEQ_R, progress=True)
    obs = runs[Method.SEQ_R] / "observations.csv"
    for m in (Method.SIM, Method.SEQ_F):  # the first run printed the flight's warnings
        run_flight(flight, runs[m], method=m, observations=obs, progress=True,
                   echo_warnings=False)
    seq_r, sim, seq_f = (read_run(runs[m]) for m in (Method.SEQ_R, Method.SIM, Method.SEQ_F))
    calibrated = seq_r.record.get("camera_estimate") is not None
    other = {m: out / f"{m.value}-{'fixed' if calibrated else 'selfcal'}"
             for m in (Method.SEQ_R, Method.SIM)}
    for m, path in other.items():
        run_flight(flight, path, method=m, observations=obs, progress=True,
                   self_calibration=not calibrated, echo_warnings=False)
    o_seq_r, o_sim = read_run(other[Method.SEQ_R]), read_run(other[Method.SIM])
    colmap, colmap_eop = _colmap(runs[Method.SIM])
    o_at = [float(im["update_ms"]) for im in o_seq_r.record["images"]]  # type: ignore[index]
    other_camera = {
        "self_calibration": not calibrated,
        "sigma0": {r.method: float(r.record["totals"]["sigma0"])  # type: ignore[index]
                   for r in (o_seq_r, o_sim)},
        "seq_r_minus_sim": _difference(o_seq_r.eop, o_sim.eop),
        "at_ms": Stats.of(o_at),
        "camera_estimate": {r.method: r.record.get("camera_estimate") for r in (o_seq_r, o_sim)},
    }
    record = seq_r.record
    images = record["images"]  # type: ignore[index]
    tracking = [im["tracking"] for im in images]  # type: ignore[index]
    counts, n_obs = _tracks(obs)
    lengths = np.array([c for c in counts.values() if c >= 2])
    read_ms = [float(t.get("read_ms", math.nan)) for t in tracking]
    detect = [float(t["detect_ms"]) for t in tracking]
    match = [float(t["match_ms"]) for t in tracking]
    total = [float(t["total_ms"]) for t in tracking]
    at = [float(im["update_ms"]) for im in images]  # type: ignore[index]
    at_refine = [a + float(im.get("refine_ms") or 0.0)  # type: ignore[union-attr]
                 for a, im in zip(at, images, strict=True)]  # type: ignore[arg-type]
    latency = [r + t + a for r, t, a in zip(read_ms, total, at, strict=True)]
    _plot(out / "latency.png", list(seq_r.eop.image_ids),
          {"read": read_ms, "detect": detect, "match": match,
           "other tracking": [t - d - m for t, d, m in zip(total, detect, match, strict=True)],
           "AT update": at})
    residuals = {m: _residuals(runs[m]) for m in runs}
    opts = record.get("tracking_options") or {}  # type: ignore[union-attr]
    bench = FlightBench(
        flight=str(flight), date=time.strftime("%Y-%m-%d"), machine=machine(load),
        images=len(seq_r.eop), skipped=len(seq_r.inputs.skipped),
        images_with_verified_pair=sum(1 for t in tracking if t["pairs_matched"] > 0),
        tracks=int(lengths.size), track_length_median=float(np.median(lengths)),
        track_length_mean=float(np.mean(lengths)),
        track_length_histogram={int(k): int(v) for k, v in
                                sorted(Counter(lengths.tolist()).items())},
        observations=n_obs, working_width_px=int(opts.get("working_width_px", 0)),
        image_width_px=seq_r.camera.width_px,
        rms_residual_px={m.value: residuals[m][0] for m in runs},
        median_residual_px={m.value: residuals[m][1] for m in runs},
        sigma0={r.method: float(r.record["totals"]["sigma0"])  # type: ignore[index]
                for r in (seq_r, sim, seq_f)},
        read_ms=Stats.of(read_ms), detect_ms=Stats.of(detect), match_ms=Stats.of(match),
        tracking_ms=Stats.of(total), at_ms=Stats.of(at),
        at_refine_ms=Stats.of(at_refine), latency_ms=Stats.of(latency),
        seq_r_minus_sim=_difference(seq_r.eop, sim.eop),
        seq_f_minus_sim=_difference(seq_f.eop, sim.eop),
        nav_minus_sim=_difference(seq_r.nav, sim.eop),
        camera_estimate={r.method: r.record.get("camera_estimate") for r in (seq_r, sim, seq_f)},
        other_camera=other_camera,
        colmap=colmap,
        colmap_minus_sim=(None if colmap_eop is None
                          else _difference(colmap_eop, sim.eop)),
        seq_r_minus_colmap=(None if colmap_eop is None
                            else _difference(seq_r.eop, colmap_eop)),
    )
    doc = {"version": 1, **to_jsonable(bench)}  # type: ignore[dict-item]
    atomic_write_text(out / "bench_flight.json",
                      json.dumps(doc, indent=1, allow_nan=False) + "\n")
    return bench
