"""What a run did about bad data: data snooping and GNSS dropouts (``run.json`` ``robustness``).

The estimators keep the observations data snooping removed (``rejections``) and the GPS/INS
groups it down-weighted (``nav_downweighted``; the GPS/INS groups the robust loss
down-weights: ``nav_robust``), over the whole run including the initial
simultaneous stage and the ray screening at a point's birth (docs/algorithm.md, *Blunders and
GNSS faults*); the frame sources list the dropout images they bridged or left out. This
module turns them into one typed record for ``run.json`` and reads it back for the report.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from pipeline.run.final_check import FinalCheck


@dataclass(frozen=True, kw_only=True)
class Rejection:
    """An image observation removed by data snooping, with its w-test value."""

    image: str
    point: str
    w: float


@dataclass(frozen=True, kw_only=True)
class NavDownweight:
    """A GPS/INS group (``position`` or ``attitude``) of an image whose σ was multiplied by
    :data:`seqat.snooping.NAV_DOWNWEIGHT`."""

    image: str
    group: str


@dataclass(frozen=True, kw_only=True)
class NavRobust:
    """A GPS/INS group (``position`` or ``attitude``) of an image that the robust loss
    down-weights in the final solution: its weight factor (below 0.9; 1 = least squares)."""

    image: str
    group: str
    weight: float


@dataclass(frozen=True, kw_only=True)
class RobustnessRecord:
    """``run.json`` ``robustness``.

    Attributes
    ----------
    snooping_critical : float or None
        Critical value of the w-test (``None``: data snooping off).
    min_rays : int
        Rays a tie point needs before it enters the adjustment.
    rejections : tuple[Rejection, ...]
        Every observation removed (final state: Sim's re-admitted ones are not listed).
    nav_downweighted : tuple[NavDownweight, ...]
    dropout_bridged : tuple[str, ...]
        GNSS dropout images sent to the estimator with a resected start value.
    dropout_skipped : tuple[str, ...]
        GNSS dropout images left out (too few known ground points to resect them).
    robust_scale : float or None
        Robust loss of the image points (sigmas; ``None``: least squares).
    undetermined_points : tuple[str, ...]
        Tie points the data do not determine (singular information), left out of the
        solution instead of failing it (docs/algorithm.md).
    diverged_images : tuple[str, ...]
        Images whose rows sent the update beyond every prior sigma (gross errors in most of
        their points), left the models' domain, or most of whose rays reject their estimate
        from the GPS/INS start and again from a resection: carried by their GPS/INS alone,
        their rays left out (docs/algorithm.md, *A poor start*).
    diverged_live : tuple[str, ...]
        Images that diverged during the flight (the estimator the images went through) and
        that a final check's adopted adjustment placed: the live map and the per-image
        reports showed them at their GPS/INS; not in ``diverged_images``, which describes
        the published solution. Empty when the run's own solution is published.
    rescued_points : tuple[str, ...]
        Tie points most of whose rays disagreed with their estimate (one born on a blunder),
        re-intersected robustly from their rays during a window re-linearisation.
    disagreeing_points : tuple[str, ...]
        Tie points with fewer than two rays within the robust loss's core at the final
        estimate (two rays, one a wrong match), whose rays fit two places or another place
        with more rays, or whose rays spread less than 1 degree: left out of the solution
        (:func:`seqat.robust.withheld_points`, :func:`seqat.robust.narrow_points`).
    off_surface_points : tuple[str, ...]
        Tie points far above or below the surface their neighbours define, with no
        neighbour at their height (a wrong match along the epipolar line): not published
        (:func:`seqat.surface.off_surface_points`).
    final_reopen_skipped : int
        Seq-R: departed parameters that the final smoothing pass did not re-open for being
        too many (their RTS-smoothed values stand; 0: every one re-opened, or none departed).
    second_starts : tuple[str, ...]
        Seq-R: images after whose update a second start of the window was kept (it fitted
        better; docs/algorithm.md, *A second start during the flight*).
    second_starts_tried : int
        Seq-R: second starts tried (after an update that moved earlier images beyond 3 σ,
        and the updates after it, when the window left camera parameters undetermined).
    nav_robust_scale : float or None
        Robust loss of the GPS/INS groups (sigmas per degree of freedom; ``None``: least
        squares).
    nav_robust : tuple[NavRobust, ...]
        The GPS/INS groups it down-weights (weight factor below
        :data:`seqat.robust.NAV_REPORT_WEIGHT`; a GNSS jump).
    contamination : float or None
        Fraction of the rays of the tie points of three rays or more clearly beyond the
        robust loss's core in the final solution (:func:`seqat.robust.contamination`;
        ``None``: not judged — no loss, no such point, or the inverse engine).
    untrusted_points : tuple[str, ...]
        The two-ray tie points left out of the final adjustment because ``contamination``
        exceeds :data:`seqat.robust.MAX_CONTAMINATION` (wrong matches that two rays cannot
        show; docs/algorithm.md, *Two-ray points of a contaminated flight*).
    final_robust_scale : float or None
        The robust scale of the image points in the final adjustment: ``robust_scale``, or
        :data:`seqat.robust.CONTAMINATED_SCALE` on such a flight (docs/algorithm.md, *The
        loss of a contaminated flight*).
    final_check : FinalCheck or None
        The flight adjusted once more from its GPS/INS when the run finished, and whether
        that replaced the run's solution (:mod:`pipeline.run.final_check`; ``None``: not
        run — ``final_check: false``, or a Sim adjusting once at the end).
    """

    snooping_critical: float | None
    min_rays: int
    rejections: tuple[Rejection, ...]
    nav_downweighted: tuple[NavDownweight, ...]
    dropout_bridged: tuple[str, ...] = ()
    dropout_skipped: tuple[str, ...] = ()
    robust_scale: float | None = None
    undetermined_points: tuple[str, ...] = ()
    diverged_images: tuple[str, ...] = ()
    diverged_live: tuple[str, ...] = ()
    rescued_points: tuple[str, ...] = ()
    disagreeing_points: tuple[str, ...] = ()
    off_surface_points: tuple[str, ...] = ()
    final_reopen_skipped: int = 0
    second_starts: tuple[str, ...] = ()
    second_starts_tried: int = 0
    nav_robust_scale: float | None = None
    nav_robust: tuple[NavRobust, ...] = ()
    contamination: float | None = None
    untrusted_points: tuple[str, ...] = ()
    final_robust_scale: float | None = None
    final_check: FinalCheck | None = None


def robustness_record(estimator: object, options: object, *, bridged: Sequence[str] = (),
                      skipped: Sequence[str] = (),
                      off_surface: Sequence[str] = (),
                      final_check: FinalCheck | None = None,
                      flown: object = None) -> RobustnessRecord:
    """The record of a finished run.

    Parameters
    ----------
    estimator : SequentialAT or SimultaneousAT
        Read: ``rejections`` [(image, point, w)], ``nav_downweighted`` [(image, group)].
    options : SequentialOptions or SimOptions
        Read: ``snooping_critical``, ``min_rays``.
    bridged, skipped : sequence of str
        Dropout image ids.
    off_surface : sequence of str
        Tie points the run left out as off the surface (``RunSession.off_surface``).
    final_check : FinalCheck or None
        ``RunSession.final_check``.
    flown : SequentialAT or SimultaneousAT, optional
        The estimator the images went through (``RunSession.flown``), when the final check
        replaced ``estimator``: read for what happened during the flight (second starts).
    """
    flown = estimator if flown is None else flown
    diverged = tuple(getattr(estimator, "diverged", ()))
    rejections = tuple(Rejection(image=i, point=p, w=round(float(w), 3))
                       for i, p, w in getattr(estimator, "rejections", ()))
    nav = tuple(NavDownweight(image=i, group=g)
                for i, g in getattr(estimator, "nav_downweighted", ()))
    return RobustnessRecord(snooping_critical=getattr(options, "snooping_critical", None),
                            min_rays=int(getattr(options, "min_rays", 2)),
                            rejections=rejections, nav_downweighted=nav,
                            dropout_bridged=tuple(bridged), dropout_skipped=tuple(skipped),
                            robust_scale=getattr(options, "robust_scale", None),
                            undetermined_points=tuple(getattr(estimator, "undetermined", ())),
                            diverged_images=diverged,
                            diverged_live=tuple(i for i in getattr(flown, "diverged", ())
                                                if flown is not estimator and i not in diverged),
                            rescued_points=tuple(dict.fromkeys(getattr(estimator, "rescued",
                                                                       ()))),
                            disagreeing_points=tuple(getattr(estimator, "disagreeing", ())),
                            off_surface_points=tuple(off_surface),
                            final_reopen_skipped=int(getattr(estimator, "final_reopen_skipped",
                                                             0)),
                            second_starts=tuple(getattr(flown, "second_starts", ())),
                            second_starts_tried=int(getattr(flown, "second_starts_tried", 0)),
                            nav_robust_scale=getattr(options, "nav_robust_scale", None),
                            nav_robust=tuple(NavRobust(image=i, group=g, weight=w) for i, g, w
                                             in getattr(estimator, "nav_robust", ())),
                            contamination=(round(eps, 4) if math.isfinite(eps := float(
                                getattr(estimator, "contamination", math.nan))) else None),
                            untrusted_points=tuple(getattr(estimator, "untrusted", ())),
                            final_robust_scale=getattr(getattr(estimator, "options", options),
                                                       "robust_scale", None),
                            final_check=final_check)


@dataclass(frozen=True, kw_only=True)
class RobustnessSummary:
    """Counts for the report (``report.json`` ``robustness``)."""

    snooping_critical: float | None
    observations_rejected: int
    observations_rejected_in_updates: int  # by the w-test of a sequential update
    images_with_rejections: int
    nav_downweighted: tuple[str, ...]  # "image: group"
    dropout_bridged: int
    dropout_skipped: tuple[str, ...]
    nav_robust: tuple[str, ...] = ()  # "image: group (weight)"
    points_disagreeing: int = 0  # tie points left out: fewer than two rays agree
    points_undetermined: int = 0  # tie points left out: singular information
    points_off_surface: int = 0  # tie points left out: off the surface, no partner
    points_untrusted: int = 0  # two-ray tie points left out: a contaminated flight
    contamination: float | None = None  # run.json robustness.contamination
    robust_scale: float | None = None  # ... robust_scale (σ; None: least squares)
    final_robust_scale: float | None = None  # ... final_robust_scale
    final_check: str = "not run"  # ... final_check, in words (check_summary)


def summarise(record: Mapping[str, object]) -> RobustnessSummary | None:
    """Counts from a ``run.json`` document (``None`` for runs written before the record)."""
    rob = record.get("robustness")
    if not isinstance(rob, Mapping):
        return None
    rejections = rob.get("rejections") or []
    nav = rob.get("nav_downweighted") or []
    images = record.get("images") or []
    assert isinstance(rejections, list) and isinstance(nav, list) and isinstance(images, list)
    in_updates = sum(len(im.get("rejected") or ()) for im in images if isinstance(im, Mapping))
    return RobustnessSummary(
        snooping_critical=_number(rob.get("snooping_critical")),
        observations_rejected=len(rejections),
        observations_rejected_in_updates=in_updates,
        images_with_rejections=len({r["image"] for r in rejections}),
        nav_downweighted=tuple(f"{n['image']}: {n['group']}" for n in nav),
        dropout_bridged=len(rob.get("dropout_bridged") or ()),  # type: ignore[arg-type]
        dropout_skipped=tuple(rob.get("dropout_skipped") or ()),  # type: ignore[arg-type]
        nav_robust=tuple(f"{n['image']}: {n['group']} ({n['weight']:.2g})"
                         for n in rob.get("nav_robust") or ()),  # type: ignore[union-attr]
        points_disagreeing=len(rob.get("disagreeing_points") or ()),  # type: ignore[arg-type]
        points_undetermined=len(rob.get("undetermined_points") or ()),  # type: ignore[arg-type]
        points_off_surface=len(rob.get("off_surface_points") or ()),  # type: ignore[arg-type]
        points_untrusted=len(rob.get("untrusted_points") or ()),  # type: ignore[arg-type]
        contamination=_number(rob.get("contamination")),
        robust_scale=_number(rob.get("robust_scale")),
        final_robust_scale=final_robust_scale(rob),
        final_check=check_summary(rob.get("final_check")))


def check_summary(check: object) -> str:
    """``run.json`` ``robustness.final_check`` in words (the report's row)."""
    if not isinstance(check, Mapping):
        return "not run"
    if check.get("failed"):
        return f"no solution ({check['failed']}); the run's kept"
    worst = _number(check.get("max_moved_sigma"))
    moved = check.get("moved_images") or []
    assert isinstance(moved, (list, tuple))
    if not moved:
        return f"agrees (largest difference {worst or 0.0:.1f} σ)"
    where = f"{len(moved)} image(s) up to {worst or 0.0:.0f} σ apart"
    warm, cold = _number(check.get("sigma0_warm")), _number(check.get("sigma0_cold"))
    fit = f"σ0 {warm:.4f} / {cold:.4f}" if warm is not None and cold is not None else ""
    if check.get("adopted"):
        whose = ("the run's estimates adjusted again" if check.get("published") == "warm"
                 else "the adjustment from the GPS/INS")
        return f"wrong minimum: {where}; published {whose} ({fit})"
    return f"{where}; the run's solution fits as well or better ({fit}), kept"


def final_robust_scale(robustness: Mapping[str, object]) -> float | None:
    """The image points' robust scale of a run's final adjustment from its ``run.json``
    ``robustness``: ``final_robust_scale``, or ``robust_scale`` for a run.json written
    before that field (``None``: least squares)."""
    return _number(robustness.get("final_robust_scale", robustness.get("robust_scale")))


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, int | float) else None


def _loss(scale: float | None) -> str:
    return "least squares" if scale is None else f"{scale:g} σ"


def robustness_rows(summary: RobustnessSummary) -> list[tuple[str, str]]:
    """Rows of the report's *Blunders and GNSS faults* table."""
    critical = summary.snooping_critical
    return [
        ("data snooping", "off" if critical is None else f"w-test, critical value {critical:g}"),
        ("observations rejected (by update w-tests) / images",
         f"{summary.observations_rejected} ({summary.observations_rejected_in_updates}) / "
         f"{summary.images_with_rejections}"),
        ("GPS/INS groups down-weighted", ", ".join(summary.nav_downweighted) or "none"),
        ("GPS/INS groups down-weighted by the robust loss (weight)",
         ", ".join(summary.nav_robust) or "none"),
        ("tie points left out: rays disagree / undetermined / off the surface",
         f"{summary.points_disagreeing} / {summary.points_undetermined} / "
         f"{summary.points_off_surface}"),
        ("contamination (rays of 3+ ray tie points clearly off) / two-ray points left out",
         ("not judged" if summary.contamination is None
          else f"{100 * summary.contamination:.1f} % / {summary.points_untrusted}")),
        ("robust loss's core, configured / final adjustment",
         f"{_loss(summary.robust_scale)} / {_loss(summary.final_robust_scale)}"),
        ("final check: the flight adjusted again from its GPS/INS", summary.final_check),
        ("GNSS dropout images bridged / skipped",
         f"{summary.dropout_bridged} / {len(summary.dropout_skipped)}"
         + (f" ({', '.join(summary.dropout_skipped)})" if summary.dropout_skipped else "")),
    ]
