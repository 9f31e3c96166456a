"""``seqat reference``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.common import console, fmt, guarded, table

app = typer.Typer()


@app.command()
@guarded
def reference(
    out: Annotated[Path, typer.Argument(help="Run folder (seqat run ... --out OUT).")],
    self_calibrate: Annotated[bool, typer.Option(
        "--self-calibrate", help="Also estimate fx, fy, cx, cy, k1, k2, p1, p2.")] = False,
    prior: Annotated[str, typer.Option(
        "--prior", help="GPS/INS prior: pose (6-DoF, as Sim) or position.")] = "pose",
    robust_loss: Annotated[str, typer.Option(
        "--robust-loss", help="trivial (off), huber, cauchy or soft_l1.")] = "trivial",
) -> None:
    """COLMAP bundle adjustment of a run's observations with GPS/INS priors: OUT/reference/."""
    from pipeline.reference.colmap_ba import PriorKind, ReferenceOptions, RobustLoss
    from pipeline.reference.stage import run_reference
    from seqat.errors import ConfigError

    for flag, value, kind in (("--prior", prior, PriorKind),
                              ("--robust-loss", robust_loss, RobustLoss)):
        if value not in {k.value for k in kind}:
            raise ConfigError(f"{flag}: expected one of {', '.join(k.value for k in kind)}, "
                              f"got {value!r}")
    options = ReferenceOptions(prior=PriorKind(prior), robust_loss=RobustLoss(robust_loss),
                               self_calibrate=self_calibrate)
    rec = run_reference(out, options).record
    console().print(table(f"seqat reference {out}", [
        ("images / points / observations",
         f"{rec.n_images_adjusted} / {rec.n_points} / {rec.n_observations}"),
        ("prior", f"{rec.options.prior.value} ({rec.n_prior_residuals} residuals of "
                  f"{rec.n_residuals})"),
        ("sigma0 (redundancy)", f"{fmt(rec.sigma0, '.4f')} ({rec.redundancy})"),
        ("rms image residual (px)", fmt(rec.rms_px, '.3f')),
        ("termination (iterations)", f"{rec.termination} ({rec.iterations})"),
        ("bundle adjustment", f"{rec.ba_s:.2f} s"),
        ("covariance", rec.covariance),
        ("camera", f"{rec.camera_model} fx {rec.camera.fx_px:.2f} fy {rec.camera.fy_px:.2f} "
                   f"cx {rec.camera.cx_px:.2f} cy {rec.camera.cy_px:.2f}"),
        ("results", str(out / "reference")),
    ]))
