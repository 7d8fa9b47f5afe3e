"""An OpenSim knee's ligaments as kneenlp sees them: bundles grouped by name (:func:`ligament_groups`)
and femur-tibia line elements (:func:`knee_line_elements`)."""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from kneenlp.io.osim.kinematics import OsimError, _apply
from kneenlp.io.osim.model import _LIGAMENT_TAG, OsimModel

# --------------------------------------------------------------------------------------
# ligament groups
# --------------------------------------------------------------------------------------
_ROOT_RE = re.compile(r"^(?P<root>[a-z]?[A-Z][A-Z0-9]*)(?P<sub>[a-z]*)$")


def _split_name(name: str) -> tuple[str, str]:
    """bundle name -> (fine group, coarse group); see :func:`ligament_groups`."""
    fine = re.sub(r"[_\-]?\d+$", "", name) or name
    m = _ROOT_RE.match(fine)
    return fine, (m.group("root") if m else fine)


def ligament_groups(names: Iterable[str] | OsimModel) -> dict[str, dict[str, list[str]]]:
    """Group bundle names at two granularities.

    Rule (document for users): a bundle name is ``<fine group><index>`` where the index is
    the trailing run of digits (``ACLam3`` -> ``ACLam``, ``pCAP7`` -> ``pCAP``).  The fine
    group is ``<root><sub-bundle>`` where ``root`` is an optional single lower-case side /
    location letter followed by a run of capitals/digits (``ACL``, ``MCL``, ``pCAP``,
    ``lPFL``, ``PT``, ``ITB``) and ``sub-bundle`` is the trailing lower-case letters
    (``am``, ``pl``, ``al``, ``pm``, ``s``, ``d``, ``p``).  The coarse group is the root:
    ACLam+ACLpl -> ACL, PCLal+PCLpm -> PCL, MCLs+MCLd+MCLp -> MCL; LCL, pCAP, PT, ITB,
    lPFL, mPFL, PFL stay as they are (note PFL = popliteofibular, lPFL/mPFL =
    lateral/medial patellofemoral: distinct roots, never merged).  Names not matching
    the pattern use the name without trailing ``[_-]digits`` for both levels.

    Returns ``{"fine": {group: [bundles...]}, "coarse": {group: [bundles...]}}`` in
    first-appearance order.
    """
    if isinstance(names, OsimModel):
        names = list(names.ligaments)
    fine: dict[str, list[str]] = {}
    coarse: dict[str, list[str]] = {}
    for n in names:
        f, c = _split_name(n)
        fine.setdefault(f, []).append(n)
        coarse.setdefault(c, []).append(n)
    return {"fine": fine, "coarse": coarse}


# --------------------------------------------------------------------------------------
# knee line elements (kneenlp convention)
# --------------------------------------------------------------------------------------
@dataclass
class LineElement:
    """A ligament as a femur-tibia line element in kneenlp's convention.

    ``femoral_point`` [m] in the femur frame, ``tibial_point`` [m] in the tibia frame
    (the tibia frame coincides with the femur frame at the reference pose of the model,
    see REPORT.md), ``ignored_points``: names of path points beyond the femoral/tibial
    ones (e.g. the pelvis origin of ITB1) that were dropped; ``wraps``: PathWraps that the
    straight line ignores.  ``extra_length`` [m]: length of the dropped path segments at the
    model's default pose; the OpenSim strain of the bundle is
    ``(|femoral - tibial| + extra_length) / slack_length - 1``.  ``extra_length_constant``
    is False when a dropped segment crosses a non-weld joint (e.g. ITB1's pelvis-femur
    segment depends on the hip angles), so ``extra_length`` is exact only at the default
    pose of those other joints."""
    name: str
    femoral_point: np.ndarray
    tibial_point: np.ndarray
    linear_stiffness: float
    slack_length: float
    transition_strain: float
    ignored_points: list[str]
    wraps: list[str]
    extra_length: float = 0.0
    extra_length_constant: bool = True


def knee_line_elements(model: OsimModel, femur_body: str = "femur_distal_r",
                       tibia_body: str = "tibia_proximal_r") -> dict[str, LineElement]:
    """Ligaments spanning femur -> tibia as straight line elements.

    Points on bodies welded to ``femur_body`` (e.g. femur_r) are expressed in
    ``femur_body``; likewise for the tibia.  The femoral point is the last path point on
    the femur side, the tibial point the first point after it on the tibia side; bundles
    without both (patellar, patellofemoral ones) are not returned."""
    fem = model.welded_bodies(femur_body)
    tib = model.welded_bodies(tibia_body)
    out: dict[str, LineElement] = {}
    for lig in model.ligaments.values():
        idx_f = [i for i, p in enumerate(lig.points) if p.body in fem]
        idx_t = [i for i, p in enumerate(lig.points) if p.body in tib]
        if not idx_f or not idx_t:
            continue
        if idx_f[-1] < idx_t[0]:
            i_f, i_t = idx_f[-1], idx_t[0]
        elif idx_t[-1] < idx_f[0]:
            i_f, i_t = idx_f[0], idx_t[-1]
        else:
            raise OsimError(f"{model.path}: {_LIGAMENT_TAG} '{lig.name}': femoral and tibial "
                            f"path points interleave")
        pf, pt = lig.points[i_f], lig.points[i_t]
        ignored = [p.name for k, p in enumerate(lig.points) if k not in (i_f, i_t)]
        extra, const = 0.0, True
        if ignored:
            T = model.body_transforms(bodies=sorted({p.body for p in lig.points}))
            lo, hi = min(i_f, i_t), max(i_f, i_t)
            for k in range(len(lig.points) - 1):
                if lo <= k < hi:
                    continue  # the kept femur-tibia segment
                a, b = lig.points[k], lig.points[k + 1]
                extra += float(np.linalg.norm(_apply(T[b.body], b.location_in_body)
                                              - _apply(T[a.body], a.location_in_body)))
                if b.body not in model.welded_bodies(a.body):
                    const = False
        out[lig.name] = LineElement(lig.name, model.point_in_body(pf, femur_body),
                                    model.point_in_body(pt, tibia_body), lig.linear_stiffness,
                                    lig.slack_length, lig.transition_strain, ignored,
                                    list(lig.wraps), extra, const)
    return out

