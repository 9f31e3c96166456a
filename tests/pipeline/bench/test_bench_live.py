"""``seqat bench live``'s page-like client: the tiles it reloads on a new mosaic revision are
the page's (``changedBoxes`` in pipeline/serve/static/serve.js)."""

from __future__ import annotations

from pipeline.bench.live import changed_boxes

A, B, C = [0.0, 0.0, 1.0, 1.0], [1.0, 1.0, 2.0, 2.0], [5.0, 5.0, 6.0, 6.0]


def live(revision: int, changes: list[list[object]] | None, maxzoom: int = 19
         ) -> dict[str, object]:
    return {"version": f"live-{revision}", "revision": revision, "maxzoom": maxzoom,
            "changes": changes}


def test_changed_boxes_known_answers() -> None:
    changes: list[list[object]] = [[None, 1, [A]], [1, 3, [B]], [3, 4, []], [4, 5, [C]]]
    cur = live(5, changes)
    assert changed_boxes(None, cur) is None  # nothing shown: every tile
    assert changed_boxes(live(5, changes), cur) == []  # the same revision: none
    assert changed_boxes(live(1, None), cur) == [B, C]  # 1 -> 3 -> 4 -> 5
    assert changed_boxes(live(3, None), cur) == [C]
    assert changed_boxes(live(2, None), cur) is None  # never shown: not in the chain
    assert changed_boxes(live(0, None), cur) is None  # older than the renderings kept
    assert changed_boxes(live(3, None, maxzoom=18), cur) is None  # other zooms
    assert changed_boxes(live(3, None), live(5, None)) is None  # no changes
    final = {"version": "123-456-789", "revision": None, "maxzoom": 19, "changes": None}
    assert changed_boxes(live(5, changes), final) is None  # mosaic.tif replaces the live one
    assert changed_boxes(final, final) == []
