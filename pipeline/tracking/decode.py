"""Checks of JPEG data before decoding (docs/formats.md, *Bad images*).

OpenCV's libjpeg decodes damaged entropy-coded data into garbage with a warning on stderr
and no error. A baseline (sequential) JPEG's scan may only hold stuffed ``FF 00`` bytes,
restart markers ``FF D0``-``FF D7`` and fill bytes until its end-of-image marker, so any
other marker inside it means the data were damaged (a transmission error, a bad card).
"""

from __future__ import annotations

import re

#: A marker other than stuffing, restart or fill inside entropy-coded data.
_MARKER = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
_STANDALONE = {0x01, *range(0xD0, 0xD8)}
_SEQUENTIAL_SOF = {0xC0, 0xC1}  # baseline / extended sequential Huffman: one scan
_SOS, _EOI = 0xDA, 0xD9


def jpeg_scan_problem(data: bytes) -> str | None:
    """What is wrong with the image data of a sequential JPEG, or None (also for anything
    this check does not cover: not a JPEG, progressive, arithmetic coding)."""
    if not data.startswith(b"\xff\xd8"):
        return None
    pos, sequential = 2, False
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None  # damaged headers: the decoder reports them
        code = data[pos + 1]
        if code == 0xFF:
            pos += 1
            continue
        if code in _STANDALONE:
            pos += 2
            continue
        length = int.from_bytes(data[pos + 2: pos + 4], "big")
        if 0xC0 <= code <= 0xCF and code not in (0xC4, 0xC8, 0xCC):
            sequential = code in _SEQUENTIAL_SOF
        pos += 2 + length
        if code == _SOS:
            break
    else:
        return None
    if not sequential:
        return None
    found = _MARKER.search(data, pos)
    if found is None or data[found.start() + 1] == _EOI:
        return None
    return (f"corrupt JPEG data (marker 0xff{data[found.start() + 1]:02x} inside the image "
            f"data at byte {found.start()})")
