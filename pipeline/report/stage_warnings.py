"""Every warning of every stage of a run folder, in one list (the report shows it near the top).

Sources (docs/formats.md): ``run.json`` ``warnings`` and ``skipped``, ``ortho.json``
``warnings`` and ``skipped``, ``reference/reference.json`` (not converged; the observations it
leaves out are rays without a second one, no warning), ``reference/sfm/sfm.json`` (images not
registered, its note), check points that could not be intersected, and the report's own notes
(what is missing).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class StageWarning:
    """One warning: the stage that gave it (``run``, ``ortho``, ``reference``, ``sfm``,
    ``check points``, ``report``) and its one-line text."""

    stage: str
    message: str


def _strings(values: object) -> list[str]:
    return [str(v) for v in values] if isinstance(values, list) else []


def _skipped(values: object) -> list[str]:
    if not isinstance(values, list):
        return []
    out = []
    for v in values:
        if isinstance(v, Mapping):
            out.append(f"image {v.get('image')!s} skipped: {v.get('reason')!s}")
        else:
            out.append(f"skipped: {v!s}")
    return out


def collect_warnings(run_record: Mapping[str, object], ortho: Mapping[str, object] | None,
                     reference: Mapping[str, object] | None,
                     sfm: Mapping[str, object] | None,
                     not_intersected: Iterable[str],
                     notes: Iterable[str]) -> tuple[StageWarning, ...]:
    """The warnings of every stage, grouped by stage in processing order.

    Parameters
    ----------
    run_record : Mapping
        ``run.json``.
    ortho : Mapping or None
        ``ortho.json`` (:func:`pipeline.run.latency.read_ortho_json`).
    reference : Mapping or None
        ``reference/reference.json``.
    sfm : Mapping or None
        ``report.json`` ``sfm_agreement`` (the condensed ``sfm.json``).
    not_intersected : iterable of str
        Check points of the run's method seen in fewer than two images.
    notes : iterable of str
        The report's notes (no reference, no check points, ...).
    """
    found = [StageWarning(stage="run", message=m) for m in
             _strings(run_record.get("warnings")) + _skipped(run_record.get("skipped"))]
    if ortho is not None:
        found += [StageWarning(stage="ortho", message=m) for m in
                  _strings(ortho.get("warnings")) + [f"image {s} not orthorectified"
                                                     for s in _strings(ortho.get("skipped"))]]
    if reference is not None:
        if reference.get("converged") is False:
            found.append(StageWarning(stage="reference", message=(
                f"COLMAP bundle adjustment did not converge ({reference.get('termination')}, "
                f"{reference.get('iterations')} iterations)")))
    if sfm is not None:
        unregistered = _strings(sfm.get("unregistered"))
        if unregistered:
            found.append(StageWarning(stage="sfm", message=(
                f"{len(unregistered)} image(s) not registered by the independent SfM: "
                + ", ".join(unregistered))))
        if sfm.get("note"):
            found.append(StageWarning(stage="sfm", message=str(sfm["note"])))
    missing = list(not_intersected)
    if missing:
        found.append(StageWarning(stage="check points", message=(
            f"{len(missing)} check point(s) seen in fewer than two images, not intersected: "
            + ", ".join(missing))))
    found += [StageWarning(stage="report", message=n) for n in notes]
    return tuple(found)
