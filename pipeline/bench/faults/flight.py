"""The rendered case of ``seqat bench faults``: faults written into a flight folder and
replayed through ``seqat run`` (:func:`pipeline.run.runner.run_flight`).

Once per benchmark the flight's images are tracked by a clean run (pipeline defaults); its
``observations.csv`` is the input of every variant. A variant writes an observations flight
beside it: ``flight.yaml`` (the flight's camera, CRS and nav settings, ``observations:``),
``nav.csv`` with the jump added or the dropout's value fields emptied (a GNSS dropout as the
pipeline reads it, docs/formats.md), ``observations.csv`` with the blunders, and an options
file (``sequential:`` with the variant's data snooping and the case's ``initial_images``).
The run folder's ``eop.csv``, ``points.csv`` and ``run.json`` (``robustness``) are scored.

Tie points of a tracked flight have no truth of their own: their reference is the
intersection of the *clean* observations with the true EOPs (``truth/eop.csv``), the best any
adjustment of these pixels could do.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from pipeline.bench.faults.cases import SIM, Case, FaultBenchOptions, Outcome, Scenario
from pipeline.common.columns import (
    FLIGHT_YAML,
    NAV_GEODETIC_COLUMNS,
    OBS_COLUMNS,
    OBS_FRAME_COLUMN,
)
from pipeline.common.csvio import format_csv_line, read_csv
from pipeline.common.strict_yaml import load_yaml
from pipeline.flight.folder import read_flight, read_truth
from pipeline.flight.nav_files import NAV_PROJECTED_COLUMNS
from pipeline.run.runner import Method, run_flight
from pipeline.run.store import fmt, read_eop_csv, read_points_csv
from seqat.errors import InputDataError
from seqat.geometry import intersect_rays, project
from seqat.types import FloatArray

#: A track with a ray this far (frame pixels) from its intersection with the true EOPs is a
#: wrong match of the tracker: it has no reference point.
REFERENCE_MAX_PX = 2.0
#: WGS 84 semi-major axis (m) and first eccentricity squared: metres -> degrees of a jump.
WGS84_A_M = 6378137.0
WGS84_E2 = 6.69437999014e-3


def enu_offset_to_geodetic(lat_deg: float, de_m: float, dn_m: float) -> tuple[float, float]:
    """Latitude and longitude change (degrees) of a small east / north offset (metres).

    Radii of curvature of the WGS 84 ellipsoid at ``lat_deg``; good to ~1e-6 relative for
    offsets of metres (the grid / true north difference of the working CRS turns the offset
    by the convergence, which leaves its length unchanged).
    """
    s2 = math.sin(math.radians(lat_deg)) ** 2
    meridian = WGS84_A_M * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5
    normal = WGS84_A_M / math.sqrt(1 - WGS84_E2 * s2)
    return (math.degrees(dn_m / meridian),
            math.degrees(de_m / (normal * math.cos(math.radians(lat_deg)))))


class FolderCase(Case):
    """A flight folder with ``truth/``, tracked once and replayed with faults."""

    def __init__(self, flight_dir: Path, work_dir: Path) -> None:
        self.name = "rendered"
        self._flight_dir, self._work = Path(flight_dir), Path(work_dir)
        flight = read_flight(flight_dir)
        truth = read_truth(flight_dir)
        if truth is None:
            raise InputDataError(f"{flight_dir}: no truth/ folder")
        self._config = load_yaml(Path(flight_dir) / FLIGHT_YAML)
        self._geodetic = flight.config.nav.frame == "geodetic"
        self._nav_columns = NAV_GEODETIC_COLUMNS if self._geodetic else NAV_PROJECTED_COLUMNS
        self._nav_rows = [dict(r.values) for r in read_csv(
            Path(flight_dir) / flight.config.nav.file, self._nav_columns)]
        tracking = self._work / "tracking"
        run_flight(flight_dir, tracking, progress=False)
        self.image_ids = flight.nav.image_ids
        img = flight.nav.index()
        rows = list(read_csv(tracking / "observations.csv", OBS_COLUMNS, (OBS_FRAME_COLUMN,)))
        points: dict[str, int] = {}
        for r in rows:
            points.setdefault(r.values["point"], len(points))
        self.point_ids = tuple(points)
        self.obs_image = np.asarray([img[r.values["image"]] for r in rows], dtype=np.int64)
        self.obs_point = np.asarray([points[r.values["point"]] for r in rows], dtype=np.int64)
        # the frame each row arrived with (late observations), kept in the flight written
        self.obs_frame = tuple(r.values.get(OBS_FRAME_COLUMN, r.values["image"]) for r in rows)
        self.obs_uv = np.asarray([[r.number("x_px"), r.number("y_px")] for r in rows],
                                 dtype=np.float64).reshape(-1, 2)
        self.times_s = flight.nav.times_s
        t_index = truth.eop.index()
        self.truth_eop = np.asarray([truth.eop.eop[t_index[i]] for i in self.image_ids])
        self.width_px = flight.camera_config.width_px
        self.height_px = flight.camera_config.height_px
        self.first_sequential = 0
        # reference tie points: clean pixels intersected with the true EOPs; tracks whose
        # rays miss that point (a wrong match of the tracker) have no reference
        origin = np.round(self.truth_eop[0, :3])
        e = self.truth_eop[self.obs_image].copy()
        e[:, :3] -= origin
        uv = flight.frame_pixels(self.obs_uv)  # the pixels of flight.camera
        m = len(self.point_ids)
        X, _ = intersect_rays(e, uv, self.obs_point, m, flight.camera)
        ok = np.all(np.isfinite(X), axis=1) & (np.bincount(self.obs_point, minlength=m) >= 2)
        miss = np.zeros(m)
        sel = ok[self.obs_point]
        res = np.linalg.norm(project(e[sel], X[self.obs_point[sel]], flight.camera) - uv[sel],
                             axis=1)
        np.maximum.at(miss, self.obs_point[sel], res)
        ok &= miss <= REFERENCE_MAX_PX
        self.truth_xyz = {int(j): X[j] + origin for j in np.flatnonzero(ok)}
        self.mismatched_tracks = int(np.count_nonzero(miss > REFERENCE_MAX_PX))
        self._count = 0

    # ------------------------------------------------------------------ writing a variant
    def _flight_yaml(self) -> str:
        doc = {k: v for k, v in self._config.items()
               if k in ("crs", "camera", "nav", "sigma_image_px")}
        nav = dict(doc.get("nav") or {})  # type: ignore[call-overload]
        nav["file"] = "nav.csv"
        doc["nav"] = nav
        doc["observations"] = "observations.csv"
        return yaml.safe_dump(doc, sort_keys=False)

    def _nav_csv(self, sc: Scenario) -> str:
        lines = [format_csv_line(self._nav_columns)]
        gap = {int(i) for i in sc.gap}
        for i, row in enumerate(self._nav_rows):
            values = dict(row)
            if i in gap:
                for c in self._nav_columns[2:]:
                    values[c] = ""
            elif sc.jump is not None and sc.jump[0] == i:
                d = sc.jump[1]
                if self._geodetic:
                    dlat, dlon = enu_offset_to_geodetic(float(values["lat_deg"]), d[0], d[1])
                    values["lat_deg"] = fmt(float(values["lat_deg"]) + dlat)
                    values["lon_deg"] = fmt(float(values["lon_deg"]) + dlon)
                    values["h_m"] = fmt(float(values["h_m"]) + d[2])
                else:
                    for c, v in zip(("x_m", "y_m", "z_m"), d, strict=True):
                        values[c] = fmt(float(values[c]) + v)
            lines.append(format_csv_line([values[c] for c in self._nav_columns]))
        return "".join(lines)

    def _observations_csv(self, sc: Scenario) -> str:
        lines = [format_csv_line((*OBS_COLUMNS, OBS_FRAME_COLUMN))]
        for q in np.flatnonzero(sc.keep):
            lines.append(format_csv_line([self.image_ids[self.obs_image[q]],
                                          self.point_ids[self.obs_point[q]],
                                          fmt(sc.uv_px[q, 0]), fmt(sc.uv_px[q, 1]),
                                          self.obs_frame[q]]))
        return "".join(lines)

    def _options_yaml(self, sc: Scenario, options: FaultBenchOptions) -> str:
        seq: dict[str, object] = {"correlation_threshold": options.threshold,
                                  "initial_images": options.rendered_initial_images}
        if sc.snooping:
            seq.update(snooping_critical=options.snooping_critical, min_rays=options.min_rays)
        return yaml.safe_dump({"sequential": seq}, sort_keys=False)

    # ------------------------------------------------------------------ running
    def run(self, sc: Scenario, options: FaultBenchOptions,
            tick: Callable[[], None]) -> Outcome:
        self._count += 1
        slug = f"{self._count:03d}_{sc.fault}_{sc.variant}".replace(" ", "_").replace("%", "pc")
        folder, out = self._work / "flights" / slug, self._work / "runs" / slug
        folder.mkdir(parents=True, exist_ok=True)
        (folder / FLIGHT_YAML).write_text(self._flight_yaml(), encoding="utf-8")
        (folder / "nav.csv").write_text(self._nav_csv(sc), encoding="utf-8")
        (folder / "observations.csv").write_text(self._observations_csv(sc), encoding="utf-8")
        (folder / "options.yaml").write_text(self._options_yaml(sc, options), encoding="utf-8")
        method = Method.SIM if sc.variant == SIM else Method.SEQ_R
        run_flight(folder, out, method=method, progress=False,
                   options_path=None if method is Method.SIM else folder / "options.yaml")
        for _ in self.image_ids:
            tick()
        return self._outcome(out, sc)

    def _outcome(self, out: Path, sc: Scenario) -> Outcome:
        img = {iid: i for i, iid in enumerate(self.image_ids)}
        pts = {pid: j for j, pid in enumerate(self.point_ids)}
        eops = read_eop_csv(out / "eop.csv")
        eop = np.full((len(self.image_ids), 6), np.nan)
        for iid, e in zip(eops.image_ids, eops.eop, strict=True):
            eop[img[iid]] = e
        points = read_points_csv(out / "points.csv")
        record = json.loads((out / "run.json").read_text(encoding="utf-8"))
        rob = record.get("robustness") or {}
        ms: FloatArray = np.asarray([u["update_ms"] for u in record["images"]
                                     if u["stage"] in ("sequential", "sim")], dtype=np.float64)
        sigma0 = record["totals"].get("sigma0")
        return Outcome(
            eop=eop, point_index=np.asarray([pts[p] for p in points.point_ids], dtype=np.int64),
            xyz_m=points.xyz_m, sigma0=math.nan if sigma0 is None else float(sigma0),
            sequential_ms=ms,
            rejections=frozenset((img[r["image"]], pts[r["point"]])
                                 for r in rob.get("rejections", ())),
            nav_downweighted=tuple((img[n["image"]], n["group"])
                                   for n in rob.get("nav_downweighted", ())),
            skipped=len(rob.get("dropout_skipped", ())))
