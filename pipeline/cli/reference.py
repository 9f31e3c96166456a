"""``seqat reference``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.common import choice, console, fmt, guarded, table

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
        "--robust-loss", help="run (the run's own: huber at its robust scale, or trivial for "
                              "a least-squares run), trivial (off), huber, cauchy or soft_l1."
        )] = "run",
    sfm: Annotated[bool, typer.Option(
        "--sfm", help="Instead: an independent COLMAP SfM of the flight's images, aligned to "
                      "each method by a similarity: OUT/reference/sfm/.")] = False,
    matching: Annotated[str, typer.Option(
        "--matching", help="--sfm: image pairs: spatial (nav positions), sequential or "
                           "exhaustive.")] = "spatial",
    max_image_size: Annotated[int, typer.Option(
        "--max-image-size", help="--sfm: SIFT on a copy at most this many pixels wide.")] = 1600,
    max_features: Annotated[int, typer.Option(
        "--max-features", help="--sfm: SIFT features per image.")] = 8192,
    refine_principal_point: Annotated[bool, typer.Option(
        "--refine-principal-point", help="--sfm: also self-calibrate cx, cy.")] = False,
    threads: Annotated[int, typer.Option("--threads", help="--sfm: CPU threads.")] = 2,
    images: Annotated[Path | None, typer.Option(
        "--images", help="--sfm: the flight's images, if not where run.json says.")] = None,
    realign: Annotated[bool, typer.Option(
        "--realign", help="--sfm: keep the earlier SfM model, only align it again (after "
                          "adding --compare runs or the bundle adjustment).")] = False,
    compare: Annotated[list[Path] | None, typer.Option(
        "--compare", help="--sfm: another run of the same flight to compare (repeatable).")
        ] = None,
) -> None:
    """COLMAP bundle adjustment of a run's observations with GPS/INS priors: OUT/reference/.

    With --sfm: COLMAP's own structure from motion of the images instead, and each method's
    agreement with it after a 7-parameter similarity (OUT/reference/sfm/).
    """
    if sfm:
        _sfm(out, matching, max_image_size, max_features, refine_principal_point, threads,
             images, compare or [], realign)
        return
    from pipeline.reference.colmap_ba import PriorKind, ReferenceOptions, RobustLoss
    from pipeline.reference.stage import run_reference

    prior = choice("--prior", prior, (k.value for k in PriorKind))
    robust_loss = choice("--robust-loss", robust_loss, ["run", *(k.value for k in RobustLoss)])
    options = ReferenceOptions(
        prior=PriorKind(prior), self_calibrate=self_calibrate,
        robust_loss=None if robust_loss == "run" else RobustLoss(robust_loss))
    rec = run_reference(out, options).record
    console().print(table(f"seqat reference {out}", [
        ("images / points / observations",
         f"{rec.n_images_adjusted} / {rec.n_points} / {rec.n_observations}"),
        ("prior", f"{rec.options.prior.value} ({rec.n_prior_residuals} residuals of "
                  f"{rec.n_residuals})"),
        ("loss of the image points", f"{rec.options.robust_loss}"
         + ("" if rec.options.robust_loss == "trivial"
            else f" at {rec.options.loss_scale_sigmas:g} sigma")),
        ("sigma0 (redundancy)", f"{fmt(rec.sigma0, '.4f')} ({rec.redundancy})"),
        ("rms image residual (px)", fmt(rec.rms_px, '.3f')),
        ("termination (iterations)", f"{rec.termination} ({rec.iterations})"),
        ("bundle adjustment", f"{rec.ba_s:.2f} s"),
        ("covariance", rec.covariance),
        ("camera", f"{rec.camera_model} fx {rec.camera.fx_px:.2f} fy {rec.camera.fy_px:.2f} "
                   f"cx {rec.camera.cx_px:.2f} cy {rec.camera.cy_px:.2f}"),
        ("results", str(out / "reference")),
    ]))


def _camera_text(cam: object) -> str:
    return (f"f {cam.fx_px:.1f} / {cam.fy_px:.1f} cx {cam.cx_px:.1f} cy {cam.cy_px:.1f} "  # type: ignore[attr-defined]
            f"k1 {cam.k1:.4f} k2 {cam.k2:.4f} p1 {cam.p1:.5f} p2 {cam.p2:.5f}")  # type: ignore[attr-defined]


def _sfm(out: Path, matching: str, max_image_size: int, max_features: int,
         refine_principal_point: bool, threads: int, images: Path | None,
         compare: list[Path], realign: bool) -> None:
    from pipeline.reference.sfm import Matching, SfmOptions
    from pipeline.reference.sfm_stage import run_sfm_check

    matching = choice("--matching", matching, (k.value for k in Matching))
    options = SfmOptions(matching=Matching(matching), max_image_size_px=max_image_size,
                         max_num_features=max_features,
                         refine_principal_point=refine_principal_point, num_threads=threads)
    s = run_sfm_check(out, options, compare=compare, images_dir=images, realign=realign)
    rows = [
        ("images registered", f"{s.n_registered} of {s.n_images}"),
        ("points / mean track length", f"{s.n_points} / {s.mean_track_length:.2f}"),
        ("mean reprojection error (px)", f"{s.mean_reprojection_px:.3f}"),
        ("SfM camera (OPENCV)", _camera_text(s.camera)),
        ("run camera", _camera_text(s.run_camera)),
    ]
    for label, st in s.methods:
        rows.append((f"agreement with {label}",
                     f"{st.position_rms_m:.3f} m rms (max {st.position_max_m:.3f}), "
                     f"{st.attitude_rms_deg:.3f}° rms (max {st.attitude_max_deg:.3f}), "
                     f"{st.n_inliers}/{st.n_images} in the fit"))
    rows += [("wall", f"{s.wall_s:.1f} s"), ("results", str(s.sfm_dir))]
    console().print(table(f"seqat reference {out} --sfm (agreement, not accuracy)", rows))
