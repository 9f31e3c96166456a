"""Replay a Seq-R run's journal through :class:`seqat.sequential.SequentialAT` in-process
and time every update (``add_frame(refine=False)``: until the image's estimate is out) and
the refinement after it (``refine()``: the drift check, re-linearisation, second start) in
CPU milliseconds (``time.process_time``).

    OPENBLAS_NUM_THREADS=1 python benchmarks/relin_replay.py RUN_DIR FLIGHT_DIR \
        [--sim SIM_RUN_DIR] [--profile N] [--json OUT.json]

``RUN_DIR`` is the output of ``seqat run FLIGHT_DIR --out RUN_DIR`` (default options): its
``journal/`` holds the frames exactly as the estimator took them. The estimator is built
as :func:`pipeline.run.runner.run_flight` builds it (default options, the flight's camera,
self-calibration and ground control), so the replay's estimates equal the run's. Prints
median / p99 / max CPU ms of the sequential updates and of update + refinement, the five
largest (update + refinement) with what they did
(re-linearisation, departures, window size), and with ``--sim`` the difference Seq-R − Sim
of the final EOPs (position m rms, attitude deg rms; ``seqat run --method sim
--observations RUN_DIR/observations.csv``). ``--profile N`` writes cProfile stats of the
N largest updates (a second replay) to ``/tmp/relin_profile_<image>.prof``.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import time
from pathlib import Path

import numpy as np

from pipeline.flight.folder import read_flight, with_self_calibration
from pipeline.run.accuracy import eop_differences
from pipeline.run.journal import read_journal
from pipeline.run.runner import (
    EstimatorConfig,
    Method,
    estimator_options,
    make_estimator,
    with_calibration,
)
from pipeline.run.store import eop_table, read_eop_csv

#: Methods timed inside an update (CPU ms per frame, summed over calls).
PARTS = ("_relinearise", "_select_window", "_insert_late", "_finalise_old", "_prune_dormant",
         "_report")


def build(flight_dir: Path):  # noqa: ANN201
    flight = with_self_calibration(read_flight(flight_dir), None)
    options = estimator_options(Method.SEQ_R, EstimatorConfig())
    options = with_calibration(options, flight.calibration)
    return make_estimator(Method.SEQ_R, flight.camera, options, control=flight.control)


def instrument(est, parts: dict[str, float]) -> None:  # noqa: ANN001
    for name in PARTS:
        fn = getattr(est, name)

        def timed(*a, _fn=fn, _name=name, **k):  # noqa: ANN002, ANN003, ANN202
            t0 = time.process_time()
            try:
                return _fn(*a, **k)
            finally:
                parts[_name] = parts.get(_name, 0.0) + (time.process_time() - t0) * 1e3
        setattr(est, name, timed)


def window_eops(est) -> tuple[tuple[str, ...], np.ndarray]:  # noqa: ANN001
    """The window images' current EOPs (no factorisation: the replay's timing untouched)."""
    w, origin = est._w, est._origin
    if est._initial is not None or origin is None:
        sol = est.solution()
        return tuple(e.image_id for e in sol.eops), np.array([e.eop for e in sol.eops])
    ids, eops = [], []
    for k in w.keys:
        if k[0] == "e":
            val = w.x[w.index(k)].copy()
            val[:3] += origin
            ids.append(est._image_ids[k[1]])
            eops.append(val)
    return tuple(ids), np.array(eops)


def replay(run_dir: Path, flight_dir: Path, profile_images: set[str] | None = None,
           window_sim=None):  # noqa: ANN001, ANN201
    contents = read_journal(run_dir)
    assert contents is not None, f"{run_dir}: no journal"
    est = build(flight_dir)
    parts: dict[str, float] = {}
    instrument(est, parts)
    rows = []
    for rec in contents.images:
        if rec.threshold is not None and rec.threshold != est.options.correlation_threshold:
            est.set_correlation_threshold(rec.threshold)
        parts.clear()
        relin0, skip0 = est.relinearisations, est.relinearisations_skipped
        prof = (cProfile.Profile() if profile_images and rec.frame.image_id in profile_images
                else None)
        t0 = time.process_time()
        if prof is not None:
            prof.enable()
        upd = est.add_frame(rec.frame, refine=False)
        ms = (time.process_time() - t0) * 1e3
        t0 = time.process_time()
        est.refine()
        refine_ms = (time.process_time() - t0) * 1e3
        if prof is not None:
            prof.disable()
        if prof is not None:
            prof.dump_stats(f"/tmp/relin_profile_{rec.frame.image_id}.prof")
        if window_sim is not None:  # the window's EOPs - Sim after this update (m, deg rms)
            ids, eops = window_eops(est)
            _, dp, da = eop_differences(ids, eops, window_sim.image_ids, window_sim.eop)
            window_acc = (float(np.sqrt(np.mean(np.sum(dp**2, axis=1)))),
                          float(np.sqrt(np.mean(np.sum(da**2, axis=1)))))
        rows.append({"image": rec.frame.image_id, "stage": upd.stage, "cpu_ms": ms + refine_ms,
                     "update_cpu_ms": ms, "refine_cpu_ms": refine_ms,
                     "window_minus_sim": window_acc if window_sim is not None else None,
                     "relin": est.relinearisations - relin0,
                     "relin_skipped": est.relinearisations_skipped - skip0,
                     "left": upd.images_left_window, "reopened": upd.reopened,
                     "window_images": upd.window_images, "window_params": upd.window_params,
                     "late": upd.late_used, "drift_px": est._drift_px,
                     "eop": np.asarray(upd.eop.eop, dtype=np.float64).tolist(),
                     "parts": {k: round(v, 1) for k, v in parts.items()}})
    t0 = time.process_time()
    est.finish()
    finish_ms = (time.process_time() - t0) * 1e3
    return est, rows, finish_ms


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("flight_dir", type=Path)
    ap.add_argument("--sim", type=Path)
    ap.add_argument("--profile", type=int, default=0)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--steps", type=int, help="seqat.relinearise.FLIGHT_RELINEARISE_STEPS")
    ap.add_argument("--window-accuracy", action="store_true",
                    help="with --sim: the window's EOPs - Sim after every update")
    a = ap.parse_args()
    if a.steps is not None:
        import seqat.relinearise

        seqat.relinearise.FLIGHT_RELINEARISE_STEPS = a.steps
    sim_eop = read_eop_csv(a.sim / "eop.csv") if a.sim is not None else None
    est, rows, finish_ms = replay(a.run_dir, a.flight_dir,
                                  window_sim=sim_eop if a.window_accuracy else None)
    seq = [r for r in rows if r["stage"] == "sequential"]
    ms = np.array([r["cpu_ms"] for r in seq])
    p50, p99 = np.percentile(ms, [50, 99])
    upd = np.array([r["update_cpu_ms"] for r in seq])
    u50, u99 = np.percentile(upd, [50, 99])
    print(f"images {len(rows)}, sequential {len(seq)}: AT update CPU ms median {u50:.1f}  "
          f"p99 {u99:.1f}  max {upd.max():.1f}; with the refinement after it median "
          f"{p50:.1f}  p99 {p99:.1f}  max {ms.max():.1f}  (finish {finish_ms:.0f} ms, "
          f"re-linearisations {est.relinearisations}, skipped {est.relinearisations_skipped})")
    top = sorted(seq, key=lambda r: -r["cpu_ms"])[:5]
    for r in top:
        print(f"  {r['image']}: {r['cpu_ms']:6.1f} ms (update {r['update_cpu_ms']:6.1f})  "
              f"relin {r['relin']}  left {r['left']}  "
              f"reopened {r['reopened']}  late {r['late']}  window {r['window_images']} img / "
              f"{r['window_params']} par  parts {r['parts']}")
    sol = est.solution()
    eops = eop_table(sol.eops)
    ref = read_eop_csv(a.run_dir / "eop.csv")
    _, dp, da = eop_differences(eops.image_ids, eops.eop, ref.image_ids, ref.eop)
    print(f"replay - run eop.csv: pos max {np.abs(dp).max():.2e} m, "
          f"att max {np.abs(da).max():.2e} deg ({len(eops.image_ids)} images, "
          f"run {len(ref.image_ids)}); sigma0 {sol.sigma0:.4f}")
    out = {"rows": rows, "finish_ms": finish_ms, "median_ms": p50, "p99_ms": p99,
           "max_ms": float(ms.max()), "update_median_ms": u50, "update_p99_ms": u99,
           "update_max_ms": float(upd.max()), "sigma0": sol.sigma0, "images": len(eops.image_ids)}
    if a.sim is not None:
        sim = read_eop_csv(a.sim / "eop.csv")
        _, dp, da = eop_differences(eops.image_ids, eops.eop, sim.image_ids, sim.eop)
        pos = float(np.sqrt(np.mean(np.sum(dp**2, axis=1))))
        att = float(np.sqrt(np.mean(np.sum(da**2, axis=1))))
        prms, arms = np.sqrt(np.mean(dp**2, axis=0)), np.sqrt(np.mean(da**2, axis=0))
        print(f"Seq-R - Sim: position rms per axis {np.round(prms, 4)} m (3-D {pos:.4f}), "
              f"attitude rms per axis {np.round(arms, 4)} deg (3-D {att:.4f})")
        out.update(seq_r_minus_sim_pos_m=prms.tolist(), seq_r_minus_sim_att_deg=arms.tolist())
        # live: each image's EOP as its own update published it
        live = np.array([r["eop"] for r in rows])
        _, dp, da = eop_differences(tuple(r["image"] for r in rows), live, sim.image_ids,
                                    sim.eop)
        lp, la = np.sqrt(np.mean(dp**2, axis=0)), np.sqrt(np.mean(da**2, axis=0))
        print(f"live (at its own update) - Sim: position rms {np.round(lp, 3)} m, "
              f"attitude rms {np.round(la, 3)} deg")
        out.update(live_minus_sim_pos_m=lp.tolist(), live_minus_sim_att_deg=la.tolist())
        if a.window_accuracy:
            acc = np.array([r["window_minus_sim"] for r in seq])
            print(f"window - Sim after each update (3-D rms over the window): position "
                  f"median {np.median(acc[:, 0]):.3f} / max {acc[:, 0].max():.3f} m, attitude "
                  f"median {np.median(acc[:, 1]):.3f} / max {acc[:, 1].max():.3f} deg")
    if a.json is not None:
        a.json.write_text(json.dumps(out, indent=1, default=float))
    if a.profile:
        names = {r["image"] for r in top[:a.profile]}
        replay(a.run_dir, a.flight_dir, names)
        print("profiles:", ", ".join(f"/tmp/relin_profile_{n}.prof" for n in sorted(names)))


if __name__ == "__main__":
    main()
