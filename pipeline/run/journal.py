"""The run journal ``OUT/journal/``: what a run needs to continue after a crash (``--resume``).

After every image the run appends one record to ``journal.log`` and fsyncs it; an image
flight first writes the tracker's state after that image to ``tracker/NNNNNNNN.npz``
(atomically). A kill at any moment thus loses at most the image in flight: on ``--resume``
the journaled frames are replayed through a fresh estimator (deterministic: the same frames
in the same order, with the same Seq-R thresholds, give the same estimates bit for bit), the
tracker is restored from the last state, and the run goes on with the next image.

``journal.log`` is a sequence of self-delimiting, checksummed lines (docs/formats.md,
*Journal*)::

    SQJ1 <payload bytes> <crc32 of the payload, 8 hex digits> <payload: one JSON object>\\n

The first record is the header (``kind: header``: version and the fingerprint of the flight
and options); then one ``kind: image`` record per image adjusted and, in watch mode, one
``kind: skip`` record per image left out and one ``kind: setup`` record (the working CRS and
the camera, fixed by the first image). A torn or corrupt *last* record (a kill during the
write) is dropped and cut off before appending; a bad record followed by good ones means the
file was damaged otherwise, and is an error. Floats are JSON numbers written with Python's
shortest round-trip representation, so a replayed frame is bit-identical to the original.
"""

from __future__ import annotations

import contextlib
import json
import os
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.common.atomic import fsync_dir
from pipeline.flight.inputs import SkippedImage
from pipeline.run.store import to_jsonable
from pipeline.tracking.records import HeldImage, TrackerState
from seqat.errors import ConfigError, InputDataError
from seqat.types import FloatArray, Frame

#: Folder, record file and tracker-state folder of the journal inside a run folder.
JOURNAL_DIR = "journal"
JOURNAL_FILE = "journal.log"
TRACKER_DIR = "tracker"
#: Layout version (header ``version``). 2: late observations in the image records and the
#: tracker's late emissions in its state files; version 1 journals (none) are still read.
JOURNAL_VERSION = 2
READABLE_VERSIONS = (1, 2)
#: First field of every record line.
MAGIC = b"SQJ1"
#: Digits of the image number in tracker state file names (``tracker/00000012.npz``).
STATE_DIGITS = 8


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class ImageRecord:
    """One adjusted image: the frame as fed to the estimator and what the run kept of it.

    Attributes
    ----------
    seq : int
        0-based position among the journal's image records.
    frame : Frame
        Exactly what :meth:`add_frame` received (frame pixels, initial EOP).
    time_s : float
        Acquisition time of the nav row.
    observed_px : (k, 2) float
        Observed (distorted, full-resolution) pixels of the frame's observations, for the
        run folder's ``observations.csv``.
    late_observed_px : (m, 2) float
        The same for the frame's late observations (of earlier images).
    threshold : float or None
        Seq-R correlation threshold this image was adjusted with (the latency budget may
        change it between images).
    live : Mapping
        Per-image timings and counts (``run.json`` ``images[].live``).
    tracking : Mapping or None
        Tracker statistics (image flights).
    budget_event : Mapping or None
        The threshold change decided after this image, if any.
    tracker_state : bool
        ``tracker/<seq>.npz`` holds the tracker's state after this image.
    """

    seq: int
    frame: Frame
    time_s: float
    observed_px: FloatArray
    threshold: float | None
    live: Mapping[str, object]
    tracking: Mapping[str, object] | None = None
    budget_event: Mapping[str, object] | None = None
    tracker_state: bool = False
    late_observed_px: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True, kw_only=True, eq=False)
class JournalContents:
    """What :func:`read_journal` found.

    Attributes
    ----------
    fingerprint : Mapping
        The header's fingerprint of flight and options.
    images : tuple[ImageRecord, ...]
    skips : tuple[SkippedImage, ...]
    valid_bytes : int
        Length of the good prefix of ``journal.log``.
    dropped : str or None
        Why the last record was dropped (torn or corrupt), or None.
    setup : Mapping or None
        Watch mode: the working CRS and camera, fixed by the first image (``kind: setup``).
    """

    fingerprint: Mapping[str, object]
    images: tuple[ImageRecord, ...]
    skips: tuple[SkippedImage, ...]
    valid_bytes: int
    dropped: str | None = None
    setup: Mapping[str, object] | None = None


def _floats(values: np.ndarray) -> list[object]:
    """JSON numbers; ``inf`` (a GNSS dropout's free nav sigma) and ``nan`` as strings, which
    ``np.asarray(..., dtype=float)`` reads back."""
    a = np.asarray(values, dtype=np.float64)
    out: list[object] = a.tolist()
    if np.all(np.isfinite(a)):
        return out

    def fix(v: object) -> object:
        if isinstance(v, list):
            return [fix(x) for x in v]
        return v if np.isfinite(v) else str(v)  # type: ignore[arg-type]

    return [fix(v) for v in out]


def _image_payload(rec: ImageRecord) -> dict[str, object]:
    f = rec.frame
    return {"kind": "image", "seq": rec.seq, "image": f.image_id, "time_s": rec.time_s,
            "nav_eop": _floats(f.nav_eop), "nav_sigma": _floats(f.nav_sigma),
            "points": list(f.point_ids), "uv_px": _floats(f.uv_px), "sigma_px": f.sigma_px,
            "initial_eop": None if f.initial_eop is None else _floats(f.initial_eop),
            "observed_px": _floats(rec.observed_px), "threshold": rec.threshold,
            "live": to_jsonable(rec.live), "tracking": to_jsonable(rec.tracking),
            "budget_event": to_jsonable(rec.budget_event),
            "tracker_state": rec.tracker_state,
            "late_images": list(f.late_image_ids), "late_points": list(f.late_point_ids),
            "late_uv_px": _floats(f.late_uv_px),
            "late_observed_px": _floats(rec.late_observed_px)}


def _image_record(doc: Mapping[str, object]) -> ImageRecord:
    """Rebuild an image record (raises KeyError, TypeError, ValueError on malformed ones)."""
    init = doc["initial_eop"]
    frame = Frame(image_id=str(doc["image"]), nav_eop=np.asarray(doc["nav_eop"], dtype=float),
                  nav_sigma=np.asarray(doc["nav_sigma"], dtype=float),
                  point_ids=tuple(str(p) for p in doc["points"]),  # type: ignore[attr-defined]
                  uv_px=np.asarray(doc["uv_px"], dtype=float).reshape(-1, 2),
                  sigma_px=float(doc["sigma_px"]),  # type: ignore[arg-type]
                  initial_eop=None if init is None else np.asarray(init, dtype=float),
                  # version 1 records have no late observations
                  late_image_ids=tuple(str(p) for p in doc.get("late_images", ())),  # type: ignore[attr-defined]
                  late_point_ids=tuple(str(p) for p in doc.get("late_points", ())),  # type: ignore[attr-defined]
                  late_uv_px=np.asarray(doc.get("late_uv_px", ()), dtype=float).reshape(-1, 2))
    threshold = doc["threshold"]
    tracking, event = doc["tracking"], doc["budget_event"]
    live = doc["live"]
    if not isinstance(live, dict) or not (tracking is None or isinstance(tracking, dict)) \
            or not (event is None or isinstance(event, dict)):
        raise TypeError("live, tracking and budget_event must be objects")
    return ImageRecord(seq=int(doc["seq"]), frame=frame,  # type: ignore[call-overload]
                       time_s=float(doc["time_s"]),  # type: ignore[arg-type]
                       observed_px=np.asarray(doc["observed_px"], dtype=float).reshape(-1, 2),
                       threshold=None if threshold is None else float(threshold),  # type: ignore[arg-type]
                       live=live, tracking=tracking, budget_event=event,
                       tracker_state=bool(doc["tracker_state"]),
                       late_observed_px=np.asarray(doc.get("late_observed_px", ()),
                                                   dtype=float).reshape(-1, 2))


def encode_record(payload: Mapping[str, object]) -> bytes:
    """One journal line: ``SQJ1 <length> <crc32> <json>\\n``."""
    body = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode("utf-8")
    return b"%s %d %08x %s\n" % (MAGIC, len(body), zlib.crc32(body), body)


def _decode_line(line: bytes) -> dict[str, object] | str:
    """The payload of one line, or why it is not a valid record."""
    if not line.endswith(b"\n"):
        return "torn record (no end of line)"
    parts = line[:-1].split(b" ", 3)
    if len(parts) != 4 or parts[0] != MAGIC:
        return "not a journal record"
    try:
        length, crc = int(parts[1]), int(parts[2], 16)
    except ValueError:
        return "malformed record header"
    body = parts[3]
    if len(body) != length:
        return f"record length {len(body)} bytes, header says {length}"
    if zlib.crc32(body) != crc:
        return "checksum mismatch"
    try:
        doc = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        return f"not JSON: {err}"
    return doc if isinstance(doc, dict) else "not a JSON object"


def read_journal(out_dir: Path | str) -> JournalContents | None:
    """Read ``OUT/journal/journal.log``; None when there is none (or only a torn header).

    Raises
    ------
    InputDataError
        Unreadable file, no valid header, a bad record followed by good ones, a record
        that does not describe a frame, or records out of order.
    """
    path = Path(out_dir) / JOURNAL_DIR / JOURNAL_FILE
    if not path.is_file():
        return None
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputDataError(f"{path}: cannot read: {err.strerror or err}") from err
    lines = data.splitlines(keepends=True)
    docs: list[dict[str, object]] = []
    pos, dropped = 0, None
    for number, line in enumerate(lines, start=1):
        doc = _decode_line(line)
        if isinstance(doc, str):
            if number < len(lines):
                raise InputDataError(f"{path}: record {number} (byte {pos}): {doc}, and "
                                     f"{len(lines) - number} record(s) follow: the journal is "
                                     "damaged; rerun without --resume")
            dropped = f"record {number} (byte {pos}): {doc}"
            break
        docs.append(doc)
        pos += len(line)
    if not docs:
        return None  # killed while the header was written: nothing to resume
    if docs[0].get("kind") != "header":
        raise InputDataError(f"{path}: no valid header record; rerun without --resume")
    header = docs[0]
    if header.get("version") not in READABLE_VERSIONS:
        raise InputDataError(f"{path}: journal version {header.get('version')!r}, this seqat "
                             f"reads {', '.join(map(str, READABLE_VERSIONS))}; rerun without "
                             "--resume")
    images: list[ImageRecord] = []
    skips: list[SkippedImage] = []
    setup: dict[str, object] | None = None
    for number, doc in enumerate(docs[1:], start=2):
        try:
            if doc.get("kind") == "setup":
                setup = doc
            elif doc.get("kind") == "image":
                images.append(_image_record(doc))
                if images[-1].seq != len(images) - 1:
                    raise ValueError(f"image number {images[-1].seq}, expected {len(images) - 1}")
            elif doc.get("kind") == "skip":
                skips.append(SkippedImage(image=str(doc["image"]), reason=str(doc["reason"])))
            else:
                raise ValueError(f"unknown kind {doc.get('kind')!r}")
        except (KeyError, TypeError, ValueError, InputDataError) as err:
            raise InputDataError(f"{path}: record {number}: {err}") from err
    fingerprint = header.get("fingerprint")
    if not isinstance(fingerprint, dict):
        raise InputDataError(f"{path}: header without fingerprint")
    return JournalContents(fingerprint=fingerprint, images=tuple(images), skips=tuple(skips),
                           valid_bytes=pos, dropped=dropped, setup=setup)


def check_fingerprint(contents: JournalContents, fingerprint: Mapping[str, object],
                      out_dir: Path | str) -> None:
    """Refuse a journal written for another flight or other options.

    Raises
    ------
    ConfigError
        Naming the first differing item, e.g. ``method: 'seq-f' in the journal, 'seq-r' now``.
    """
    now = to_jsonable(fingerprint)
    assert isinstance(now, dict)
    for key in sorted(set(now) | set(contents.fingerprint)):
        old, new = contents.fingerprint.get(key), now.get(key)
        if old != new:
            raise ConfigError(
                f"{Path(out_dir) / JOURNAL_DIR / JOURNAL_FILE}: written for another flight or "
                f"other options ({key}: {_short(old)} in the journal, {_short(new)} now); "
                "rerun without --resume to start over")


def _short(value: object, limit: int = 80) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --------------------------------------------------------------------------------------------
# Tracker state files
# --------------------------------------------------------------------------------------------


def state_path(out_dir: Path | str, seq: int) -> Path:
    """``OUT/journal/tracker/<seq>.npz``: the tracker after image ``seq``."""
    return Path(out_dir) / JOURNAL_DIR / TRACKER_DIR / f"{seq:0{STATE_DIGITS}d}.npz"


def _write_state(path: Path, state: TrackerState) -> None:
    """The newest held image's features and the tracker's small mutable state, atomically."""
    newest = state.held[-1]
    assert newest.seq == state.seq - 1, "the state of the image just added"
    tmp = path.with_name(f".{path.name}.tmp")
    origin = np.full(2, np.nan) if state.origin_xy is None else state.origin_xy
    with tmp.open("wb") as handle:
        np.savez(handle, image_id=np.array(newest.image_id), nav_eop=newest.nav_eop,
                 kp_work=newest.kp_work, desc=newest.desc, point_nums=newest.point_nums,
                 counters=np.array([state.seq, state.next_point], dtype=np.int64),
                 origin_xy=origin,
                 held=np.array([[h.seq, h.last_overlap_seq] for h in state.held],
                               dtype=np.int64).reshape(-1, 2),
                 tracks=state.tracks,
                 # the held images' late emissions: their files keep the numbers as added
                 late=np.concatenate([np.column_stack([np.full(len(h.late), h.seq), h.late])
                                      for h in state.held] + [np.zeros((0, 3))]
                                     ).astype(np.int64).reshape(-1, 3))
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def _read_state(out_dir: Path, seq: int) -> TrackerState:
    """The tracker after image ``seq``, from its file and its held images' files."""

    def load(s: int) -> Mapping[str, np.ndarray]:
        path = state_path(out_dir, s)
        try:
            with np.load(path) as npz:
                return {k: npz[k] for k in npz.files}
        except (OSError, ValueError, KeyError) as err:
            raise InputDataError(f"{path}: cannot read the tracker state needed to resume "
                                 f"({err}); rerun without --resume") from err

    last = load(seq)
    late = last.get("late", np.zeros((0, 3), dtype=np.int64))  # version 1: none
    held: list[HeldImage] = []
    for held_seq, last_overlap in last["held"].tolist():
        d = last if held_seq == seq else load(held_seq)
        mine = late[late[:, 0] == held_seq, 1:]
        nums = np.array(d["point_nums"], dtype=np.int64)
        nums[mine[:, 0]] = mine[:, 1]
        held.append(HeldImage(image_id=str(d["image_id"]), seq=held_seq, nav_eop=d["nav_eop"],
                              kp_work=d["kp_work"], desc=d["desc"], point_nums=nums,
                              last_overlap_seq=last_overlap, late=mine.copy()))
    origin = last["origin_xy"]
    n_seq, next_point = last["counters"].tolist()
    return TrackerState(seq=n_seq, next_point=next_point,
                        origin_xy=None if np.isnan(origin).any() else origin,
                        held=tuple(held), tracks=last["tracks"])


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------


class Journal:
    """Appends records to ``OUT/journal/journal.log`` (flush + fsync per record).

    Use :meth:`create` for a new run (an old journal is removed) or :meth:`resume` to
    continue one.
    """

    def __init__(self, out_dir: Path, created: list[Path], valid_bytes: int) -> None:
        self.out_dir = out_dir
        self.folder = out_dir / JOURNAL_DIR
        self._created = created  # folders this journal created, deepest first
        self._path = self.folder / JOURNAL_FILE
        self._handle = self._path.open("r+b" if self._path.exists() else "w+b")
        self._handle.truncate(valid_bytes)  # cut a torn tail off before appending
        self._handle.seek(valid_bytes)
        self._states: set[int] = set()
        state_dir = self.folder / TRACKER_DIR
        if state_dir.is_dir():
            self._states = {int(p.stem) for p in state_dir.glob("*.npz") if p.stem.isdigit()}

    @classmethod
    def create(cls, out_dir: Path | str, fingerprint: Mapping[str, object]) -> Journal:
        """Start a new journal (removing any earlier one) and write its header."""
        out = Path(out_dir)
        if out.exists() and not out.is_dir():
            raise InputDataError(f"{out}: exists and is not a folder")
        created: list[Path] = []
        probe = out / JOURNAL_DIR / TRACKER_DIR
        while not probe.exists():
            created.append(probe)
            probe = probe.parent
        _remove_journal(out)
        (out / JOURNAL_DIR / TRACKER_DIR).mkdir(parents=True, exist_ok=True)
        fsync_dir(out)
        journal = cls(out, created, 0)
        journal._append({"kind": "header", "version": JOURNAL_VERSION,
                         "fingerprint": to_jsonable(fingerprint)})
        return journal

    @classmethod
    def resume(cls, out_dir: Path | str, contents: JournalContents) -> Journal:
        """Continue the journal read as ``contents`` (torn tail cut off)."""
        out = Path(out_dir)
        (out / JOURNAL_DIR / TRACKER_DIR).mkdir(parents=True, exist_ok=True)
        return cls(out, [], contents.valid_bytes)

    def load_tracker_state(self, seq: int) -> TrackerState:
        """The tracker state after image ``seq`` (:func:`read_journal`'s records)."""
        return _read_state(self.out_dir, seq)

    def append_image(self, record: ImageRecord, tracker: TrackerState | None = None) -> None:
        """Journal one image: the tracker state file first, then the record (fsynced).

        Once the record is durable, state files of images the tracker no longer holds go.
        """
        if tracker is not None:
            _write_state(state_path(self.out_dir, record.seq), tracker)
            self._states.add(record.seq)
        self._append(_image_payload(record))
        if tracker is not None:
            keep = {h.seq for h in tracker.held} | {record.seq}
            for seq in sorted(self._states - keep):
                with contextlib.suppress(FileNotFoundError):
                    state_path(self.out_dir, seq).unlink()
                self._states.discard(seq)

    def append_skip(self, skip: SkippedImage) -> None:
        self._append({"kind": "skip", "image": skip.image, "reason": skip.reason})

    def append_setup(self, setup: Mapping[str, object]) -> None:
        """Watch mode: the CRS and camera fixed by the first image (``kind: setup``)."""
        self._append({**setup, "kind": "setup"})

    def _append(self, payload: Mapping[str, object]) -> None:
        self._handle.write(encode_record(payload))
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def close(self) -> None:
        self._handle.close()

    def discard(self) -> None:
        """Remove the journal, and the folders :meth:`create` made (a failed run)."""
        self.close()
        _remove_journal(self.out_dir)
        for folder in self._created:
            with contextlib.suppress(OSError):
                folder.rmdir()


def _remove_journal(out: Path) -> None:
    """Delete a journal's own files (never anything else of the run folder)."""
    folder = out / JOURNAL_DIR
    for path in [*(folder / TRACKER_DIR).glob("*.npz"), *(folder / TRACKER_DIR).glob(".*.tmp"),
                 folder / JOURNAL_FILE]:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def replay_checks(contents: JournalContents, image_ids: Sequence[str],
                  nav_eop: np.ndarray | None, out_dir: Path | str) -> None:
    """The journal's images must be the first images of the flight, with the same nav.

    Raises
    ------
    ConfigError
        Another image at some position, or a changed nav row.
    """
    where = Path(out_dir) / JOURNAL_DIR / JOURNAL_FILE
    if len(contents.images) > len(image_ids):
        raise ConfigError(f"{where}: {len(contents.images)} images journaled but the flight has "
                          f"{len(image_ids)}; rerun without --resume to start over")
    for k, rec in enumerate(contents.images):
        if rec.frame.image_id != image_ids[k]:
            raise ConfigError(f"{where}: image {k + 1} of the journal is "
                              f"{rec.frame.image_id!r}, of the flight {image_ids[k]!r}; rerun "
                              "without --resume to start over")
        if nav_eop is not None and not np.array_equal(rec.frame.nav_eop, nav_eop[k]):
            raise ConfigError(f"{where}: the nav of image {image_ids[k]!r} differs from the "
                              "journal's; rerun without --resume to start over")
