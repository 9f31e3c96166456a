"""The embedded sample flights the journal and watch tests run, and how runs are compared."""

from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
#: An observations flight (60 images) and a rendered image flight (12 images, geodetic nav).
STRIP = REPO_ROOT / "sample_data" / "strip_demo"
AUTZEN = REPO_ROOT / "sample_data" / "autzen_rendered"
#: Result files that must be bit-identical between equivalent runs.
RESULT_FILES = ("eop.csv", "points.csv", "observations.csv")


def assert_same_results(ref: Path, out: Path) -> None:
    """The estimates and observations of two run folders are bit-identical."""
    for name in RESULT_FILES:
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name
