"""Journal and ``--resume``: a run killed at any point and resumed equals an uninterrupted run.

Kills are simulated in process (a listener raises after image N: the image in flight is
lost, as with kill -9; or the journal write of image N fails between the tracker state file
and its record), followed by a torn journal tail, and once for real (a subprocess killed
with SIGKILL). The kill points are drawn with a fixed seed.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.run import journal as journal_module
from pipeline.run.journal import JOURNAL_DIR, JOURNAL_FILE, read_journal
from pipeline.run.runner import run_flight
from seqat.errors import InputDataError
from seqat.types import Frame, ImageUpdate, Solution

from ..sample_runs import AUTZEN, REPO_ROOT, STRIP, assert_same_results

#: Seed of the kill points.
KILL_SEED = 2026
_rng = np.random.default_rng(KILL_SEED)
STRIP_KILLS = sorted(int(n) for n in _rng.choice(np.arange(1, 61), size=6, replace=False))
AUTZEN_KILLS = sorted(int(n) for n in _rng.choice(np.arange(2, 13), size=4, replace=False))
#: Images in the journal before the subprocess is killed, and the extra delay (s).
SIGKILL_AFTER = int(_rng.integers(15, 45))
SIGKILL_DELAY_S = float(_rng.uniform(0.0, 0.02))
#: A budget every image exceeds: the threshold doubles deterministically to its cap.
ALWAYS_OVER_MS = 1e-6


class Crash(Exception):
    """Stands for a kill -9 in the middle of an image."""


class CrashAt:
    """Listener that kills the run while image ``n`` (1-based) is being adjusted."""

    def __init__(self, n: int) -> None:
        self.n, self.seen = n, 0

    def on_image(self, frame: Frame, update: ImageUpdate, estimator: object) -> None:
        self.seen += 1
        if self.seen == self.n:
            raise Crash

    def on_finish(self, solution: Solution) -> None:
        pass


def _tear(out: Path, rng: np.random.Generator) -> None:
    """Append a torn record: the first bytes of a valid-looking one, no end of line."""
    with (out / JOURNAL_DIR / JOURNAL_FILE).open("ab") as handle:
        handle.write(b'SQJ1 999 0badf00d {"kind":"image","seq":'[: int(rng.integers(1, 40))])


def _crash_and_resume(flight: Path, out: Path, n: int, tear_rng: np.random.Generator | None,
                      **kwargs: object) -> None:
    with pytest.raises(Crash):
        run_flight(flight, out, progress=False, listeners=[CrashAt(n)], **kwargs)  # type: ignore[arg-type]
    if tear_rng is not None:
        _tear(out, tear_rng)
    summary = run_flight(flight, out, progress=False, resume=True, **kwargs)  # type: ignore[arg-type]
    assert summary.replayed == n - 1


@pytest.mark.parametrize("n", STRIP_KILLS)
def test_observations_flight_killed_and_resumed_equals_uninterrupted(
        n: int, strip_run: Path, tmp_path: Path) -> None:
    _crash_and_resume(STRIP, tmp_path / "out", n, np.random.default_rng(n) if n % 2 else None)
    assert_same_results(strip_run, tmp_path / "out")


@pytest.mark.parametrize("n", AUTZEN_KILLS)
def test_image_flight_killed_and_resumed_equals_uninterrupted(
        n: int, autzen_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    _crash_and_resume(AUTZEN, out, n, np.random.default_rng(n))
    assert_same_results(autzen_run, out)
    # the tracker state files left are those of the held images only
    states = sorted((out / JOURNAL_DIR / "tracker").glob("*.npz"))
    assert 1 <= len(states) <= 12


def test_kill_between_tracker_state_and_record(autzen_run: Path, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Image 7's state file is on disk, its record is not: resume from image 6's state."""
    original = journal_module.Journal._append

    def append(self: journal_module.Journal, payload: dict[str, object]) -> None:
        if payload.get("kind") == "image" and payload.get("seq") == 6:
            raise Crash
        original(self, payload)

    out = tmp_path / "out"
    monkeypatch.setattr(journal_module.Journal, "_append", append)
    with pytest.raises(Crash):
        run_flight(AUTZEN, out, progress=False)
    monkeypatch.setattr(journal_module.Journal, "_append", original)
    assert (out / JOURNAL_DIR / "tracker" / "00000006.npz").is_file()
    assert run_flight(AUTZEN, out, progress=False, resume=True).replayed == 6
    assert_same_results(autzen_run, out)


def test_sigkill_of_a_real_run_then_resume(strip_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", "from pipeline.cli import app; app()", "run",
                             str(STRIP), "--out", str(out), "--no-progress"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    log = out / JOURNAL_DIR / JOURNAL_FILE
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        if log.is_file() and log.read_bytes().count(b"\n") > SIGKILL_AFTER:
            break
        time.sleep(0.002)
    time.sleep(SIGKILL_DELAY_S)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "killed before the end of the run"
    assert not (out / "eop.csv").exists()
    summary = run_flight(STRIP, out, progress=False, resume=True)
    assert summary.replayed >= SIGKILL_AFTER
    assert_same_results(strip_run, out)


def test_budget_thresholds_are_journaled_and_replayed(tmp_path: Path) -> None:
    ref, out = tmp_path / "ref", tmp_path / "out"
    run_flight(STRIP, ref, progress=False, budget_ms=ALWAYS_OVER_MS)
    _crash_and_resume(STRIP, out, 13, None, budget_ms=ALWAYS_OVER_MS)
    assert_same_results(ref, out)
    budget = json.loads((out / "run.json").read_text())["latency_budget"]
    steps = [(e["old_threshold"], e["new_threshold"]) for e in budget["events"]]
    assert steps[:3] == [(0.1, 0.2), (0.2, 0.4), (0.4, 0.8)]  # x2 per image up to the cap
    # then the window cap, 0.75 x per image down to its floor; the resumed run (killed at
    # image 13, between the two dials) replays and continues the same decisions
    caps = [e["new_window_cap"] for e in budget["events"][3:]]
    assert caps and caps[-1] == 4 and caps == sorted(caps, reverse=True)
    ref_budget = json.loads((ref / "run.json").read_text())["latency_budget"]
    assert [(e["image"], e["new_threshold"], e["new_window_cap"]) for e in budget["events"]] \
        == [(e["image"], e["new_threshold"], e["new_window_cap"]) for e in ref_budget["events"]]
    assert budget["events"][0]["image"] == "img_0011"  # the first sequential image
    assert budget["events"][0]["reason"] == "over budget"
    assert budget == json.loads((ref / "run.json").read_text())["latency_budget"] | {
        "events": budget["events"]}


def _journal_copy(strip_run: Path, tmp_path: Path) -> tuple[Path, list[bytes]]:
    out = tmp_path / "out"
    shutil.copytree(strip_run / JOURNAL_DIR, out / JOURNAL_DIR)
    path = out / JOURNAL_DIR / JOURNAL_FILE
    return out, path.read_bytes().splitlines(keepends=True)


@pytest.mark.parametrize("damage", ["torn", "checksum", "length"])
def test_a_bad_last_record_is_dropped(damage: str, strip_run: Path, tmp_path: Path) -> None:
    out, lines = _journal_copy(strip_run, tmp_path)
    last = lines[-1]
    bad = {"torn": last[: len(last) // 2],
           "checksum": last[:-3] + (b"0" if last[-3:-2] != b"0" else b"1") + last[-2:],
           "length": last[:-2] + b"\n"}[damage]
    (out / JOURNAL_DIR / JOURNAL_FILE).write_bytes(b"".join(lines[:-1]) + bad)
    contents = read_journal(out)
    assert contents is not None and contents.dropped is not None
    assert len(contents.images) == len(lines) - 2  # header and the bad record
    assert contents.valid_bytes == len(b"".join(lines[:-1]))
    summary = run_flight(STRIP, out, progress=False, resume=True)
    assert summary.replayed == len(lines) - 2
    assert_same_results(strip_run, out)


def test_a_torn_header_is_no_journal(strip_run: Path, tmp_path: Path) -> None:
    out, lines = _journal_copy(strip_run, tmp_path)
    (out / JOURNAL_DIR / JOURNAL_FILE).write_bytes(lines[0][:10])
    assert read_journal(out) is None
    assert run_flight(STRIP, out, progress=False, resume=True).replayed == 0
    assert_same_results(strip_run, out)


def test_a_bad_record_followed_by_good_ones_is_an_error(strip_run: Path, tmp_path: Path) -> None:
    out, lines = _journal_copy(strip_run, tmp_path)
    lines[5] = lines[5].replace(b'"kind":"image"', b'"kind":"imagf"')
    (out / JOURNAL_DIR / JOURNAL_FILE).write_bytes(b"".join(lines))
    with pytest.raises(InputDataError, match=r"record 6 .*checksum mismatch.*damaged"):
        read_journal(out)


def _resume_cli(flight: Path, out: Path, *extra: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["run", str(flight), "--out", str(out), "--no-progress",
                                      "--resume", *extra])
    return result.exit_code, result.stderr


def test_a_journal_of_other_options_or_another_flight_is_refused(strip_run: Path,
                                                                 tmp_path: Path) -> None:
    out, _ = _journal_copy(strip_run, tmp_path)
    code, err = _resume_cli(STRIP, out, "--threshold", "0.2")
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"seqat: error: {out / JOURNAL_DIR / JOURNAL_FILE}: written for "
                          "another flight or other options (options: ")
    other = tmp_path / "other"
    shutil.copytree(STRIP, other)
    code, err = _resume_cli(other, out)
    assert code == 2 and err.count("\n") == 1
    assert "written for another flight or other options (flight: " in err
    code, err = _resume_cli(STRIP, out, "--method", "seq-f")
    assert code == 2 and "(method: \"seq-r\" in the journal, \"seq-f\" now)" in err
    assert not (out / "eop.csv").exists()
