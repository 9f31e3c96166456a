"""Fast JSON for the files a live run replaces several times a second and the layers the
server encodes after each change (``live/estimates.json``, ``run.json``, the GeoJSON layers):
orjson, 3-4x faster than :mod:`json` to read and ~14x to write a 100-image flight's
``live/estimates.json`` (docs/benchmarks.md, *The live map, fourth pass*).

Written JSON is compact UTF-8; numpy scalars and arrays are written as numbers and lists;
NaN and infinities are written as ``null`` (never the invalid ``NaN`` of :func:`json.dumps`).
"""

from __future__ import annotations

import orjson

#: Raised by :func:`loads` on a malformed document; a subclass of ``json.JSONDecodeError``
#: (and of ``ValueError``).
JSONDecodeError = orjson.JSONDecodeError


def dumps(doc: object) -> bytes:
    """``doc`` as compact UTF-8 JSON bytes."""
    return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)


def loads(data: bytes | str) -> object:
    """The JSON document ``data``; raises :data:`JSONDecodeError`."""
    return orjson.loads(data)
