"""A ligament bundle's path from its tibial to its femoral attachment: a part beside its law.

A path gives, at a pose, the bundle's length and where and along which line its tension pulls the
tibia (:class:`Route`).  Both are exact CasADi expressions of the pose, so the equilibrium, the
simultaneous NLP and the sensitivities keep exact derivatives.

* :class:`StraightPath` (the default): the straight line between the attachments.
* :class:`ViaPoints`: straight segments through points fixed to the tibia, then to the femur.
* :class:`CylinderWrap`: the shortest path that does not enter a cylinder fixed to the femur or
  the tibia (a bone's rim or condyle; OpenSim's ``WrapCylinder``): straight to a tangent point, a
  helix on the cylinder, straight from the other tangent point.  In the plane across the axis the
  path leaves the tibial attachment, touches the circle and goes round it on the path's ``side``
  (+1: counterclockwise about the axis, -1: clockwise) to the tangent point seen from the femoral
  attachment; unrolled, the cylinder is a plane and the geodesic a straight line, so the length is
  ``sqrt(planar^2 + dz^2)`` with ``planar = t_s + r beta + t_e`` (tangent lengths and arc) and
  ``dz`` the axial distance of the attachments (closed form, Garner & Pandy 2000).  The path wraps
  only while the straight segment would cut the circle; at the switch both lengths and their
  first derivatives agree.  The tibia feels the tension at the last point of the path fixed to it
  (its attachment for a femoral cylinder, the femoral-side tangent point for a tibial one), along
  the path's next segment; the cylinder of the femur takes the rest (the femur is fixed).

Coordinates are the femoral frame (m), a cylinder's own in its body's frame.  A conditional
(``if_else``) chooses between wrapped and straight: the CasADi, C and NumPy exports carry it; the
AMPL ``.nl`` writer has no conditional and refuses such a knee with its one-line error.
"""

from __future__ import annotations

import itertools
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from kneenlp.model.elements import Pose

#: Bodies a path's obstacle can be fixed to.
BODIES = ("femur", "tibia")


@dataclass(frozen=True)
class Route:
    """A path at a pose: its ``length`` (m), the ``arm`` from the tibial origin to the point where
    its tension acts on the tibia and the unit ``direction`` it pulls the tibia along (femoral
    frame's axes, m)."""

    length: ca.SX
    arm: ca.SX
    direction: ca.SX


class LigamentPath(ABC):
    """How a bundle runs from its tibial to its femoral attachment (module docstring); each kind
    of path implements :meth:`route`."""

    @abstractmethod
    def route(self, femur: ca.SX, tibia: ca.SX, pose: Pose) -> Route:
        """The path from the tibial attachment ``tibia`` (tibial frame) to the femoral one ``femur``
        (femoral frame) with the tibia at ``pose`` (m)."""

    def length(self, femur: np.ndarray, tibia: np.ndarray, R: np.ndarray, p: np.ndarray) -> float:
        """The path's length (m) with the tibia at rotation ``R`` and origin ``p`` (numbers)."""
        pose = Pose(ca.DM(R), ca.DM(p), ca.DM.zeros(5), ca.DM(0))
        return float(self.route(ca.DM(femur), ca.DM(tibia), pose).length)


@dataclass(frozen=True)
class StraightPath(LigamentPath):
    """The straight line between the attachments."""

    def route(self, femur, tibia, pose: Pose) -> Route:
        arm = pose.R @ tibia
        u = femur - (pose.p + arm)
        length = ca.norm_2(u)
        return Route(length, arm, u / length)


@dataclass(frozen=True)
class ViaPoints(LigamentPath):
    """Straight segments through via points: ``tibia`` points (tibial frame) from the tibial
    attachment outwards, then ``femur`` points (femoral frame) towards the femoral attachment (m).
    The tibia feels the segment from its last point to the femur's first."""

    tibia: tuple[tuple[float, float, float], ...] = ()
    femur: tuple[tuple[float, float, float], ...] = ()

    def route(self, femur, tibia, pose: Pose) -> Route:
        arms = [pose.R @ tibia, *[pose.R @ ca.DM(v) for v in self.tibia]]
        chain = [pose.p + arm for arm in arms] + [ca.DM(v) for v in self.femur] + [femur]
        length = sum((ca.norm_2(b - a) for a, b in itertools.pairwise(chain)), ca.DM(0))
        pull = chain[len(arms)] - chain[len(arms) - 1]
        return Route(length, arms[-1], pull / ca.norm_2(pull))


@dataclass(frozen=True)
class CylinderWrap(LigamentPath):
    """The shortest path about a cylinder of ``radius`` (m) through ``centre`` along ``axis`` (its
    ``body``'s frame, m), passing it on ``side`` (+1 counterclockwise about ``axis`` going from the
    tibial to the femoral attachment, -1 clockwise); module docstring."""

    centre: np.ndarray
    axis: np.ndarray
    radius: float
    body: str = "femur"
    side: int = 1
    #: two unit vectors across the axis (its body's frame), with ``axis`` a right-handed basis
    basis: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        axis = np.asarray(self.axis, float)
        if self.body not in BODIES:
            raise ValueError(f"a wrapping cylinder is fixed to the femur or the tibia, got {self.body!r}")
        if self.side not in (1, -1) or not self.radius > 0 or not np.linalg.norm(axis) > 0:
            raise ValueError("a wrapping cylinder needs a radius > 0, an axis and a side of +1 or -1")
        axis = axis / np.linalg.norm(axis)
        helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1)
        object.__setattr__(self, "axis", axis)
        object.__setattr__(self, "centre", np.asarray(self.centre, float))
        object.__setattr__(self, "basis", (e1, np.cross(axis, e1)))

    def _frame(self, pose: Pose) -> tuple[ca.SX, ...]:
        """Centre, axis and the two cross vectors in the femoral frame."""
        vectors = [ca.DM(v) for v in (self.centre, self.axis, *self.basis)]
        if self.body == "femur":
            return tuple(vectors)
        c, a, e1, e2 = vectors
        return pose.p + pose.R @ c, pose.R @ a, pose.R @ e1, pose.R @ e2

    def route(self, femur, tibia, pose: Pose) -> Route:
        arm = pose.R @ tibia
        tibia = pose.p + arm  # the attachment in the femoral frame
        c, a, e1, e2 = self._frame(pose)
        r, side = self.radius, float(self.side)
        s, e = tibia - c, femur - c
        xs, ys, zs = ca.dot(s, e1), side * ca.dot(s, e2), ca.dot(s, a)
        xe, ye, ze = ca.dot(e, e1), side * ca.dot(e, e2), ca.dot(e, a)
        ds2, de2 = xs**2 + ys**2, xe**2 + ye**2
        ts, te = ca.sqrt(ca.fmax(ds2 - r**2, 0)), ca.sqrt(ca.fmax(de2 - r**2, 0))  # tangent lengths
        gap = ca.atan2(ye, xe) - ca.atan2(ys, xs)
        gap = gap - 2 * np.pi * ca.floor(gap / (2 * np.pi))  # counterclockwise, in [0, 2 pi)
        beta = gap - ca.atan2(ts, r) - ca.atan2(te, r)  # the arc on the cylinder
        planar = ts + te + r * beta
        dz = ze - zs
        wrapped = ca.sqrt(planar**2 + dz**2)
        chord = femur - tibia
        straight = ca.norm_2(chord)
        # the straight segment's nearest point to the axis, across it
        sx, sy = xe - xs, ye - ys
        t = ca.fmin(ca.fmax(-(xs * sx + ys * sy) / (sx**2 + sy**2 + 1e-30), 0), 1)
        active = ca.logic_and((xs + t * sx) ** 2 + (ys + t * sy) ** 2 < r**2, beta > 0)
        length = ca.if_else(active, wrapped, straight)
        if self.body == "femur":  # the tibia feels the first segment, at its attachment
            theta = ca.atan2(ys, xs) + ca.atan2(ts, r)
            z = zs + dz * ts / planar
            tangent = c + r * ca.cos(theta) * e1 + side * r * ca.sin(theta) * e2 + z * a
            first = tangent - tibia
            direction = ca.if_else(active, first / ca.norm_2(first), chord / straight)
            return Route(length, arm, direction)
        theta = ca.atan2(ye, xe) - ca.atan2(te, r)  # the tibia's cylinder: the last segment, at its tangent point
        z = ze - dz * te / planar
        tangent = c + r * ca.cos(theta) * e1 + side * r * ca.sin(theta) * e2 + z * a
        last = femur - tangent
        return Route(length, ca.if_else(active, tangent - pose.p, arm),
                     ca.if_else(active, last / ca.norm_2(last), chord / straight))
