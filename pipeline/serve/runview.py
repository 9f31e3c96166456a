"""What ``seqat serve`` shows of a run folder, read at the time of each request.

A finished run has ``run.json``, ``eop.csv`` and ``points.csv`` (published together); a live
run (``seqat run`` / ``watch`` still going) has its journal (``journal/journal.log``, one
record per adjusted image) and, with ``--ortho``, the per-image orthos; a live ``seqat
watch`` also replaces ``live/estimates.json`` (every camera and ground point at its current
estimate with σ, :mod:`pipeline.run.live_view`) after each image, which is read instead of
the journal when it is there. Everything here reads what exists and never fails on a file that
is missing, being replaced or damaged: the status says so in ``warnings`` instead. Nothing
is ever written.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np
import pyproj

from pipeline.common.columns import (
    EOP_FILE,
    LIVE_DIR,
    LIVE_ESTIMATES_FILE,
    LIVE_MOSAIC_INDEX,
    POINTS_FILE,
    RUN_FILE,
)
from pipeline.common.outdir import LEGACY_RUN_MARKERS, RUN_MARKER
from pipeline.run.journal import JOURNAL_DIR, JOURNAL_FILE, read_journal
from pipeline.run.live_view import is_estimates
from pipeline.run.store import read_eop_csv, read_json_object, read_points_csv
from pipeline.serve import live as shapes
from seqat.errors import InputDataError

ORTHO_JSON = "ortho.json"
MOSAIC_FILE = "mosaic.tif"
#: At most this many tie points go to the page (an even subsample of ``points.csv``).
MAX_POINTS = 5000

T = TypeVar("T")


def check_run_folder(out: Path) -> None:
    """``out`` is a run folder of seqat (its marker, ``run.json`` or a journal).

    Raises
    ------
    InputDataError
        Naming ``out``.
    """
    if not out.exists():
        raise InputDataError(f"{out}: no such run folder")
    if not out.is_dir():
        raise InputDataError(f"{out}: not a folder; seqat serve shows a run folder "
                             "(seqat run ... --out OUT)")
    if not any((out / m).is_file() for m in (RUN_MARKER, *LEGACY_RUN_MARKERS)):
        raise InputDataError(f"{out}: not a seqat run folder (no {RUN_MARKER}, {RUN_FILE} or "
                             f"{JOURNAL_DIR}/{JOURNAL_FILE})")


def _stat_key(path: Path) -> tuple[int, int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_mtime_ns, st.st_size)


def _finite(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _sigma_norm(sigma: np.ndarray) -> list[float | None]:
    """√(σx² + σy² + σz²) per row, None where a σ is missing."""
    with np.errstate(invalid="ignore"):
        return _nullable(np.sqrt(np.sum(np.square(sigma), axis=1)))


def _nullable(values: np.ndarray) -> list[float | None]:
    """``values`` as a list, None where not finite."""
    finite = np.isfinite(values)
    if finite.all():
        return values.tolist()  # type: ignore[no-any-return]
    return np.where(finite, values, None).tolist()  # type: ignore[no-any-return]


def _opt(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


@dataclass(frozen=True, eq=False)
class Table:
    """Cameras or ground points from ``eop.csv`` / ``points.csv`` or ``estimates.json``:
    ids, values (n, 6 or 3), σ (same shape), the CRS's WKT and extra properties per row."""

    ids: list[str]
    values: np.ndarray
    sigma: np.ndarray
    crs_wkt: str
    extra: list[dict[str, object]]
    key: object


@dataclass(frozen=True, eq=False)
class LiveEstimatesView:
    """``live/estimates.json`` parsed."""

    doc: dict[str, object]
    cameras: Table
    points: Table


def _parse_estimates(doc: dict[str, object], key: object) -> LiveEstimatesView:
    """Raises KeyError, TypeError or ValueError on a malformed file."""
    if not is_estimates(doc):
        raise ValueError("not a seqat live estimates file")
    crs = str(doc["crs"])
    cams = doc["cameras"]
    assert isinstance(cams, list)

    def arr(rows: object, width: int) -> np.ndarray:
        # numpy reads JSON's null as NaN; ragged or non-numeric rows raise ValueError
        return np.array(rows, dtype=np.float64).reshape(-1, width)

    cameras = Table(ids=[str(c["image"]) for c in cams], values=arr([c["eop"] for c in cams], 6),
                    sigma=arr([c["sigma"] for c in cams], 6), crs_wkt=crs,
                    extra=[{"in_window": bool(c.get("in_window")),
                            "at_unix_s": c.get("at_unix_s")} for c in cams], key=key)
    pts = doc["points"]
    assert isinstance(pts, dict)
    points = Table(ids=[str(i) for i in pts["point"]], values=arr(pts["xyz_m"], 3),
                   sigma=arr(pts["sigma_m"], 3), crs_wkt=crs,
                   extra=[{"n_obs": int(n)} for n in pts["n_obs"]], key=key)
    if not (len(points.ids) == len(points.values) == len(points.sigma) == len(points.extra)):
        raise ValueError("points: columns of different lengths")
    return LiveEstimatesView(doc=doc, cameras=cameras, points=points)


@dataclass(frozen=True)
class JournalView:
    """The journal's images: ``live`` records, ids, nav positions (working CRS) and the
    working CRS when the journal records it (``seqat watch``'s ``setup`` record)."""

    live: list[Mapping[str, object]] = field(default_factory=list)
    image_ids: list[str] = field(default_factory=list)
    nav_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    crs_wkt: str | None = None
    warning: str | None = None


class RunView:
    """The run folder ``out`` as the page sees it; parsed files are cached per file version
    (inode, mtime, size), so polling costs a ``stat`` per file while nothing changes."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[object, object]] = {}
        self._loading: dict[str, threading.RLock] = {}

    def _cached(self, name: str, key: object, load: Callable[[], T]) -> T:
        """``load()``'s value for this version ``key`` of its source; one thread loads it
        while the others asking for it wait (pages ask together after a change)."""
        with self._lock:
            hit = self._cache.get(name)
            if hit is not None and hit[0] == key:
                return hit[1]  # type: ignore[return-value]
            loading = self._loading.setdefault(name, threading.RLock())
        with loading:
            with self._lock:
                hit = self._cache.get(name)
                if hit is not None and hit[0] == key:
                    return hit[1]  # type: ignore[return-value]
            value = load()
            with self._lock:
                self._cache[name] = (key, value)
        return value

    def _json(self, name: str) -> tuple[dict[str, object] | None, str | None]:
        """A JSON file of the folder, or None and why not (None: absent)."""
        path = self.out / name
        key = _stat_key(path)
        if key is None:
            return None, None

        def load() -> tuple[dict[str, object] | None, str | None]:
            try:
                return read_json_object(path), None
            except InputDataError as err:
                return None, str(err)

        return self._cached(name, key, load)

    def _journal(self) -> JournalView:
        """What the journal says of the images adjusted so far."""
        path = self.out / JOURNAL_DIR / JOURNAL_FILE
        key = _stat_key(path)
        if key is None:
            return JournalView()

        def load() -> JournalView:
            try:
                contents = read_journal(self.out)
            except InputDataError as err:
                return JournalView(warning=str(err))
            if contents is None:
                return JournalView()
            setup_crs = None if contents.setup is None else contents.setup.get("crs")
            return JournalView(
                live=[dict(r.live) for r in contents.images],
                image_ids=[r.frame.image_id for r in contents.images],
                nav_xyz=np.array([r.frame.nav_eop[:3] for r in contents.images],
                                 float).reshape(-1, 3),
                crs_wkt=None if setup_crs is None else str(setup_crs))

        return self._cached("journal", key, load)

    def _estimates(self) -> tuple[LiveEstimatesView | None, str | None]:
        """``live/estimates.json`` of a live watch, or None and why not (None: absent)."""
        path = self.out / LIVE_DIR / LIVE_ESTIMATES_FILE
        key = _stat_key(path)
        if key is None:
            return None, None

        def load() -> tuple[LiveEstimatesView | None, str | None]:
            try:
                return _parse_estimates(read_json_object(path), key), None
            except InputDataError as err:
                return None, str(err)
            except (KeyError, TypeError, ValueError, AssertionError) as err:
                return None, f"{LIVE_DIR}/{LIVE_ESTIMATES_FILE}: cannot read: {err}"

        return self._cached("estimates", key, load)

    def _live_mosaic(self) -> dict[str, object] | None:
        """``live/mosaic.json`` (the live ortho's index), None when absent or unreadable."""
        doc, _ = self._json(f"{LIVE_DIR}/{LIVE_MOSAIC_INDEX}")
        return doc

    def _camera_table(self) -> tuple[Table | None, str]:
        """The estimated cameras: the published ``eop.csv`` when the run is done, else the
        live estimates; and which (``final`` / ``live``)."""
        if self.is_done():
            run, _ = self._json(RUN_FILE)
            path = self.out / EOP_FILE
            key = (_stat_key(path), _stat_key(self.out / RUN_FILE))
            if run is None or key[0] is None:
                return None, "final"

            def load() -> Table | None:
                try:
                    t = read_eop_csv(path)
                except InputDataError:
                    return None
                return Table(ids=list(t.image_ids), values=t.eop, sigma=t.sigma,
                             crs_wkt=str(run.get("crs")), extra=[{}] * len(t.image_ids),
                             key=key)

            return self._cached("eop_table", key, load), "final"
        est, _ = self._estimates()
        return (None if est is None else est.cameras), "live"

    def _point_table(self) -> Table | None:
        """The ground points: ``points.csv`` when the run is done, else the live estimates."""
        if self.is_done():
            run, _ = self._json(RUN_FILE)
            path = self.out / POINTS_FILE
            key = (_stat_key(path), _stat_key(self.out / RUN_FILE))
            if run is None or key[0] is None:
                return None

            def load() -> Table | None:
                try:
                    t = read_points_csv(path)
                except InputDataError:
                    return None
                return Table(ids=list(t.point_ids), values=t.xyz_m, sigma=t.sigma_m,
                             crs_wkt=str(run.get("crs")),
                             extra=[{"n_obs": int(n)} for n in t.n_obs], key=key)

            return self._cached("points_table", key, load)
        est, _ = self._estimates()
        return None if est is None else est.points

    def stop_sigma_m(self, override_cm: float | None = None) -> float | None:
        """The stop criterion: ``override_cm`` (the page's field), else the run's
        ``--stop-sigma-cm`` (in ``live/estimates.json``)."""
        if override_cm is not None:
            return override_cm / 100.0
        est, _ = self._estimates()
        value = None if est is None else _finite(est.doc.get("stop_sigma_m"))
        return value if value is not None and value > 0 else None

    def _crs_transformer(self, wkt: str) -> pyproj.Transformer:
        return self._cached("transformer", wkt, lambda: pyproj.Transformer.from_crs(
            pyproj.CRS.from_wkt(wkt), "EPSG:4326", always_xy=True))

    def is_done(self) -> bool:
        """``run.json`` is there, complete, and no newer journal says a new run started."""
        run, _ = self._json(RUN_FILE)
        if run is None or not isinstance(run.get("totals"), dict):
            return False
        run_key = _stat_key(self.out / RUN_FILE)
        journal_key = _stat_key(self.out / JOURNAL_DIR / JOURNAL_FILE)
        return run_key is not None and (journal_key is None or journal_key[1] <= run_key[1])

    def status(self, mosaic: Mapping[str, object] | None,
               mosaic_error: str | None = None,
               stop_sigma_cm: float | None = None) -> dict[str, object]:
        """``status.json`` (docs/formats.md, *seqat serve*); ``mosaic``: its
        :class:`~pipeline.serve.tiles.MosaicInfo` as a dict, ``mosaic_error``: why it cannot
        be read; ``stop_sigma_cm``: the page's stop criterion instead of the run's."""
        warnings: list[str] = []
        run, run_err = self._json(RUN_FILE)
        ortho, ortho_err = self._json(ORTHO_JSON)
        est, est_err = self._estimates()
        done = self.is_done()
        # the journal is parsed whole when it changes: only while nothing else tells
        journal = self._journal() if est is None and not done else JournalView()
        live_mosaic = self._live_mosaic()
        warnings += [w for w in (run_err, ortho_err, journal.warning) if w]
        if not done and est_err:
            warnings.append(est_err)
        cameras = self.cameras()
        record: Mapping[str, object] | None = None
        images = 0
        last_image = None
        if done and run is not None:
            totals = run["totals"]
            images_doc = run.get("images")
            if isinstance(images_doc, list) and images_doc and isinstance(images_doc[-1], dict):
                record = images_doc[-1].get("live")  # type: ignore[assignment]
                last_image = images_doc[-1].get("image_id")
            images = int(totals.get("images", 0))  # type: ignore[union-attr]
            sigma0 = _finite(totals.get("sigma0"))  # type: ignore[union-attr]
            warnings += [str(w) for w in run.get("warnings", []) or []]  # type: ignore[union-attr]
        elif est is not None:
            images = int(est.doc.get("images", 0))  # type: ignore[call-overload]
            last = est.doc.get("last")
            record = last if isinstance(last, dict) else None
            last_image = None if record is None else record.get("image")
            sigma0 = _finite(est.doc.get("sigma0"))
        else:
            images = len(journal.live)
            last_image = journal.image_ids[-1] if journal.image_ids else None
            record = journal.live[-1] if journal.live else None
            sigma0 = None if record is None else _finite(record.get("sigma0"))
            if images == 0:
                warnings.append("no image adjusted yet")
        latency_ms, latency_kind = None, None
        stages: dict[str, float | None] = {"tracking": None, "at": None, "ortho": None}
        if isinstance(record, Mapping):
            for kind in ("latency_ms", "processing_ms"):
                latency_ms = _finite(record.get(kind))
                if latency_ms is not None:
                    latency_kind = kind
                    break
            stages["tracking"] = _finite(record.get("prep_ms"))
            stages["at"] = _finite(record.get("update_ms"))
        ortho_latency = None
        mosaic_images = 0
        if ortho is not None:
            rows = ortho.get("images")
            if isinstance(rows, list) and rows and isinstance(rows[-1], dict):
                ortho_latency = _finite(rows[-1].get("latency_ms"))
                mosaic_images = len(rows)
            warnings += [str(w) for w in ortho.get("warnings", []) or []]  # type: ignore[union-attr]
        elif live_mosaic is not None:
            rows = live_mosaic.get("images")
            if isinstance(rows, list) and rows and isinstance(rows[-1], dict):
                ortho_latency = _finite(rows[-1].get("ortho_ms"))
                mosaic_images = len(rows)
        stages["ortho"] = ortho_latency
        if mosaic_error is not None:
            warnings.append(mosaic_error)
        elif mosaic is None:
            warnings.append(f"no {MOSAIC_FILE}" if done else f"no {MOSAIC_FILE} yet")
        points = self._point_table()
        stop = None
        stop_m = self.stop_sigma_m(stop_sigma_cm)
        if stop_m is not None:
            stop = self._cached("stop", (None if points is None else points.key, stop_m),
                                lambda: shapes.stop_summary(
                                    points.sigma if points else np.zeros((0, 3)),
                                    points.values if points else np.zeros((0, 3)), stop_m))
        versions = [mosaic["version"] if mosaic else "-"] + [
            "-" if k is None else f"{k[1]}-{k[2]}" for k in (
                _stat_key(self.out / n) for n in (RUN_FILE, EOP_FILE, POINTS_FILE, ORTHO_JSON,
                                                  f"{LIVE_DIR}/{LIVE_ESTIMATES_FILE}"))]
        return {
            "run": self.out.name,
            "method": None if run is None else run.get("method"),
            "crs_name": run.get("crs_name") if run is not None else (
                None if est is None else self._crs_name(est.cameras.crs_wkt)),
            "done": done,
            "images": images,
            "last_image": last_image,
            "cameras": len(cameras["features"]),  # type: ignore[arg-type]
            "cameras_position": cameras.get("position"),
            "points": 0 if points is None else len(points.ids),
            "sigma0": sigma0,
            "last_latency_ms": latency_ms,
            "last_latency_kind": latency_kind,
            "last_mosaic_latency_ms": ortho_latency,
            "latency_ms": stages,
            "mosaic_images": mosaic_images,
            "stop": stop,
            "mosaic": mosaic,
            "warnings": warnings,
            "version": f"{images}:" + ":".join(versions),
        }

    def _crs_name(self, wkt: str) -> str | None:
        def load() -> str | None:
            try:
                return str(pyproj.CRS.from_wkt(wkt).name)
            except pyproj.exceptions.CRSError:
                return None

        return self._cached("crs_name", wkt, load)

    def _table_transformer(self, table: Table) -> pyproj.Transformer | None:
        try:
            return self._crs_transformer(table.crs_wkt)
        except pyproj.exceptions.CRSError:
            return None

    def cameras(self) -> dict[str, object]:
        """The estimated cameras in WGS 84 with their posterior σ: ``eop.csv`` of a finished
        run, ``live/estimates.json`` of a live watch; before either, the journal's images at
        their nav position (a journal with its CRS: ``seqat watch``); else none.
        ``position``: ``final``, ``live`` or ``nav``."""
        table, kind = self._camera_table()
        if table is None:
            journal = self._journal()
            if not self.is_done() and journal.crs_wkt is not None and journal.image_ids:
                return self._live_cameras(journal)
            return {"type": "FeatureCollection", "features": [], "position": None}

        def load() -> dict[str, object]:
            transformer = self._table_transformer(table)
            if transformer is None:
                return {"type": "FeatureCollection", "features": [], "position": kind}
            lon, lat = transformer.transform(table.values[:, 0], table.values[:, 1])
            deg = np.degrees(table.values[:, 3:6])
            sdeg = np.degrees(table.sigma[:, 3:6])
            sigma_pos = _sigma_norm(table.sigma[:, :3])
            features = []
            for i, image in enumerate(table.ids):
                if not (np.isfinite(lon[i]) and np.isfinite(lat[i])):
                    continue
                props: dict[str, object] = {"image": image, "position": "estimate",
                                            "estimate": kind,
                                            "sigma_position_m": sigma_pos[i], **table.extra[i]}
                for j, name in enumerate(("x_m", "y_m", "z_m")):
                    props[name] = float(table.values[i, j])
                for j, name in enumerate(("omega_deg", "phi_deg", "kappa_deg")):
                    props[name] = _opt(deg[i, j])
                for j, name in enumerate(("sx_m", "sy_m", "sz_m")):
                    props[name] = _opt(table.sigma[i, j])
                for j, name in enumerate(("somega_deg", "sphi_deg", "skappa_deg")):
                    props[name] = _opt(sdeg[i, j])
                features.append({"type": "Feature", "properties": props, "geometry": {
                    "type": "Point", "coordinates": [float(lon[i]), float(lat[i])]}})
            return {"type": "FeatureCollection", "features": features, "position": kind}

        return self._cached("cameras", (table.key, kind), load)

    def ellipses(self) -> dict[str, object]:
        """Error ellipses (σ_E, σ_N, enlarged) of the estimated cameras
        (:func:`pipeline.serve.live.ellipses`)."""
        table, kind = self._camera_table()
        if table is None:
            return {"type": "FeatureCollection", "features": [], "scale": None}

        def load() -> dict[str, object]:
            transformer = self._table_transformer(table)
            if transformer is None:
                return {"type": "FeatureCollection", "features": [], "scale": None}
            return shapes.ellipses(transformer, table.ids, table.values[:, :2],
                                   table.sigma[:, :2])

        return self._cached("ellipses", (table.key, kind), load)

    def footprints(self) -> dict[str, object]:
        """The live cameras' footprints (``live/estimates.json``; kept after the run)."""
        est, _ = self._estimates()
        if est is None:
            return {"type": "FeatureCollection", "features": []}

        in_mosaic = self.mosaic_image_ids()

        def load() -> dict[str, object]:
            transformer = self._table_transformer(est.cameras)
            if transformer is None:
                return {"type": "FeatureCollection", "features": []}
            return shapes.footprints(transformer, est.doc["cameras"],  # type: ignore[arg-type]
                                     in_mosaic)

        return self._cached("footprints", (est.cameras.key, in_mosaic), load)

    def mosaic_image_ids(self) -> frozenset[str]:
        """The images the mosaic shows: ``ortho.json``'s once the run's ortho is published,
        else those of the live mosaic's index (announced with their web tiles)."""
        for doc in (self._json(ORTHO_JSON)[0], self._live_mosaic()):
            rows = None if doc is None else doc.get("images")
            if isinstance(rows, list):
                return frozenset(str(r.get("image")) for r in rows
                                 if isinstance(r, dict) and r.get("image") is not None)
        return frozenset()

    def coverage(self, stop_sigma_cm: float | None = None) -> dict[str, object]:
        """Coverage cells of the stop criterion, done / not yet done."""
        table = self._point_table()
        stop_m = self.stop_sigma_m(stop_sigma_cm)
        if table is None or stop_m is None:
            return {"type": "FeatureCollection", "features": [],
                    "stop_sigma_cm": None if stop_m is None else stop_m * 100.0}

        def load() -> dict[str, object]:
            transformer = self._table_transformer(table)
            if transformer is None:
                return {"type": "FeatureCollection", "features": []}
            return shapes.coverage(transformer, table.values, table.sigma, stop_m)

        return self._cached("coverage", (table.key, stop_m), load)

    def _live_cameras(self, journal: JournalView) -> dict[str, object]:
        """A live ``seqat watch``: the journal's images at their nav position (the estimate
        is published at the end) with the posterior σ right after their update."""
        try:
            transformer = self._crs_transformer(str(journal.crs_wkt))
        except pyproj.exceptions.CRSError:
            return {"type": "FeatureCollection", "features": []}
        lon, lat = transformer.transform(journal.nav_xyz[:, 0], journal.nav_xyz[:, 1])
        features = []
        for i, image in enumerate(journal.image_ids):
            if not (np.isfinite(lon[i]) and np.isfinite(lat[i])):
                continue  # a GNSS dropout without a start value
            raw = journal.live[i].get("sigma_position_m")
            sigma = np.array(raw if isinstance(raw, list | tuple) and len(raw) == 3
                             else [np.nan] * 3, float)
            props: dict[str, object] = {
                "image": image, "position": "nav",
                "sigma_position_m": _sigma_norm(sigma[None, :])[0],
                "x_m": float(journal.nav_xyz[i, 0]), "y_m": float(journal.nav_xyz[i, 1]),
                "z_m": float(journal.nav_xyz[i, 2]),
                "sx_m": _opt(sigma[0]), "sy_m": _opt(sigma[1]), "sz_m": _opt(sigma[2])}
            features.append({"type": "Feature", "properties": props, "geometry": {
                "type": "Point", "coordinates": [float(lon[i]), float(lat[i])]}})
        return {"type": "FeatureCollection", "features": features}

    def points(self) -> dict[str, object]:
        """The tie points (``points.csv`` of a finished run, ``live/estimates.json`` of a live
        watch) in WGS 84 with σ (``sigma_max_m``: the largest of σX, σY, σZ, which the stop
        criterion compares); at most :data:`MAX_POINTS`, an even subsample (``total`` and
        ``shown`` say how many)."""
        table = self._point_table()
        if table is None:
            return {"type": "FeatureCollection", "features": [], "total": 0, "shown": 0}

        def load() -> dict[str, object]:
            transformer = self._table_transformer(table)
            if transformer is None:
                return {"type": "FeatureCollection", "features": [], "total": 0, "shown": 0}
            total = len(table.ids)
            keep = np.unique(np.linspace(0, total - 1, min(total, MAX_POINTS)).astype(int)) \
                if total else np.zeros(0, int)
            lon, lat = transformer.transform(table.values[keep, 0], table.values[keep, 1])
            sig = table.sigma[keep]
            # plain lists (NaN read as None): no numpy scalar per property
            columns = [_nullable(sig[:, 0]), _nullable(sig[:, 1]), _nullable(sig[:, 2]),
                       _sigma_norm(sig), _nullable(shapes.point_sigma(sig))]
            z = table.values[keep, 2].tolist()
            finite = (np.isfinite(lon) & np.isfinite(lat)).tolist()
            lon, lat = np.asarray(lon).tolist(), np.asarray(lat).tolist()
            features = []
            for k, i in enumerate(keep.tolist()):
                if not finite[k]:
                    continue
                features.append({"type": "Feature", "geometry": {
                    "type": "Point", "coordinates": [lon[k], lat[k]]},
                    "properties": {
                        "point": table.ids[i], "z_m": z[k], "sx_m": columns[0][k],
                        "sy_m": columns[1][k], "sz_m": columns[2][k], "sigma_m": columns[3][k],
                        "sigma_max_m": columns[4][k], **table.extra[i]}})
            return {"type": "FeatureCollection", "features": features, "total": total,
                    "shown": len(features)}

        return self._cached("points", table.key, load)
