"""The report's section "Agreement with an independent SfM" (``OUT/reference/sfm/``, written
by ``seqat reference OUT --sfm``): self-contained, so the report can be redesigned around it.
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Mapping
from pathlib import Path

from pipeline.common.columns import REFERENCE_DIR, SFM_DIR
from pipeline.reference.sfm_stage import SFM_JSON, SFM_PLOT

#: Keys of ``sfm.json`` carried into ``report.json`` ``sfm_agreement``.
SUMMARY_KEYS = ("n_images", "n_registered", "unregistered", "n_points",
                "mean_reprojection_px", "mean_track_length", "camera", "run_camera", "note")
METHOD_KEYS = ("label", "n_images", "n_inliers", "scale", "position_rms_m", "position_max_m",
               "position_rms_xyz_m", "attitude_rms_deg", "attitude_max_deg",
               "attitude_rms_opk_deg")


def sfm_dir(run_path: Path) -> Path:
    return run_path / REFERENCE_DIR / SFM_DIR


def read_sfm_agreement(run_path: Path) -> dict[str, object] | None:
    """``report.json`` ``sfm_agreement``: the SfM's figures and each method's agreement, or
    None when the run has no SfM check (or an unreadable one)."""
    path = sfm_dir(run_path) / SFM_JSON
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        summary: dict[str, object] = {k: doc[k] for k in SUMMARY_KEYS}
        summary["methods"] = [{k: m[k] for k in METHOD_KEYS} for m in doc["methods"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    summary["file"] = str(path)
    return summary


def _n(value: object, digits: int) -> str:
    return "-" if value is None else f"{float(value):.{digits}f}"  # type: ignore[arg-type]


def _camera(cam: Mapping[str, object]) -> str:
    return (f"f {_n(cam['fx_px'], 1)} / {_n(cam['fy_px'], 1)}, cx {_n(cam['cx_px'], 1)}, "
            f"cy {_n(cam['cy_px'], 1)}, k1 {_n(cam['k1'], 4)}, k2 {_n(cam['k2'], 4)}, "
            f"p1 {_n(cam['p1'], 5)}, p2 {_n(cam['p2'], 5)}")


def sfm_section_html(summary: Mapping[str, object], run_path: Path) -> str:
    """The section: what it is, the SfM's figures, the per-method table and the residual map."""
    rows = [
        ("images registered", f"{summary['n_registered']} of {summary['n_images']}"),
        ("points / mean track length",
         f"{summary['n_points']} / {_n(summary['mean_track_length'], 2)}"),
        ("mean reprojection error (px)", _n(summary["mean_reprojection_px"], 3)),
        ("SfM camera (self-calibrated OPENCV)", _camera(summary["camera"])),  # type: ignore[arg-type]
        ("run camera", _camera(summary["run_camera"])),  # type: ignore[arg-type]
    ]
    parts = ["<h2>Agreement with an independent SfM</h2>",
             "<p class='note'>This is an agreement, not an accuracy: COLMAP's own structure "
             "from motion of the same images (its features, its self-calibrated camera) "
             "aligned to each method by a 7-parameter similarity on the camera centres; "
             "errors both share, or that a similarity absorbs, do not show.</p>",
             "<table><tr><th>SfM</th><th>value</th></tr>"]
    parts += [f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in rows]
    parts.append("</table>")
    head = ["method", "images (in fit)", "scale", "position rms (m)", "max (m)", "X", "Y", "Z",
            "attitude rms (°)", "max (°)", "ω", "φ", "κ"]
    parts.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>")
    for m in summary["methods"]:  # type: ignore[attr-defined]
        cells = [html.escape(str(m["label"])), f"{m['n_images']} ({m['n_inliers']})",
                 _n(m["scale"], 6), _n(m["position_rms_m"], 3), _n(m["position_max_m"], 3),
                 *(_n(v, 3) for v in m["position_rms_xyz_m"]), _n(m["attitude_rms_deg"], 3),
                 _n(m["attitude_max_deg"], 3), *(_n(v, 3) for v in m["attitude_rms_opk_deg"])]
        parts.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    parts.append("</table>")
    png = sfm_dir(run_path) / SFM_PLOT
    if png.is_file():
        data = base64.b64encode(png.read_bytes()).decode("ascii")
        parts.append(f'<img alt="SfM residuals per image" src="data:image/png;base64,{data}">')
    return "".join(parts)
