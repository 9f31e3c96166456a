"""The embedded sample flights the journal and watch tests run, and how runs are compared."""

from __future__ import annotations

import shutil
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
#: An observations flight (60 images) and a rendered image flight (12 images, geodetic nav).
STRIP = REPO_ROOT / "sample_data" / "strip_demo"
AUTZEN = REPO_ROOT / "sample_data" / "autzen_rendered"
#: A real image flight (18 Seneca images; nav and camera from EXIF/XMP).
MINI = REPO_ROOT / "sample_data" / "seneca_mini"
#: Ortho pixel of the session's chain on MINI, metres: 3.5x its GSD (0.070 m), 1/12 of the
#: pixels; what the chain is tested for (every stage writes its files, the ortho runs image by
#: image) does not depend on it. The GSD default: tests/pipeline/ortho/test_ortho.py.
MINI_ORTHO_PIXEL_M = 0.25
#: Result files that must be bit-identical between equivalent runs.
RESULT_FILES = ("eop.csv", "points.csv", "observations.csv")
#: What ``seqat run --ortho --report`` writes besides the files of a plain ``seqat run``.
ORTHO_AND_REPORT_FILES = ("ortho", "ortho.json", "mosaic.tif", "cameras.gpkg", "report.html",
                          "report.json", "report.pdf")


def assert_same_results(ref: Path, out: Path) -> None:
    """The estimates and observations of two run folders are bit-identical."""
    for name in RESULT_FILES:
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name


def copy_run_files(run: Path, to: Path) -> Path:
    """Copy a run folder without its ortho and report products: the folder a plain
    ``seqat run`` of the same flight and options writes (results bit-identical: the live
    ortho only listens), for a test that writes into it."""
    shutil.copytree(run, to, ignore=shutil.ignore_patterns(*ORTHO_AND_REPORT_FILES))
    return to


def resize_images(paths: list[Path], sizes: list[tuple[int, int]]) -> None:
    """Rewrite each JPEG of ``paths`` at the matching size, keeping its EXIF and XMP (a
    camera's other mode, as Seneca's first image)."""
    from PIL import Image

    for path, size in zip(paths, sizes, strict=True):
        with Image.open(path) as im:
            exif, xmp = im.info.get("exif"), im.info.get("xmp")
            small = im.resize(size)
        small.save(path, "JPEG", exif=exif, **({"xmp": xmp} if xmp else {}))
