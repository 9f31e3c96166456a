"""``seqat simulate``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.common import console, guarded, table

app = typer.Typer()


@app.command()
@guarded
def simulate(
    config: Annotated[Path, typer.Argument(help="Simulation config (configs/*_sim.yaml).")],
    out: Annotated[Path, typer.Option("--out", help="Flight folder to write.")],
    seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
) -> None:
    """Simulate a flight and write it as a flight folder with truth/."""
    from pipeline.simulate.stage import simulate_to_folder

    summary = simulate_to_folder(config, out, seed)
    console().print(table("seqat simulate", [
        ("flight", str(summary.out_dir)),
        ("crs", summary.crs),
        ("seed", str(summary.seed)),
        ("images", str(summary.n_images)),
        ("points", str(summary.n_points)),
        ("observations", str(summary.n_observations)),
        ("duration", f"{summary.duration_s:.1f} s"),
    ]))


# Options shared by `run` and `watch`.
