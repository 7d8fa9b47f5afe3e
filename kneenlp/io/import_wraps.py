"""An OpenSim bundle's wrapping surface as a kneenlp path (:mod:`kneenlp.model.paths`).

OpenSim's ``WrapCylinder`` becomes a cylinder wrap, its ``WrapEllipsoid`` (and ``WrapSphere``, an
ellipsoid of equal radii) an ellipsoid wrap, fixed to the knee's femur or tibia body they sit on
(or on a body welded to it).  OpenSim's unconstrained wrap (``quadrant`` all) goes round the short
way: a cylinder's side is the side the straight line passes the axis on in the model's default
pose, an ellipsoid's path passes on the side away from its centre (as kneenlp's).

What a kneenlp path cannot be is left straight and said (:func:`wrap_table` returns a note):
several wraps on one bundle, another shape, a constrained quadrant, a surface on another body, and
an attachment inside the surface in the default pose, where OpenSim itself runs the path straight
(the Lenhart knee's MCLp1: its tibial attachment lies inside ``Med_LigP_r``).
"""

from __future__ import annotations

import numpy as np

from kneenlp.io.osim import LineElement, OsimModel
from kneenlp.io.osim.model import rot_body_xyz

#: The OpenSim wrap surfaces kneenlp represents.
SHAPES = ("WrapCylinder", "WrapEllipsoid", "WrapSphere")


def _in_body(model: OsimModel, body: str, on: str, translation: np.ndarray, rotation: np.ndarray):
    """A surface placed at ``translation`` with axes ``rotation`` in body ``on`` -> in ``body``."""
    X = model.transform(body, on)
    return X[:3, :3] @ translation + X[:3, 3], X[:3, :3] @ rotation


def wrap_table(model: OsimModel, line: LineElement, bodies: dict[str, str]) -> tuple[dict | None, str | None]:
    """The knee file's ``wrap`` table (m, the body's frame) of ``line``'s wrapping surface and a
    note on what was left straight; ``bodies``: the knee's body names by role (``femur``,
    ``tibia``).  ``(None, None)``: the bundle does not wrap."""
    if not line.wraps:
        return None, None
    name = line.name
    if len(line.wraps) > 1:
        return None, f"{name}: wraps {len(line.wraps)} surfaces ({', '.join(line.wraps)}); kneenlp wraps one (straight)"
    wo = model.wrap_objects.get(line.wraps[0])
    if wo is None or wo.type not in SHAPES:
        what = "not found" if wo is None else f"a {wo.type}"
        return None, f"{name}: its wrap surface {line.wraps[0]!r} is {what} (straight)"
    if wo.quadrant not in ("all", ""):
        return None, f"{name}: {wo.name} is constrained to quadrant {wo.quadrant!r} (straight)"
    role = next((r for r, b in bodies.items() if wo.body in model.welded_bodies(b)), None)
    if role is None:
        return None, f"{name}: {wo.name} is on {wo.body}, neither the femur nor the tibia (straight)"
    centre, axes = _in_body(model, bodies[role], wo.body, wo.translation, rot_body_xyz(wo.xyz_body_rotation))
    femur, tibia = line.femoral_point, line.tibial_point  # the frames coincide in the default pose
    if wo.type == "WrapCylinder":
        radius = float(wo.dimensions["radius"][0])
        axis = axes[:, 2]
        inside = [n for n, x in (("femoral", femur), ("tibial", tibia))
                  if np.linalg.norm((x - centre) - ((x - centre) @ axis) * axis) < radius]
        turn = np.cross(tibia - centre, femur - centre) @ axis  # > 0: the short way is counterclockwise
        table = {"shape": "cylinder", "body": role, "centre": _floats(centre), "axis": _floats(axis),
                 "radius": radius, "side": "positive" if turn > 0 else "negative"}
    else:
        radii = (np.repeat(wo.dimensions["radius"][0], 3) if wo.type == "WrapSphere"
                 else np.asarray(wo.dimensions["dimensions"], float))
        inside = [n for n, x in (("femoral", femur), ("tibial", tibia))
                  if np.sum((axes.T @ (x - centre) / radii) ** 2) < 1]
        table = {"shape": "ellipsoid", "body": role, "centre": _floats(centre),
                 "axes": [_floats(a) for a in axes.T], "radii": _floats(radii)}
    if inside:
        return None, (f"{name}: its {' and '.join(inside)} attachment lies inside {wo.name} in the default pose, "
                      "where OpenSim runs the path straight (straight)")
    return table, None


def _floats(v) -> list[float]:
    return [float(x) for x in v]
