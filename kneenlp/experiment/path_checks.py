"""Where a wrapped ligament path is not smooth at a solved pose (:meth:`kneenlp.model.paths.WrapPath.jump`):
an attachment inside its obstacle, or the path where it switches sides.  The equilibrium is
discontinuous there, so a solve that lands there is named, not left to fail or pass silently."""

from __future__ import annotations

import numpy as np

from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.model.paths import WrapPath


def wrapped_bundles(model: KneeModel) -> list[tuple]:
    """``(ligament, bundle)`` of every bundle of ``model``'s elements whose path wraps an obstacle."""
    return [(lig, b) for lig in model.elements if hasattr(lig, "bundles")
            for b in lig.bundles if isinstance(b.path, WrapPath)]


def path_jumps(model: KneeModel, q: np.ndarray, theta: np.ndarray, flexions) -> list[str]:
    """One note per trial (``""`` where every path is smooth) at the poses ``q`` (T x 5, SI) and
    ``flexions`` (T, rad) with the parameters ``theta``: each bundle whose path is not (its
    attachments moved by the parameters that shift them)."""
    bundles = wrapped_bundles(model)
    notes = [""] * len(q)
    if not bundles:
        return notes
    values = dict(zip(model.parameter_names, np.asarray(theta, float), strict=True))
    for i, (qi, flexion) in enumerate(zip(np.asarray(q, float), flexions, strict=True)):
        R, p = (np.asarray(v) for v in model.pose(qi, flexion, theta))
        found = []
        for lig, b in bundles:
            femur, tibia = lig.attachments(b, values)
            why = b.path.jump(femur, tibia, R, p.ravel())
            if why:
                found.append(f"{lig.name} bundle {b.name or lig.name!r}: {why}")
        notes[i] = "; ".join(found)
    return notes
