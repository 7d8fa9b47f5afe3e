"""Depth below the articular side of a thin closed shell (a segmented cartilage layer).

A femoral cartilage segmented from MRI is a closed shell 2-3 mm thick (S192803: 2.9 mm on average,
``2 volume / area``).  Its signed distance turns at mid-thickness: a point pressed 1.5 mm into the
layer is nearer the bone side than the articular side, so the distance shrinks again, the contact
force turns and the contact stiffness becomes negative.  On S192803 that happens from about 1.0-1.6 mm
of penetration; Newton then stalls on the load ramp and the knee snaps to another branch for a 0.5 %
change of a stiffness.  The elastic foundation's depth is measured from the articular surface, so
for a shell the field is :class:`ShellDistance`:

* outside the shell, where the nearest face is on the articular side: the signed distance itself;
* everywhere else (inside the layer, and behind its bone side): minus the distance to the articular
  faces, which keeps deepening through the layer and into the bone.

Both pieces meet continuously on the articular faces (zero) and on the bone-side faces (the same
distance on either side).  The bone side is the faces whose outward normal faces the flexion axis
(within :data:`BONE_SIDE_ANGLE`: the condyles wrap the axis and the trochlea lies in front of it);
the articular side (:func:`articular_faces`) is every other face, the rim's walls included, so that
a point beside the layer's edge is outside it as before and the only seam of the field lies behind
the layer, in the bone.  A mesh is a shell (:func:`shell_thickness`) when it is watertight and thinner than
:data:`SHELL_THICKNESS` on average; a bone, or a bone with an offset, is left as it is.
"""

from __future__ import annotations

import numpy as np
import trimesh

from kneenlp.geometry.distance import MeshDistance

#: A watertight mesh thinner than this on average (``2 volume / area``, m) is a cartilage shell; a
#: distal femur is 15 mm or more.
SHELL_THICKNESS = 6e-3
#: A face whose outward normal is within this angle (deg) of the direction to the flexion axis is on
#: the bone side (S192803: 4124 mm^2 of faces within 53 deg, 4200 mm^2 of the articular side beyond
#: 135 deg, 1000 mm^2 of rim walls between).
BONE_SIDE_ANGLE = 53.0


def shell_thickness(mesh: trimesh.Trimesh) -> float | None:
    """Mean thickness (m) of ``mesh`` if it is a thin closed shell (:data:`SHELL_THICKNESS`), else None."""
    if not mesh.is_watertight or mesh.area <= 0:
        return None
    thickness = 2.0 * abs(float(mesh.volume)) / float(mesh.area)
    return thickness if thickness < SHELL_THICKNESS else None


def articular_faces(mesh: trimesh.Trimesh, point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Faces (bool per face) of the articular side: all but those whose outward normal faces the axis
    through ``point`` along ``direction`` (the flexion axis; femoral frame, m) within :data:`BONE_SIDE_ANGLE`."""
    a = np.asarray(direction, float) / np.linalg.norm(direction)
    rel = np.asarray(mesh.triangles_center) - np.asarray(point, float)
    radial = rel - np.outer(rel @ a, a)
    radial /= np.maximum(np.linalg.norm(radial, axis=1), 1e-12)[:, None]
    return np.einsum("ij,ij->i", np.asarray(mesh.face_normals), radial) > -np.cos(np.radians(BONE_SIDE_ANGLE))


class ShellDistance:
    """The shell's field (module docstring) at points: ``(d, closest, gradient)`` as
    :class:`~kneenlp.geometry.distance.MeshDistance` returns them, with the articular faces'
    closest point and gradient where the depth below them is taken."""

    def __init__(self, mesh: trimesh.Trimesh, articular: np.ndarray):
        self.whole = MeshDistance(mesh)
        #: the articular side alone (an open surface; its vertex normals tell a far point's side)
        self.surface = mesh.submesh([np.flatnonzero(articular)], append=True)
        self.articular = MeshDistance(self.surface)

    def __call__(self, points: np.ndarray, certify: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d, closest, grad = self.whole(points, certify=certify)
        d_a, closest_a, grad_a = self.articular(points, certify=certify)
        # outside, with an articular face nearest: the distances to the whole and to that side agree
        outside = (d > 0) & (np.abs(d_a) <= np.abs(d) * (1 + 1e-9) + 1e-15)
        depth = -np.abs(d_a)
        sign = np.where(d_a < 0, 1.0, -1.0)[:, None]  # gradient of -|d_a|: away from the articular side
        return (np.where(outside, d, depth), np.where(outside[:, None], closest, closest_a),
                np.where(outside[:, None], grad, sign * grad_a))
