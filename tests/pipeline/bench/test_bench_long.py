"""``seqat bench long`` harness on a short strip (the 10,000-image run is a benchmark)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from pipeline.bench.long import SAMPLES, run_long_bench


def test_long_bench_streams_final_parameters(tmp_path: Path) -> None:
    b = run_long_bench(tmp_path, images=200, lag=40, compare_full=False)
    (v,) = b.variants
    assert len(v.samples) == SAMPLES and v.samples[-1].images == 200
    assert v.samples[-1].records_kept < 0.6 * 200  # old departure records were dropped
    with (tmp_path / "final_eop.csv").open() as fh:
        rows = list(csv.reader(fh))[1:]
    assert 100 < len(rows) < 200  # everything but the last lag-and-a-bit images
    assert len({r[0] for r in rows}) == len(rows)  # each final once
    data = json.loads((tmp_path / "bench_long.json").read_text())
    assert data["images"] == 200 and (tmp_path / "long_memory.png").stat().st_size > 0
