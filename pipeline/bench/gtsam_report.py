"""The tables of ``seqat bench gtsam`` (:mod:`pipeline.bench.gtsam`): the pooled timing and
accuracy summary, and the markdown report written beside the JSON."""

from __future__ import annotations

import math


def _f(v: object, fmt: str = ".2f") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return format(v, fmt)


def summary_table(report: dict) -> list[str]:
    """The pooled timing and accuracy table (markdown lines): one row per method."""
    lines: list[str] = []
    gts = [s["label"] for s in report["summary"] if s["label"].startswith("GTSAM")]
    head = ("| method | n | median | p95 | max | " + " | ".join(f"ratio to {x}" for x in gts)
            + " | CPU median | CPU p95 | " + " | ".join(f"CPU ratio to {x}" for x in gts)
            + " | GTSAM build median | update+build median | σ median | update+σ median | "
            "EOP pos RMSE (m) | "
            "att RMSE (deg) | GP RMSE (m) | failed runs |")
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for s in report["summary"]:
        u = s["update"] or {"n": 0, "median_ms": None, "p95_ms": None, "max_ms": None}
        c = s["cpu"] or {"median_ms": None, "p95_ms": None}
        ratios = " | ".join(_f(s["ratio_to_gtsam_median"][x]) for x in gts)
        ratios += f" | {_f(c['median_ms'])} | {_f(c['p95_ms'])} | " + " | ".join(
            _f(s["cpu_ratio_to_gtsam_median"][x]) for x in gts)
        b = s["build"]["median_ms"] if s["build"] else None
        t = s["update_plus_build"]["median_ms"] if s["update_plus_build"] else None
        sg = s.get("sigma")
        us = s.get("update_plus_sigma")
        a = s["accuracy_mean_over_seeds"]
        lines.append(f"| {s['label']} | {u['n'] or '–'} | {_f(u['median_ms'])} | "
                     f"{_f(u['p95_ms'])} | {_f(u['max_ms'])} | {ratios} | {_f(b)} | {_f(t)} | "
                     f"{_f(sg['median_ms'] if sg else None)} | "
                     f"{_f(us['median_ms'] if us else None)} | "
                     f"{_f(a['pos_rmse_m'], '.3f')} | {_f(a['att_rmse_deg'], '.4f')} | "
                     f"{_f(a['gp_rmse_m'], '.3f')} | {s['failures']} |")
    return lines


def render_markdown(report: dict) -> str:
    """Tables of the report: pooled timing with ratios, then accuracy per seed."""
    m = report["machine"]
    g = report["gtsam"]
    conv = report["conversion_check_noise_free_seed0"]
    lines = [
        "# GTSAM IncrementalFixedLagSmoother vs Seq-R (same run)",
        "",
        f"Config `{report['config_path']}`, seeds {report['seeds']}, lags (images) "
        f"{report['lag_images']}; {report['date_utc']}; {m['cpu_model']} ({m['cpu_count']} "
        f"CPUs), load average 1 min {_f(m['load_average_1m'])} at start, "
        f"{_f(m['load_average_1m_end'])} at end ({report['uptime']}); gtsam {g['version']} "
        f"(`{g['smoother']}`; TBB/OpenMP libraries: {g['thread_libraries'] or 'none'}), "
        f"numpy {m['numpy']}, Python {report['python']}. Run time {report['runtime_s']:.0f} s.",
        "",
        f"Pose conversion check (noise-free copy of seed {report['seeds'][0]}'s strip, every "
        f"observation): PinholeCameraCal3_S2 vs observed uv max "
        f"{conv['max_px_vs_observed']:.1e} px, vs seqat.geometry.project max "
        f"{conv['max_px_vs_seqat_project']:.1e} px.",
        "",
        "Per-image time (ms), pooled over seeds, on Seq-R's timed images (its sequential "
        "stage). GTSAM `update` = `smoother.update(...)` only; `build` = that image's factors, "
        "values, timestamps and triangulations; `σ` (runs marked *+ σ*) = the "
        "`marginalCovariance` calls after the update for what Seq-R publishes after each image "
        "(the new pose's sigmas; with *landmarks*, every landmark's too). Ratio = the row's "
        "median update time over that GTSAM run's median update time (*+ σ* runs: update + σ "
        "per image, in the row and as the reference). *CPU* = process CPU time of Seq-R's "
        "whole `add_frame` (the published sigmas included) and of GTSAM's `update` call (and "
        "its σ): on a shared machine the wall clock "
        "also counts the time the process waited for a core. Accuracy: mean over seeds of the "
        "RMSE against truth (r.m.s. over the three components). The machine is shared: only "
        "ratios within this run count.",
        "",
        *summary_table(report),
    ]
    lines += [
        "",
        "Accuracy against truth (final estimates: Seq-R real time = departure values; GTSAM = "
        "last estimate of each key before it was marginalised, the rest from the final "
        "`calculateEstimate()`). RMSE = r.m.s. over the three components.",
        "",
        "| seed | method | median ms | EOP pos RMSE (m) | att RMSE (deg) | GP RMSE (m) | "
        "GP RMSE common GPs (m) | images | GPs (common) | notes |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["results"]:
        for x in r["methods"]:
            a = x["accuracy"]
            e = x["extra"]
            notes = []
            if x["failure"]:
                f = x["failure"]
                notes.append(f"FAILED at image {f['image']}: {f['type']}")
            if "window_images_median" in e:
                notes.append(f"window median {_f(e['window_images_median'], '.0f')} images")
            if "landmarks_entered" in e:
                notes.append(f"{e['obs_dropped_departed']} obs dropped, "
                             f"{e['triangulation_failed']} triangulations failed, "
                             f"prior {'/'.join(e['prior_noise_models'])} "
                             f"(max corr {e['prior_max_correlation']:.1e}), "
                             f"process threads {e['threads_before']} -> {e['threads_max']}, "
                             f"calculateEstimate median "
                             f"{_f(e['calculate_estimate_ms']['median_ms'])} ms")
            med = x["update"]["median_ms"] if x["update"] else None
            lines.append(
                f"| {r['seed']} | {x['label']} | {_f(med)} | {_f(a['pos_rmse_m'], '.3f')} | "
                f"{_f(a['att_rmse_deg'], '.4f')} | {_f(a['gp_rmse_m'], '.3f')} | "
                f"{_f(a['gp_rmse_common_m'], '.3f')} | {a['n_images']} | "
                f"{a['n_points']} ({a['n_points_common']}) | {'; '.join(notes)} |"
            )
    return "\n".join(lines) + "\n"
