"""``seqat report``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.common import METRE_FORMAT, console, fmt, guarded, table

app = typer.Typer()


@app.command()
@guarded
def report(
    out: Annotated[Path, typer.Argument(help="Run folder (seqat run ... --out OUT).")],
    compare: Annotated[list[Path] | None, typer.Option(
        "--compare", help="Another run folder of the same flight (repeat for several).")]
    = None,
) -> None:
    """Flight report: OUT/report.html (figures embedded) and OUT/report.json."""
    from pipeline.report.stage import make_report

    summary = make_report(out, compare or ())
    rep = summary.report
    rows = [("methods", ", ".join(rep.methods))]
    for acc in rep.accuracy.values():
        what = "agreement with the reference" if acc.against == "reference" else "vs truth"
        rows.append((f"{acc.method}: position H / 3D RMS (m), {what}",
                     f"{fmt(acc.pos_rmse_h_m, METRE_FORMAT)} / "
                     f"{fmt(acc.pos_rmse_3d_m, METRE_FORMAT)}"))
    cp = rep.checkpoints
    rows.append(("check points", "none" if cp is None else
                 f"{cp['count']}: RMSE_H {fmt(cp['rmse_h_m'], METRE_FORMAT)} m, "
                 f"RMSE_V {fmt(cp['rmse_v_m'], METRE_FORMAT)} m"))
    rows += [(n, "") for n in rep.notes]
    rows += [("written", "  ".join(str(f) for f in summary.files))]
    console().print(table(f"seqat report {out}", rows))
