"""The femoral frame of a knee given in scanner coordinates, built from what a knee MRI has.

``coordinates = "scan"`` in a knee file: every point and mesh is in the scanner's frame.  kneenlp
maps it rigidly into the femoral frame (X anterior, Y proximal, Z lateral, origin at the knee
centre; :mod:`kneenlp.base.conventions`), ``x_femoral = rotation @ (x_scan - origin)``, built by one
of two methods (``frame = ...`` in the knee file):

* ``"cylinders"`` (default when the knee has a femoral mesh; the laxity-noise paper's procedure):
  ``Z`` is the flexion axis through the centres of cylinders fitted to the medial and lateral
  femoral articular surfaces (:func:`kneenlp.geometry.axes.fit_flexion_axis`), the origin is the
  midpoint of those centres (the knee centre), ``Y`` points to the hip centre (landmark
  ``hip_center``) made perpendicular to ``Z`` or, without it, along the scan's own ``Y`` axis.
  Without landmarks the scan axes must be roughly anatomical (X anterior, Y proximal, Z lateral
  within ~30 deg): they only choose the fitted region.
* ``"landmarks"``: ISB (Wu et al. 2002) from ``hip_center`` and the epicondyles; origin at the
  midpoint of the condyle centres (cylinder or explicit sphere centres).

The frame and the fits behind it are reported (:attr:`Frame.how`) so the user can check them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from kneenlp.base.errors import InputError


@dataclass(frozen=True)
class Frame:
    """Rigid map scan -> femoral frame (m): ``x_f = rotation @ (x - origin)``."""

    rotation: np.ndarray
    origin: np.ndarray
    how: str = "the file's coordinates are the femoral frame"

    @classmethod
    def identity(cls) -> Frame:
        return cls(np.eye(3), np.zeros(3))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        pts = np.asarray(points, dtype=float)
        return (pts - self.origin) @ self.rotation.T

    def direction(self, v: np.ndarray) -> np.ndarray:
        return np.asarray(v, float) @ self.rotation.T

    def mesh(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        out = mesh.copy()
        out.vertices = self(mesh.vertices)
        return out


def landmark_axes(landmarks: dict[str, np.ndarray], source: str) -> np.ndarray:
    """ISB femoral axes as the rows of a rotation (scan -> femoral): Y from the epicondyle
    midpoint to the hip centre, Z along the epicondylar axis made perpendicular to Y (towards the
    lateral epicondyle), X = Y x Z."""
    need = ("hip_center", "medial_epicondyle", "lateral_epicondyle")
    missing = [n for n in need if n not in landmarks]
    if missing:
        raise InputError(f"frame = 'landmarks' needs landmarks {', '.join(missing)}", source=source,
                         field="landmarks")
    mid = (landmarks["medial_epicondyle"] + landmarks["lateral_epicondyle"]) / 2
    y = landmarks["hip_center"] - mid
    z = landmarks["lateral_epicondyle"] - landmarks["medial_epicondyle"]
    y = y / np.linalg.norm(y)
    z = z - (z @ y) * y
    if np.linalg.norm(z) < 1e-9:
        raise InputError("epicondyles on the hip-knee line: frame undefined", source=source, field="landmarks")
    z = z / np.linalg.norm(z)
    return np.vstack([np.cross(y, z), y, z])


def axes_from_flexion(direction: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rotation whose Z is the flexion axis ``direction`` and whose Y is ``up`` made perpendicular."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    y = np.asarray(up, float) - (np.asarray(up, float) @ z) * z
    y = y / np.linalg.norm(y)
    return np.vstack([np.cross(y, z), y, z])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two directions (deg)."""
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
