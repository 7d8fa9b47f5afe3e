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

* :class:`EllipsoidWrap`: the shortest path over an ellipsoid fixed to the femur or the tibia
  (OpenSim's ``WrapEllipsoid``) among the paths that lie in one plane through both attachments:
  in the plane the section is an ellipse, an affine map makes it the unit circle (tangent points
  in closed form), the arc is a fixed Gauss-Legendre quadrature, and the plane is the one that
  makes the path shortest (Newton steps on its angle about the straight line, started in the plane
  of the ellipsoid's outward normal where the straight line runs deepest).  The path passes the
  ellipsoid on the side away from its centre.  It wraps only while the straight segment cuts the
  ellipsoid (OpenSim's rule); at the switch both lengths and their gradients agree.  OpenSim's
  ``hybrid`` method chooses its plane by a heuristic; on the Lenhart knee's MCL ellipsoids over
  laxity poses the two lengths agree to 0.006 mm (tests/test_osim_wraps.py).  The planar path is
  not the geodesic, which may be shorter by a little where the ellipsoid is far from a sphere.

Coordinates are the femoral frame (m), an obstacle's own in its body's frame.  A conditional
(``if_else``) chooses between wrapped and straight: the CasADi, C and NumPy exports carry it; the
AMPL ``.nl`` writer has no conditional and refuses such a knee with its one-line error.
"""

from __future__ import annotations

import dataclasses
import functools
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

    def wrench(self, tension: ca.SX) -> tuple[ca.SX, ca.SX]:
        """The force (N) and the moment about the tibial origin (N m) the path's ``tension`` (N)
        puts on the tibia."""
        force = tension * self.direction
        return force, ca.cross(self.arm, force)


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


class WrapPath(LigamentPath):
    """A path over an obstacle fixed to the femur or the tibia; the obstacle's :meth:`level` says
    where a point lies (< 1 inside)."""

    body: str
    #: the obstacle's name in messages
    shape = "obstacle"

    @abstractmethod
    def level(self, point: np.ndarray, R: np.ndarray, p: np.ndarray) -> float:
        """Where a femoral-frame ``point`` (m) lies with the tibia at ``R``, ``p``: < 1 inside the
        obstacle, 1 on its surface."""

    def inside(self, femur: np.ndarray, tibia: np.ndarray, R: np.ndarray, p: np.ndarray) -> list[str]:
        """Which attachments (``"femoral"``, ``"tibial"``) lie inside the obstacle at ``R``, ``p``."""
        points = {"femoral": np.asarray(femur, float), "tibial": R @ np.asarray(tibia, float) + p}
        return [name for name, x in points.items() if self.level(x, R, p) < 1]

    def jump(self, femur: np.ndarray, tibia: np.ndarray, R: np.ndarray, p: np.ndarray) -> str:
        """Why the path's length is not smooth near ``R``, ``p`` ("" where it is): an attachment
        inside the obstacle (the path is not defined; OpenSim runs it straight), or the path at
        the pose where it switches sides (:meth:`side_switch`)."""
        inside = self.inside(femur, tibia, R, p)
        if inside:
            return f"its {' and '.join(inside)} attachment lies inside the wrapping {self.shape}"
        return self.side_switch(femur, tibia, R, p)

    @abstractmethod
    def side_switch(self, femur: np.ndarray, tibia: np.ndarray, R: np.ndarray, p: np.ndarray) -> str:
        """Why the path at ``R``, ``p`` is near where it switches sides ("" if it is not)."""

    def wraps(self, femur: np.ndarray, tibia: np.ndarray, R: np.ndarray, p: np.ndarray) -> bool:
        """Whether the path touches the obstacle at ``R``, ``p`` (it is then longer than the line)."""
        straight = np.linalg.norm(np.asarray(femur, float) - (R @ np.asarray(tibia, float) + p))
        return self.length(femur, tibia, R, p) > straight * (1 + 1e-12)

    def placed(self, R: np.ndarray, p: np.ndarray, centre: np.ndarray, vectors) -> tuple[np.ndarray, ...]:
        """The obstacle's ``centre`` and direction ``vectors`` in the femoral frame (numbers)."""
        if self.body == "femur":
            return (np.asarray(centre), *[np.asarray(v) for v in vectors])
        return (R @ centre + p, *[R @ v for v in vectors])


def _placed(body: str, pose: Pose, centre: np.ndarray, vectors: tuple[np.ndarray, ...]) -> tuple[ca.SX, ...]:
    """An obstacle's ``centre`` and direction ``vectors`` (its body's frame) in the femoral frame."""
    if body == "femur":
        return (ca.DM(centre), *[ca.DM(v) for v in vectors])
    return (pose.p + pose.R @ ca.DM(centre), *[pose.R @ ca.DM(v) for v in vectors])


def _check_body(body: str, what: str) -> None:
    if body not in BODIES:
        raise ValueError(f"a wrapping {what} is fixed to the femur or the tibia, got {body!r}")


@dataclass(frozen=True)
class CylinderWrap(WrapPath):
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
        _check_body(self.body, "cylinder")
        if self.side not in (1, -1) or not self.radius > 0 or not np.linalg.norm(axis) > 0:
            raise ValueError("a wrapping cylinder needs a radius > 0, an axis and a side of +1 or -1")
        axis = axis / np.linalg.norm(axis)
        helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1)
        object.__setattr__(self, "axis", axis)
        object.__setattr__(self, "centre", np.asarray(self.centre, float))
        object.__setattr__(self, "basis", (e1, np.cross(axis, e1)))

    shape = "cylinder"

    def side_switch(self, femur, tibia, R, p) -> str:
        """The path goes the long way round: the straight line passes the axis on the other side,
        where OpenSim's path (the short way) switches sides and its length jumps."""
        other = dataclasses.replace(self, side=-self.side)
        if other.wraps(femur, tibia, R, p) and other.length(femur, tibia, R, p) < self.length(femur, tibia, R, p):
            return ("the straight line passes the wrapping cylinder's axis on the other side than declared: the path "
                    "goes the long way round (OpenSim's would switch sides there, its length jumping)")
        return ""

    def level(self, point, R, p) -> float:
        c, a = self.placed(R, p, self.centre, (self.axis,))
        v = np.asarray(point, float) - c
        return float((v @ v - (v @ a) ** 2) / self.radius**2)

    def route(self, femur, tibia, pose: Pose) -> Route:
        arm = pose.R @ tibia
        tibia = pose.p + arm  # the attachment in the femoral frame
        c, a, e1, e2 = _placed(self.body, pose, self.centre, (self.axis, *self.basis))
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


def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` Gauss-Legendre nodes and weights on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(n)
    return (x + 1) / 2, w / 2


#: Quadrature of an ellipsoid wrap's arc: 12 nodes integrate the arc of a section ellipse with
#: axes up to 1:3 to 1e-12 of its length; the plane is sought with 4 (the length's error is second
#: order in the plane's, so a slightly displaced minimum costs nothing measurable).
_ARC, _ARC_SEARCH = _gauss_legendre(12), _gauss_legendre(4)
#: Newton steps on the wrapping plane's angle: from the start plane two bring the length to 1e-10
#: of the shortest planar path's (a brute-force search, tests/test_paths.py), one to 5e-4.
_PLANE_STEPS = 2
#: A wrapped path whose straight line passes closer than this to the ellipsoid's centre (a fraction
#: of the way to its surface) is near where it switches sides (:meth:`EllipsoidWrap.side_switch`).
NEAR_CENTRE = 0.1
#: The angle step (rad) of the central differences of those Newton steps.
_PLANE_STEP = 0.02


@dataclass(frozen=True)
class EllipsoidWrap(WrapPath):
    """The shortest planar path over an ellipsoid of semi-axes ``radii`` (m) along the columns of
    ``axes`` (a rotation, its body's frame), centred at ``centre`` (m), fixed to ``body``; module
    docstring."""

    centre: np.ndarray
    axes: np.ndarray
    radii: np.ndarray
    body: str = "tibia"

    def __post_init__(self) -> None:
        _check_body(self.body, "ellipsoid")
        axes, radii = np.asarray(self.axes, float), np.asarray(self.radii, float)
        if axes.shape != (3, 3) or not np.allclose(axes.T @ axes, np.eye(3), atol=1e-9):
            raise ValueError("a wrapping ellipsoid's axes are the columns of a rotation matrix")
        if radii.shape != (3,) or not np.all(radii > 0):
            raise ValueError("a wrapping ellipsoid needs three semi-axes > 0")
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "radii", radii)
        object.__setattr__(self, "centre", np.asarray(self.centre, float))

    shape = "ellipsoid"

    def side_switch(self, femur, tibia, R, p) -> str:
        """The straight line passes within :data:`NEAR_CENTRE` of the centre (in the ellipsoid's own
        scale), where the side the path passes on flips and its length jumps."""
        centre, *axes = self.placed(R, p, self.centre, tuple(self.axes.T))
        frame = np.column_stack(axes)
        s, e = (ca.DM(frame.T @ (x - centre)) for x in (R @ np.asarray(tibia, float) + p, np.asarray(femur, float)))
        t, _, level = self.depth(s, e)
        t, level = float(t), float(level)
        near = np.sqrt(max(level, 0.0))
        if 0 < t < 1 and near < NEAR_CENTRE:
            return (f"the straight line passes {100 * near:.0f} % of the way from the wrapping ellipsoid's centre to "
                    "its surface, where the path switches sides and its length jumps")
        return ""

    def level(self, point, R, p) -> float:
        c, *axes = self.placed(R, p, self.centre, tuple(self.axes.T))
        x = np.array([(np.asarray(point, float) - c) @ a for a in axes])
        return float(np.sum((x / self.radii) ** 2))

    def local(self, pose: Pose, point: ca.SX) -> ca.SX:
        """A femoral-frame point in the ellipsoid's own axes about its centre (m)."""
        c, *axes = _placed(self.body, pose, self.centre, tuple(self.axes.T))
        return ca.vertcat(*[ca.dot(point - c, a) for a in axes])

    def depth(self, s: ca.SX, e: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX]:
        """Where the straight line from ``s`` to ``e`` (own axes) runs deepest: its parameter
        (0 at ``s``), the point, and the ellipsoid's level there (< 1 inside)."""
        D = ca.DM(1 / self.radii**2)
        d = e - s
        t = -ca.dot(s * D, d) / ca.dot(d * D, d)
        y = s + t * d
        return t, y, ca.dot(y * D, y)

    def planar(self, s: ca.SX, e: ca.SX, phi: ca.SX, arc_rule=_ARC) -> tuple[ca.SX, ca.SX, ca.SX, ca.SX]:
        """The path from ``s`` to ``e`` (own axes, outside) in the plane through both turned by
        ``phi`` (rad) about the straight line from the plane of the outward normal where the line
        runs deepest: its length (m), the tangent points seen from ``s`` and from ``e`` (own axes),
        and the arc's angle on the unit circle (> 0 where the plane's section is cut);
        ``arc_rule``: the quadrature's nodes and weights on [0, 1]."""
        D = ca.DM(1 / self.radii**2)
        chord = e - s
        span = ca.norm_2(chord)
        u = chord / span
        _, y, _ = self.depth(s, e)
        g = y * D
        g = g / ca.norm_2(g)
        w = ca.cross(u, g)
        v = ca.cos(phi) * g + ca.sin(phi) * w  # in-plane, across the line, towards the wrap
        quv = ca.dot(u * D, v)
        q11, q22 = ca.dot(u * D, u), ca.dot(v * D, v)
        b1, b2 = ca.dot(s * D, u), ca.dot(s * D, v)
        det = q11 * q22 - quv**2
        c1, c2 = -(q22 * b1 - quv * b2) / det, -(q11 * b2 - quv * b1) / det  # the section's centre
        rho = ca.fmax(-(b1 * c1 + b2 * c2) - (ca.dot(s * D, s) - 1), 1e-30)  # the section's size: (x-c)^T Q (x-c) = rho
        # Q = L^T L, L = [[l11, l12], [0, l22]]; z = L (x - c) / sqrt(rho) maps the section to the unit circle
        l11 = ca.sqrt(q11)
        l12 = quv / l11
        l22 = ca.sqrt(ca.fmax(q22 - l12**2, 1e-30))
        root = ca.sqrt(rho)

        def circle(x1, x2):
            return (l11 * (x1 - c1) + l12 * (x2 - c2)) / root, l22 * (x2 - c2) / root

        za, zb = circle(0, 0), circle(span, 0)
        ra, rb = ca.sqrt(za[0] ** 2 + za[1] ** 2), ca.sqrt(zb[0] ** 2 + zb[1] ** 2)
        th_a = ca.atan2(za[1], za[0]) - ca.acos(ca.fmin(1 / ra, 1))
        th_b = ca.atan2(zb[1], zb[0]) + ca.acos(ca.fmin(1 / rb, 1))
        arc = th_a - th_b
        arc = arc - 2 * np.pi * ca.floor((arc + np.pi) / (2 * np.pi))  # the short way, in [-pi, pi)

        def plane_point(th):
            x2 = c2 + root * ca.sin(th) / l22
            x1 = c1 + (root * ca.cos(th) - l12 * (x2 - c2)) / l11
            return x1, x2

        def speed(th):  # |dx/dtheta| in the plane
            dx2 = root * ca.cos(th) / l22
            dx1 = (-root * ca.sin(th) - l12 * dx2) / l11
            return ca.sqrt(dx1**2 + dx2**2)

        along = sum(float(wk) * speed(th_a - arc * float(xk)) for xk, wk in zip(*arc_rule, strict=True))
        ta, tb = plane_point(th_a), plane_point(th_b)
        first = ca.sqrt(ta[0] ** 2 + ta[1] ** 2)
        last = ca.sqrt((span - tb[0]) ** 2 + tb[1] ** 2)
        length = first + arc * along + last
        return length, s + ta[0] * u + ta[1] * v, s + tb[0] * u + tb[1] * v, arc

    def wrapped(self, s: ca.SX, e: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX, ca.SX]:
        """The shortest planar path from ``s`` to ``e`` (own axes): its length, tangent points
        and arc angle (:meth:`planar`) in the plane found by Newton steps on the angle, the
        derivatives by central differences of :data:`_PLANE_STEP` (a parabola through three
        planes: exact derivatives of the length would triple the expression for nothing the
        length can see)."""
        angle, h = ca.SX(0), _PLANE_STEP
        for _ in range(_PLANE_STEPS):
            low, mid, high = (self.planar(s, e, angle + d, _ARC_SEARCH)[0] for d in (-h, 0.0, h))
            angle = angle - h / 2 * (high - low) / ca.fmax(high - 2 * mid + low, 1e-9 * h**2 * mid)
        return self.planar(s, e, angle)

    @functools.cached_property
    def _function(self) -> ca.Function:
        """The length (:meth:`path_length`), the tangent points seen from the start and from the
        end (femoral frame) and whether the path wraps, as a function of the start, the end, the
        centre and the axes (built once per path; not pickled)."""
        x, end, c, frame = ca.SX.sym("x", 3), ca.SX.sym("end", 3), ca.SX.sym("c", 3), ca.SX.sym("A", 3, 3)
        s, e = frame.T @ (x - c), frame.T @ (end - c)
        t, _, level = self.depth(s, e)
        length, first, last, arc = self.wrapped(s, e)
        active = ca.logic_and(ca.logic_and(t > 0, t < 1), ca.logic_and(level < 1, arc > 0))
        length = ca.if_else(active, length, ca.norm_2(end - x))
        return ca.Function("ellipsoid_path", [x, end, c, frame], [length, c + frame @ first, c + frame @ last, active])

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_function"}

    def length(self, femur, tibia, R, p) -> float:
        centre, *axes = self.placed(R, p, self.centre, tuple(self.axes.T))
        start = R @ np.asarray(tibia, float) + p
        return float(self._function(start, np.asarray(femur, float), centre, np.column_stack(axes))[0])

    def route(self, femur, tibia, pose: Pose) -> Route:
        """The tension runs along the free segments, as OpenSim applies a wrapped path's force: the
        tibia feels the first segment at its attachment (an ellipsoid of the femur) or the last
        at its tangent point (an ellipsoid of the tibia).  The planar path is not a geodesic, so
        this force differs from the length's gradient by up to ~0.1 % of the tension (a geodesic's
        would be exact)."""
        arm = pose.R @ tibia
        start = pose.p + arm  # the tibial attachment in the femoral frame
        centre, *axes = _placed(self.body, pose, self.centre, tuple(self.axes.T))
        length, first, last, active = self._function(start, femur, centre, ca.horzcat(*axes))
        chord = femur - start
        straight = chord / ca.norm_2(chord)
        if self.body == "femur":
            to = first - start
            return Route(length, arm, ca.if_else(active, to / ca.norm_2(to), straight))
        out = femur - last
        return Route(length, ca.if_else(active, last - pose.p, arm), ca.if_else(active, out / ca.norm_2(out), straight))
