"""Whether the adjusted EOPs and the GPS/INS disagree systematically (a ``run.json`` warning).

A GNSS jump moves a few images' GPS/INS away from where their rays put them; the robust
loss and data snooping handle that (docs/algorithm.md, *Blunders and GNSS faults*). When
most images' adjusted EOPs lie beyond a few σ of their GPS/INS, the two disagree as a
whole: the model is wrong, not the odd fix. A camera held fixed with a wrong calibration
(focal length, distortion) does it: the tie points bend the block away from the GPS/INS,
by metres and degrees, whatever the GPS/INS's weight (a rendered block in
docs/benchmarks.md); so can a wrong lever arm, nav frame or time offset, or a GNSS step
that lasts over much of the flight. The run cannot
tell which model is wrong, so it says what it saw and what to try (docs/algorithm.md,
*The GPS/INS and the images disagree*).
"""

from __future__ import annotations

import numpy as np

from pipeline.common.tables import EopTable, NavTable
from pipeline.run.accuracy import eop_differences
from seqat.types import FloatArray

#: An image's adjusted position (or attitude) disagrees with its GPS/INS when it lies
#: beyond this many σ per degree of freedom from it (r.m.s. over X, Y, Z or ω, φ, κ).
IMAGE_LIMIT_SIGMA = 3.0
#: The disagreement is systematic when more than this share of the images disagree: a
#: GNSS jump or two is a fault here and there, half the flight is the model.
SYSTEMATIC_SHARE = 0.25
#: Fewer images with a GPS/INS fix than this are not judged.
MIN_IMAGES = 8


def _from_fixes(eops: EopTable, nav: NavTable) -> tuple[np.ndarray, FloatArray, FloatArray]:
    """:func:`eop_differences` of the published EOPs from the GPS/INS fixes (rows of a GNSS
    dropout, non-finite, left out)."""
    fix = np.all(np.isfinite(nav.eop), axis=1)
    ids = tuple(iid for iid, ok in zip(nav.image_ids, fix, strict=True) if ok)
    return eop_differences(eops.image_ids, eops.eop, ids, nav.eop[fix])


def nav_disagreement_warning(eops: EopTable, nav: NavTable, nav_sigma: FloatArray, *,
                             camera_fixed: bool) -> str | None:
    """A one-line warning when the images and the GPS/INS disagree systematically.

    Parameters
    ----------
    eops : EopTable
        The published EOPs (metres, radians).
    nav : NavTable
        The GPS/INS EOPs the run was given, in the same CRS; rows of a GNSS dropout
        (non-finite) are not judged.
    nav_sigma : (6,) float
        Their a priori σ: metres and radians.
    camera_fixed : bool
        The camera was held fixed (no self-calibration): then the warning names it as
        the likely cause.

    Returns
    -------
    str or None
        ``None`` when at most :data:`SYSTEMATIC_SHARE` of the images disagree (or fewer
        than :data:`MIN_IMAGES` have a fix).
    """
    rows, d_pos, d_att = _from_fixes(eops, nav)
    if rows.size < MIN_IMAGES:
        return None
    sigma = np.asarray(nav_sigma, dtype=np.float64)
    u_pos = np.sqrt(np.mean((d_pos / sigma[:3]) ** 2, axis=1))
    u_att = np.sqrt(np.mean((np.radians(d_att) / sigma[3:]) ** 2, axis=1))
    off = (u_pos > IMAGE_LIMIT_SIGMA) | (u_att > IMAGE_LIMIT_SIGMA)
    if np.count_nonzero(off) <= SYSTEMATIC_SHARE * rows.size:
        return None
    rms_pos, rms_att = np.sqrt(np.mean(u_pos**2)), np.sqrt(np.mean(u_att**2))
    check = ("check the lever arm, the nav's frame, time offset and σ, and for a GNSS step "
             "that lasted")
    cause = ("the camera was held fixed: if its model is wrong (focal length, distortion), "
             "it bends the block; run again with --self-calibration (flight.yaml: "
             f"self_calibration: {{enabled: true}}); else {check}"
             if camera_fixed else check)
    return (f"the adjusted EOPs of {np.count_nonzero(off)} of {rows.size} images lie beyond "
            f"{IMAGE_LIMIT_SIGMA:g} σ of their GPS/INS (r.m.s. {rms_pos:.1f} σ in position, "
            f"{rms_att:.1f} σ in attitude): the images and the GPS/INS disagree on much of "
            f"the flight; {cause}")


#: A single fix is named (:func:`nav_fault_warnings`) when one of its components lies
#: beyond this many σ of the adjusted EOP: clean flights stay within 3.5 σ (Seneca's INS,
#: 5-20 deg off at σ 5 / 15 deg, and four rendered flights), a GNSS blunder of 30-40 m at
#: σ 3-5 m lies 8-12 σ off.
FAULT_LIMIT_SIGMA = 5.0
#: At most this many fixes are named, then counted.
MAX_FAULT_WARNINGS = 10
_GROUPS = (("position", "a GNSS", ("X", "Y", "Z"), " m"),
           ("attitude", "an INS", ("ω", "φ", "κ"), "°"))


def nav_fault_warnings(eops: EopTable, nav: NavTable, nav_sigma: FloatArray) -> list[str]:
    """One line per GPS/INS fix (an image's position or attitude) that one of its components
    puts beyond :data:`FAULT_LIMIT_SIGMA` σ of the adjusted EOP: the tie points placed the
    image and the robust loss weighed the fix down, but only run.json said so
    (``robustness.nav_robust``, a weight). Not when the disagreement is systematic
    (:func:`nav_disagreement_warning` says it then); an image without tie points rests on
    its fix and is not judged here (its own warning)."""
    rows, d_pos, d_att = _from_fixes(eops, nav)
    sigma = np.asarray(nav_sigma, dtype=np.float64)
    diffs = (d_pos, d_att)  # metres; degrees
    sig = (sigma[:3], np.degrees(sigma[3:]))
    lines = []
    for k, row in enumerate(rows):
        for (group, source, names, unit), d, s in zip(_GROUPS, diffs, sig, strict=True):
            z = np.abs(d[k] / s)
            worst = int(np.argmax(z))
            if z[worst] > FAULT_LIMIT_SIGMA:
                lines.append(
                    f"{eops.image_ids[row]}: its GPS/INS {group} lies "
                    f"{np.linalg.norm(d[k]):.1f}{unit} from the adjusted one "
                    f"({names[worst]} {-d[k][worst]:+.1f}{unit}: {z[worst]:.1f} σ): {source} "
                    f"fault? The tie points place the image; the robust loss weighed that "
                    f"fix down")
    if len(lines) > MAX_FAULT_WARNINGS:
        lines = lines[:MAX_FAULT_WARNINGS] + [
            f"{len(lines) - MAX_FAULT_WARNINGS} more GPS/INS fix(es) beyond "
            f"{FAULT_LIMIT_SIGMA:g} σ of the adjusted EOPs"]
    return lines
