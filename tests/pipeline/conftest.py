"""Fixtures of the pipeline tests, and the ``shared`` marker.

Tests marked ``shared`` need the shared data folder: ``../shared`` beside the repository (as
CI checks it out) or ``/work/shared``. When neither exists they are skipped, never failed
(the hook below sees every collected test, ``tests/seqat`` included).
"""

from __future__ import annotations

import fcntl
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.simulate.folder import write_simulated_flight
from seqat.simulate import SimulatedFlight, simulate_strip

from .sample_flight import FLIGHT_FILES, SIM_CRS, SIM_SEED, SMALL_SIM, FlightMaker
from .sample_runs import AUTZEN, MINI, MINI_ORTHO_PIXEL_M, STRIP

REPO_ROOT = Path(__file__).resolve().parents[2]
#: Where the shared data folder may be, in order of preference.
SHARED_CANDIDATES = (REPO_ROOT.parent / "shared", Path("/work/shared"))
SHARED_ABSENT = "shared data folder (../shared or /work/shared) is absent"


def shared_dir() -> Path | None:
    """The shared folder (holding ``data/``), or None when it is absent."""
    for candidate in SHARED_CANDIDATES:
        if (candidate / "data").is_dir():
            return candidate
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip every test marked ``shared`` when the shared folder is absent."""
    if shared_dir() is not None:
        return
    skip = pytest.mark.skip(reason=SHARED_ABSENT)
    for item in items:
        if "shared" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``<shared>/data``; skips the test when the shared folder is absent."""
    found = shared_dir()
    if found is None:
        pytest.skip(SHARED_ABSENT)
    return found / "data"


@pytest.fixture
def make_flight(tmp_path: Path) -> FlightMaker:
    """Write the hand-written flight into ``tmp_path/flight``; keyword args replace files.

    ``make_flight(**{"nav.csv": text})`` replaces a file's text; ``None`` omits the file.
    """

    def make(**files: str | None) -> Path:
        folder = tmp_path / "flight"
        folder.mkdir()
        for name, text in {**FLIGHT_FILES, **files}.items():
            if text is not None:
                (folder / name).write_text(text, encoding="utf-8")
        return folder

    return make


@pytest.fixture(scope="session")
def small_sim() -> SimulatedFlight:
    """A seeded simulated strip with exact truth."""
    return simulate_strip(SMALL_SIM, SIM_SEED)


@pytest.fixture(scope="session")
def small_sim_dir(small_sim: SimulatedFlight, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``small_sim`` written as a flight folder (read-only for the tests)."""
    return write_simulated_flight(small_sim, SIM_CRS, tmp_path_factory.mktemp("sim") / "flight")


def built_once(tmp_path_factory: pytest.TempPathFactory, name: str,
               build: Callable[[Path], None]) -> Path:
    """A session fixture's folder ``name``, which ``build(folder)`` fills: once per test
    session, not once per pytest-xdist worker (``make test`` runs two). The first worker
    to ask builds it in the session's shared temporary folder under a lock and marks it
    done; the others wait for the lock and read it. A build that failed leaves no mark,
    and the next worker that asks builds it again (and fails the same way)."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        folder = tmp_path_factory.mktemp(name)
        build(folder)
        return folder
    folder = tmp_path_factory.getbasetemp().parent / f"once-{name}"
    with open(folder.with_name(folder.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (folder / ".built").is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            (folder / ".built").touch()
    return folder


@pytest.fixture(scope="session")
def strip_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``seqat run`` of ``sample_data/strip_demo`` (Seq-R; read-only for the tests)."""
    from pipeline.run.runner import run_flight

    return built_once(tmp_path_factory, "strip_run",
                      lambda root: run_flight(STRIP, root / "out", progress=False)) / "out"


@pytest.fixture(scope="session")
def autzen_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``seqat run`` of ``sample_data/autzen_rendered`` (Seq-R; read-only for the tests)."""
    from pipeline.run.runner import run_flight

    return built_once(tmp_path_factory, "autzen_run",
                      lambda root: run_flight(AUTZEN, root / "out", progress=False)) / "out"


@pytest.fixture(scope="session")
def mini_chain(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``seqat run sample_data/seneca_mini --ortho --ortho-options O --report`` (Seq-R with
    tracking, live ortho on the tie-point plane, report; read-only for the tests). The suite
    tracks these 18 images once: the image-flight, SfM and flight-bench tests read this run
    (``copy_run_files`` gives its plain ``seqat run`` folder)."""
    from typer.testing import CliRunner

    from pipeline.cli import app

    def build(root: Path) -> None:
        options = root / "ortho.yaml"
        options.write_text(f"ortho:\n  pixel_m: {MINI_ORTHO_PIXEL_M}\n", encoding="utf-8")
        result = CliRunner().invoke(app, ["run", str(MINI), "--out", str(root / "out"),
                                          "--no-progress", "--ortho", "--ortho-options",
                                          str(options), "--report"])
        assert result.exit_code == 0, result.output

    return built_once(tmp_path_factory, "mini_chain", build) / "out"
