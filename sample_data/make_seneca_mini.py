"""Write ``sample_data/seneca_mini/`` from the Seneca flight (CC0): 18 images at 1000 px.

Usage: ``python sample_data/make_seneca_mini.py /path/to/seneca sample_data/seneca_mini``.
Images IMG_0460-IMG_0477 (the first long strip, the reverse leg over it and the start of
the next strip), downscaled with Pillow's Lanczos filter to 1000 px width, quality 90; the
EXIF (GPS, time, focal length, focal-plane resolution and the original ExifImageWidth) and
the senseFly XMP packet are copied unchanged, so seqat reads the navigation and the
approximate camera from them as from the original files.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from PIL import Image

FIRST, LAST = 460, 477
WIDTH_PX = 1000
QUALITY = 90


def main(src: Path, dst: Path) -> None:
    images = dst / "images"
    images.mkdir(parents=True, exist_ok=True)
    for n in range(FIRST, LAST + 1):
        path = src / "images" / f"IMG_{n:04d}.jpg"
        with Image.open(path) as im:
            exif = im.info.get("exif", b"")
            xmp = im.info.get("xmp", b"")
            height = round(im.height * WIDTH_PX / im.width)
            small = im.resize((WIDTH_PX, height), Image.Resampling.LANCZOS)
            small.save(images / path.name, "JPEG", quality=QUALITY, exif=exif, xmp=xmp)
    shutil.copy(src / "LICENSE-CC0.txt", dst / "LICENSE-CC0.txt")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
