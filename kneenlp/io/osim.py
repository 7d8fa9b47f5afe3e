"""Self-contained reader for OpenSim / OpenSim JAM knee models (.osim) and a
calibrated-model writer.

Only numpy and the standard library are used (``xml.etree.ElementTree``); the
``opensim`` package is *not* needed (it cannot load OpenSim JAM classes such as
``Smith2018ContactMesh`` anyway).  It is used only as an external oracle in the
tests.

Units: everything is returned exactly as stored in the file, which for OpenSim
models is SI (lengths in m, angles in rad, forces in N).  ``OsimModel.length_units``
and ``force_units`` give what the file declares.

Conventions (all verified against the ``opensim`` 4.6 package, see test_osim.py):

* Homogeneous transforms are 4x4 numpy arrays ``X_AB`` that map coordinates of a
  point expressed in frame B to frame A: ``p_A = X_AB[:3,:3] @ p_B + X_AB[:3,3]``.
* ``PhysicalOffsetFrame.orientation`` (and wrap-object ``xyz_body_rotation``,
  contact-mesh ``orientation``) are body-fixed X-Y-Z Euler angles in rad:
  ``R = Rx(a) @ Ry(b) @ Rz(c)``; ``translation`` is expressed in the parent frame.
* ``CustomJoint`` ``SpatialTransform``: ``X_FM = [R1 R2 R3 | sum_i t_i*axis_i]`` where
  ``R_k`` is a rotation by ``f_k(q)`` about ``axis_k`` (body-fixed sequence
  rotation1, rotation2, rotation3) and the three translations are along their
  axes expressed in the joint's parent frame F.
* A joint places its child frame M relative to its parent frame F:
  ``X_G,childbody = X_G,F @ X_FM(q) @ inv(X_childbody,M)``.

Public API (see docstrings): :func:`read_osim`, :class:`OsimModel`
(``body_transforms``, ``transform``, ``point_in_body``, ``frame_in_body``),
:func:`ligament_groups`, :func:`knee_line_elements`, :func:`blankevoort_force`,
:func:`write_calibrated`, :func:`write_opensim_loadable_copy`, :class:`OsimError`.
"""
from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from kneenlp.io.atomic import write_text_atomic

__all__ = [
    "BLANKEVOORT_DEFAULTS",
    "JAM_ONLY_CLASSES",
    "BodyInfo",
    "ContactMesh",
    "Coordinate",
    "Joint",
    "Ligament",
    "LineElement",
    "MeshGeometry",
    "OffsetFrame",
    "OsimError",
    "OsimModel",
    "PathPoint",
    "TransformAxis",
    "WrapObject",
    "blankevoort_force",
    "knee_line_elements",
    "ligament_groups",
    "read_osim",
    "rot_body_xyz",
    "write_calibrated",
    "write_opensim_loadable_copy",
]


class OsimError(ValueError):
    """One-line error about an .osim file; the message names the file and the element."""


#: OpenSim 4.x defaults of Blankevoort1991Ligament properties that may be omitted in a file
#: (transition_strain [-], damping_coefficient [N*s per unit strain rate], i.e. force/strain-rate).
BLANKEVOORT_DEFAULTS: dict[str, float] = {"transition_strain": 0.06, "damping_coefficient": 0.003}

#: Classes that exist only in the OpenSim JAM plugin (not in the opensim wheel).
JAM_ONLY_CLASSES: tuple[str, ...] = ("Smith2018ArticularContactForce", "Smith2018ContactMesh")

_LIGAMENT_TAG = "Blankevoort1991Ligament"
_SKIPPED_POINT_TAGS = ("ConditionalPathPoint", "MovingPathPoint")
_WRAP_TAGS = ("WrapEllipsoid", "WrapCylinder", "WrapSphere", "WrapTorus", "WrapCylinderObst",
              "WrapDoubleCylinderObst", "WrapSphereObst")
_SUPPORTED_JOINTS = ("CustomJoint", "WeldJoint", "PinJoint", "SliderJoint")


# --------------------------------------------------------------------------------------
# small math helpers
# --------------------------------------------------------------------------------------
def _axis_rot(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix for ``angle`` [rad] about unit-normalised ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float)
    n = np.linalg.norm(a)
    if n == 0.0:
        raise ValueError("zero rotation axis")
    a = a / n
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def rot_body_xyz(angles: Sequence[float]) -> np.ndarray:
    """OpenSim frame orientation: body-fixed X-Y-Z Euler angles [rad] -> 3x3 rotation.

    ``R = Rx(angles[0]) @ Ry(angles[1]) @ Rz(angles[2])`` (columns = child axes in parent).
    """
    a, b, c = (float(v) for v in angles)
    return (_axis_rot(np.array([1.0, 0, 0]), a) @ _axis_rot(np.array([0, 1.0, 0]), b)
            @ _axis_rot(np.array([0, 0, 1.0]), c))


def _xform(R: np.ndarray | None = None, p: Sequence[float] | None = None) -> np.ndarray:
    X = np.eye(4)
    if R is not None:
        X[:3, :3] = R
    if p is not None:
        X[:3, 3] = np.asarray(p, float)
    return X


def _inv(X: np.ndarray) -> np.ndarray:
    R, p = X[:3, :3], X[:3, 3]
    return _xform(R.T, -R.T @ p)


def _apply(X: np.ndarray, p: Sequence[float]) -> np.ndarray:
    return X[:3, :3] @ np.asarray(p, float) + X[:3, 3]


# --------------------------------------------------------------------------------------
# OpenSim functions (used by CustomJoint TransformAxis)
# --------------------------------------------------------------------------------------
class _Function(ABC):
    """Callable f(x0, x1, ...) -> float built from an OpenSim Function element."""

    @abstractmethod
    def __call__(self, *x: float) -> float:
        """The function's value at the coordinate values ``x``."""


class _Constant(_Function):
    def __init__(self, value: float):
        self.value = value

    def __call__(self, *x: float) -> float:
        return self.value


class _Linear(_Function):
    def __init__(self, slope: float, intercept: float):
        self.slope, self.intercept = slope, intercept

    def __call__(self, *x: float) -> float:
        return self.slope * x[0] + self.intercept


class _Multiplier(_Function):
    def __init__(self, inner: _Function, scale: float):
        self.inner, self.scale = inner, scale

    def __call__(self, *x: float) -> float:
        return self.scale * self.inner(*x)


class _PiecewiseLinear(_Function):
    def __init__(self, x: np.ndarray, y: np.ndarray):
        self.x, self.y = x, y

    def __call__(self, *v: float) -> float:
        x, y, t = self.x, self.y, v[0]
        if len(x) == 1:
            return float(y[0])
        if t < x[0]:  # OpenSim extrapolates with the end segments' slopes
            return float(y[0] + (y[1] - y[0]) / (x[1] - x[0]) * (t - x[0]))
        if t > x[-1]:
            return float(y[-1] + (y[-1] - y[-2]) / (x[-1] - x[-2]) * (t - x[-1]))
        return float(np.interp(t, x, y))


class _SimmSpline(_Function):
    """Cubic spline of SIMM/OpenSim ``SimmSpline`` (Forsythe-Malcolm-Moler end conditions:
    the end third derivatives match those of the cubic through the 4 end points; linear for
    2 points).  Outside [x0, xn] it extrapolates linearly with the end slopes."""

    def __init__(self, x: np.ndarray, y: np.ndarray):
        n = len(x)
        if n < 2 or len(y) != n:
            raise ValueError("SimmSpline needs >= 2 points and equal x/y lengths")
        self.x, self.y = np.asarray(x, float), np.asarray(y, float)
        self.b, self.c, self.d = self._coefficients(self.x, self.y)

    @staticmethod
    def _coefficients(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(x)
        b, c, d = np.zeros(n), np.zeros(n), np.zeros(n)
        if n < 3:
            b[:] = (y[1] - y[0]) / (x[1] - x[0])
            return b, c, d
        m = n - 1
        d[0] = x[1] - x[0]
        c[1] = (y[1] - y[0]) / d[0]
        for i in range(1, m):
            d[i] = x[i + 1] - x[i]
            b[i] = 2.0 * (d[i - 1] + d[i])
            c[i + 1] = (y[i + 1] - y[i]) / d[i]
            c[i] = c[i + 1] - c[i]
        b[0] = -d[0]
        b[m] = -d[n - 2]
        c[0] = c[m] = 0.0
        if n > 3:
            c[0] = c[2] / (x[3] - x[1]) - c[1] / (x[2] - x[0])
            c[m] = c[n - 2] / (x[m] - x[n - 3]) - c[n - 3] / (x[n - 2] - x[n - 4])
            c[0] = c[0] * d[0] ** 2 / (x[3] - x[0])
            c[m] = -c[m] * d[n - 2] ** 2 / (x[m] - x[n - 4])
        for i in range(1, n):  # forward elimination
            t = d[i - 1] / b[i - 1]
            b[i] -= t * d[i - 1]
            c[i] -= t * c[i - 1]
        c[m] /= b[m]  # back substitution
        for i in range(m - 1, -1, -1):
            c[i] = (c[i] - d[i] * c[i + 1]) / b[i]
        b[m] = (y[m] - y[n - 2]) / d[n - 2] + d[n - 2] * (c[n - 2] + 2.0 * c[m])
        for i in range(m):
            b[i] = (y[i + 1] - y[i]) / d[i] - d[i] * (c[i + 1] + 2.0 * c[i])
            d[i] = (c[i + 1] - c[i]) / d[i]
            c[i] = 3.0 * c[i]
        c[m] = 3.0 * c[m]
        d[m] = d[n - 2]
        return b, c, d

    def __call__(self, *v: float) -> float:
        x, y, t = self.x, self.y, float(v[0])
        if t < x[0]:
            return float(y[0] + self.b[0] * (t - x[0]))
        if t > x[-1]:
            return float(y[-1] + self.b[-1] * (t - x[-1]))
        i = int(np.clip(np.searchsorted(x, t, side="right") - 1, 0, len(x) - 2))
        dx = t - x[i]
        return float(y[i] + dx * (self.b[i] + dx * (self.c[i] + dx * self.d[i])))


class _Unsupported(_Function):
    """Placeholder for a function type this reader does not evaluate; raises when called."""

    def __init__(self, message: str):
        self.message = message

    def __call__(self, *x: float) -> float:
        raise OsimError(self.message)


# --------------------------------------------------------------------------------------
# data classes
# --------------------------------------------------------------------------------------
@dataclass
class MeshGeometry:
    """A ``Mesh`` attached to a frame.  ``frame`` is the absolute path of the frame it is
    attached to, ``body`` the body that frame is fixed to; ``scale_factors`` unitless."""
    name: str
    mesh_file: str
    frame: str
    body: str
    scale_factors: np.ndarray


@dataclass
class BodyInfo:
    """An OpenSim ``Body`` (or ground).  mass [kg], mass_center [m] in the body frame."""
    name: str
    path: str
    mass: float
    mass_center: np.ndarray
    meshes: list[MeshGeometry] = field(default_factory=list)


@dataclass
class OffsetFrame:
    """A ``PhysicalOffsetFrame``: ``translation`` [m] in the parent frame and
    ``orientation`` [rad] body-fixed XYZ relative to the parent frame."""
    name: str
    path: str
    parent: str
    translation: np.ndarray
    orientation: np.ndarray

    @property
    def X_parent(self) -> np.ndarray:
        """4x4 transform parent <- this frame."""
        return _xform(rot_body_xyz(self.orientation), self.translation)


@dataclass
class Coordinate:
    """A joint ``Coordinate``: default_value and range in rad (rotational) or m."""
    name: str
    joint: str
    default_value: float
    range: tuple[float, float]
    locked: bool
    clamped: bool


@dataclass
class TransformAxis:
    """One axis of a CustomJoint SpatialTransform: value = function(coordinates...)."""
    name: str
    coordinates: tuple[str, ...]
    axis: np.ndarray
    function: _Function
    function_type: str


@dataclass
class Joint:
    """A joint; ``parent_frame``/``child_frame`` are absolute frame paths."""
    name: str
    type: str
    parent_frame: str
    child_frame: str
    coordinates: list[Coordinate]
    transform_axes: list[TransformAxis]


@dataclass
class PathPoint:
    """A fixed ``PathPoint``: ``location`` [m] in ``frame`` (absolute path) and
    ``location_in_body`` [m] in the frame of ``body`` (offset frames composed)."""
    name: str
    frame: str
    body: str
    location: np.ndarray
    location_in_body: np.ndarray


@dataclass
class Ligament:
    """A ``Blankevoort1991Ligament`` bundle.

    linear_stiffness [N per unit strain], slack_length [m], transition_strain [-],
    damping_coefficient [N per unit strain rate, i.e. N*s].  ``from_file`` lists the
    properties present in the XML (others are the OpenSim defaults).  ``points`` are the
    fixed path points in path order; ``wraps`` the names of PathWrap objects;
    ``skipped`` human-readable notes about what was ignored (wraps, conditional/moving
    points)."""
    name: str
    linear_stiffness: float
    slack_length: float
    transition_strain: float
    damping_coefficient: float
    applies_force: bool
    points: list[PathPoint]
    wraps: list[str]
    skipped: list[str]
    from_file: tuple[str, ...]

    @property
    def bodies(self) -> tuple[str, ...]:
        """Bodies of the fixed path points, in path order."""
        return tuple(p.body for p in self.points)


@dataclass
class ContactMesh:
    """A ``Smith2018ContactMesh``: mesh files as written (relative to the model's
    Geometry search path), ``location`` [m] / ``orientation`` [rad, body-fixed XYZ] of the
    mesh in ``frame``; thickness [m], elastic_modulus [Pa], poissons_ratio [-]."""
    name: str
    mesh_file: str
    mesh_back_file: str | None
    frame: str
    body: str
    location: np.ndarray
    orientation: np.ndarray
    thickness: float
    elastic_modulus: float
    poissons_ratio: float
    use_variable_thickness: bool

    def X_body_mesh(self, model: OsimModel) -> np.ndarray:
        """4x4 transform body <- mesh coordinates."""
        return model.frame_in_body(self.frame)[1] @ _xform(rot_body_xyz(self.orientation),
                                                            self.location)


@dataclass
class WrapObject:
    """A wrap surface (type e.g. WrapEllipsoid) on ``body``: translation [m], body-fixed
    XYZ rotation [rad] and raw dimension properties (m)."""
    name: str
    type: str
    body: str
    translation: np.ndarray
    xyz_body_rotation: np.ndarray
    dimensions: dict[str, np.ndarray]


# --------------------------------------------------------------------------------------
# the model
# --------------------------------------------------------------------------------------
@dataclass
class OsimModel:
    """Parsed .osim model.  Dicts keep file order.  ``skipped`` lists one-line notes about
    components that were recognised but not (fully) represented."""
    path: str
    name: str
    length_units: str
    force_units: str
    bodies: dict[str, BodyInfo]
    frames: dict[str, OffsetFrame]
    joints: dict[str, Joint]
    coordinates: dict[str, Coordinate]
    ligaments: dict[str, Ligament]
    contact_meshes: dict[str, ContactMesh]
    wrap_objects: dict[str, WrapObject]
    skipped: list[str]

    # ---- frames --------------------------------------------------------------------
    def body_path(self, body: str) -> str:
        """Absolute path of a body name ('ground' -> '/ground')."""
        return "/ground" if body == "ground" else f"/bodyset/{body}"

    def frame_in_body(self, frame: str) -> tuple[str, np.ndarray]:
        """Resolve a frame path (body, ground or PhysicalOffsetFrame chain) to
        ``(body_name, X_body_frame)`` with X a 4x4 transform body <- frame."""
        X = np.eye(4)
        seen: set[str] = set()
        cur = frame
        while cur in self.frames:
            if cur in seen:
                raise OsimError(f"{self.path}: cyclic PhysicalOffsetFrame chain at '{cur}'")
            seen.add(cur)
            f = self.frames[cur]
            X = f.X_parent @ X
            cur = f.parent
        if cur == "/ground":
            return "ground", X
        if cur.startswith("/bodyset/") and cur[len("/bodyset/"):] in self.bodies:
            return cur[len("/bodyset/"):], X
        raise OsimError(f"{self.path}: frame '{frame}' does not resolve to a body or ground")

    def default_coordinates(self) -> dict[str, float]:
        """Coordinate name -> default_value (rad or m)."""
        return {n: c.default_value for n, c in self.coordinates.items()}

    def joint_transform(self, joint: str, coords: Mapping[str, float] | None = None) -> np.ndarray:
        """X_FM (4x4) of a joint: its child frame M in its parent frame F at ``coords``
        (missing coordinates take their default values)."""
        j = self.joints[joint]
        q = self.default_coordinates()
        if coords:
            q.update(coords)
        if j.type == "WeldJoint":
            return np.eye(4)
        if j.type == "PinJoint":  # rotation about Z of F
            return _xform(_axis_rot(np.array([0, 0, 1.0]), q[j.coordinates[0].name]))
        if j.type == "SliderJoint":  # translation along X of F
            return _xform(None, [q[j.coordinates[0].name], 0, 0])
        if j.type == "CustomJoint":
            R = np.eye(3)
            p = np.zeros(3)
            for ta in j.transform_axes:
                try:
                    val = ta.function(*[q[c] for c in ta.coordinates])
                except KeyError as e:
                    raise OsimError(f"{self.path}: CustomJoint '{joint}' TransformAxis "
                                    f"'{ta.name}' uses unknown coordinate {e}") from None
                if ta.name.startswith("rotation"):
                    R = R @ _axis_rot(ta.axis, val)
                else:
                    n = np.linalg.norm(ta.axis)
                    p = p + val * ta.axis / n
            return _xform(R, p)
        raise OsimError(f"{self.path}: joint '{joint}' of type {j.type} is not supported for "
                        f"kinematics (supported: {', '.join(_SUPPORTED_JOINTS)})")

    def body_transforms(self, coords: Mapping[str, float] | None = None,
                        bodies: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """X_ground_body (4x4) for each body at ``coords`` (default values where missing).

        Only bodies on the path from ground to the requested ``bodies`` are evaluated, so a
        model with unsupported joints elsewhere still works.  Default: all bodies."""
        child_joint: dict[str, Joint] = {}
        for j in self.joints.values():
            b, _ = self.frame_in_body(j.child_frame)
            child_joint[b] = j
        out: dict[str, np.ndarray] = {"ground": np.eye(4)}

        def solve(b: str, depth: int = 0) -> np.ndarray:
            if b in out:
                return out[b]
            if depth > len(self.bodies) + 1:
                raise OsimError(f"{self.path}: kinematic loop reaching body '{b}'")
            if b not in child_joint:
                raise OsimError(f"{self.path}: body '{b}' is not the child of any joint")
            j = child_joint[b]
            pb, X_pb_F = self.frame_in_body(j.parent_frame)
            _, X_cb_M = self.frame_in_body(j.child_frame)
            X = solve(pb, depth + 1) @ X_pb_F @ self.joint_transform(j.name, coords) @ _inv(X_cb_M)
            out[b] = X
            return X

        for b in (self.bodies if bodies is None else bodies):
            solve(b)
        return out if bodies is None else {b: out[b] for b in bodies}

    def transform(self, a: str, b: str, coords: Mapping[str, float] | None = None) -> np.ndarray:
        """X_ab: 4x4 transform mapping coordinates in body ``b`` to body ``a`` at ``coords``."""
        T = self.body_transforms(coords, bodies=[a, b])
        return _inv(T[a]) @ T[b]

    def point_in_body(self, point: PathPoint, body: str,
                      coords: Mapping[str, float] | None = None) -> np.ndarray:
        """A path point's location [m] expressed in ``body``'s frame at ``coords``."""
        if point.body == body:
            return point.location_in_body.copy()
        return _apply(self.transform(body, point.body, coords), point.location_in_body)

    def welded_bodies(self, body: str) -> set[str]:
        """Bodies rigidly connected to ``body`` through WeldJoints (incl. ``body``)."""
        adj: dict[str, set[str]] = {}
        for j in self.joints.values():
            if j.type == "WeldJoint":
                a, _ = self.frame_in_body(j.parent_frame)
                c, _ = self.frame_in_body(j.child_frame)
                adj.setdefault(a, set()).add(c)
                adj.setdefault(c, set()).add(a)
        out, todo = {body}, [body]
        while todo:
            for n in adj.get(todo.pop(), ()):
                if n not in out:
                    out.add(n)
                    todo.append(n)
        return out


# --------------------------------------------------------------------------------------
# parsing
# --------------------------------------------------------------------------------------
class _Ctx:
    def __init__(self, path: str):
        self.path = path

    def err(self, what: str) -> OsimError:
        return OsimError(f"{self.path}: {what}")

    def text(self, el: ET.Element, tag: str, owner: str, required: bool = True) -> str | None:
        sub = el.find(tag)
        if sub is None or sub.text is None or not sub.text.strip():
            if required:
                raise self.err(f"{owner}: missing <{tag}>")
            return None
        return sub.text.strip()

    def floats(self, el: ET.Element, tag: str, owner: str, n: int | None = None,
               required: bool = True) -> np.ndarray | None:
        t = self.text(el, tag, owner, required)
        if t is None:
            return None
        try:
            v = np.array([float(s) for s in t.split()], float)
        except ValueError:
            raise self.err(f"{owner} <{tag}>: cannot parse '{t}' as numbers") from None
        if (n is not None and v.size != n) or not np.all(np.isfinite(v)):
            raise self.err(f"{owner} <{tag}>: expected {n or 'finite'} finite numbers, got '{t}'")
        return v

    def float1(self, el: ET.Element, tag: str, owner: str, required: bool = True) -> float | None:
        v = self.floats(el, tag, owner, 1, required)
        return None if v is None else float(v[0])

    def boolean(self, el: ET.Element, tag: str, owner: str, default: bool) -> bool:
        t = self.text(el, tag, owner, required=False)
        if t is None:
            return default
        if t.lower() not in ("true", "false"):
            raise self.err(f"{owner} <{tag}>: expected true/false, got '{t}'")
        return t.lower() == "true"


def _resolve(owner_path: str, ref: str) -> str:
    """Resolve an OpenSim socket path ``ref`` relative to the component at ``owner_path``."""
    ref = ref.strip()
    parts = [] if ref.startswith("/") else [p for p in owner_path.split("/") if p]
    for seg in ref.split("/"):
        if seg in ("", "."):
            continue
        if seg == "..":
            if parts:
                parts.pop()
        else:
            parts.append(seg)
    return "/" + "/".join(parts)


def _parse_function(ctx: _Ctx, el: ET.Element, owner: str) -> tuple[_Function, str]:
    tag = el.tag
    where = f"{owner} <{tag}>"
    if tag == "Constant":
        return _Constant(ctx.float1(el, "value", where)), tag
    if tag == "LinearFunction":
        c = ctx.floats(el, "coefficients", where, 2)
        return _Linear(float(c[0]), float(c[1])), tag
    if tag in ("SimmSpline", "PiecewiseLinearFunction"):
        x = ctx.floats(el, "x", where)
        y = ctx.floats(el, "y", where)
        if x.size != y.size or x.size < 1 or np.any(np.diff(x) <= 0):
            raise ctx.err(f"{where}: x must be strictly increasing and match y")
        if x.size == 1:
            return _Constant(float(y[0])), tag
        return (_SimmSpline(x, y) if tag == "SimmSpline" else _PiecewiseLinear(x, y)), tag
    if tag == "MultiplierFunction":
        holder = el.find("function")
        inner = list(holder) if holder is not None else []
        if len(inner) != 1:
            raise ctx.err(f"{where}: expected one function inside <function>")
        f, t = _parse_function(ctx, inner[0], owner)
        return _Multiplier(f, ctx.float1(el, "scale", where)), f"{tag}({t})"
    return _Unsupported(f"{ctx.path}: {where}: function type not supported by this reader"), tag


def _iter_components(el: ET.Element, path: str):
    """Yield (element, absolute_component_path) for every named XML element under ``el``.

    OpenSim component paths are formed from ``name`` attributes; unnamed containers such as
    ``<objects>``, ``<frames>``, ``<components>`` do not add a path segment."""
    for ch in el:
        name = ch.get("name")
        p = f"{path}/{name}" if name else path
        if name:
            yield ch, p
        yield from _iter_components(ch, p)


def read_osim(path: str | os.PathLike) -> OsimModel:
    """Parse an .osim file (OpenSim 4.x XML, incl. OpenSim JAM components) without OpenSim.

    Raises :class:`OsimError` with a one-line message naming the file and element for
    malformed XML, missing/unparseable required values, unresolvable frames or unknown
    path-point types inside a ligament."""
    path = os.fspath(path)
    ctx = _Ctx(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise OsimError(f"{path}: malformed XML ({e})") from None
    except OSError as e:
        raise OsimError(f"{path}: cannot read file ({e.strerror})") from None
    if root.tag != "OpenSimDocument":
        raise ctx.err(f"root element <{root.tag}> is not <OpenSimDocument>")
    model_el = root.find("Model")
    if model_el is None:
        raise ctx.err("<OpenSimDocument> has no <Model> element")
    skipped: list[str] = []

    # --- pass 1: bodies, offset frames (anywhere), meshes, wraps ----------------------
    bodies: dict[str, BodyInfo] = {}
    frames: dict[str, OffsetFrame] = {}
    bodies["ground"] = BodyInfo("ground", "/ground", 0.0, np.zeros(3))
    bodyset = model_el.find("BodySet/objects")
    for b in (bodyset if bodyset is not None else []):
        if b.tag != "Body":
            raise ctx.err(f"BodySet: unknown element <{b.tag}> '{b.get('name')}'")
        nm = b.get("name")
        if not nm:
            raise ctx.err("BodySet: <Body> without a name")
        where = f"Body '{nm}'"
        bodies[nm] = BodyInfo(nm, f"/bodyset/{nm}", ctx.float1(b, "mass", where),
                              ctx.floats(b, "mass_center", where, 3))
    all_comps = list(_iter_components(model_el, ""))
    for el, p in all_comps:
        if el.tag == "PhysicalOffsetFrame":
            where = f"PhysicalOffsetFrame '{p}'"
            par = ctx.text(el, "socket_parent", where)
            frames[p] = OffsetFrame(el.get("name"), p, _resolve(p, par),
                                    ctx.floats(el, "translation", where, 3),
                                    ctx.floats(el, "orientation", where, 3))

    model = OsimModel(path, model_el.get("name", ""),
                      (model_el.findtext("length_units") or "").strip(),
                      (model_el.findtext("force_units") or "").strip(),
                      bodies, frames, {}, {}, {}, {}, {}, skipped)

    def owner_frame_of_geometry(comp_path: str) -> str:
        # geometry path is <frame path>/<geom name>; socket '..' resolves to the frame.
        return comp_path.rsplit("/", 1)[0]

    for el, p in all_comps:
        if el.tag == "Mesh":
            where = f"Mesh '{p}'"
            sock = el.findtext("socket_frame") or ".."
            fr = _resolve(p, sock.strip())
            if fr == "/":
                fr = owner_frame_of_geometry(p)
            body, _ = model.frame_in_body(fr)
            sf = ctx.floats(el, "scale_factors", where, 3, required=False)
            mg = MeshGeometry(el.get("name"), ctx.text(el, "mesh_file", where), fr, body,
                              np.ones(3) if sf is None else sf)
            bodies[body].meshes.append(mg)
        elif el.tag in _WRAP_TAGS:
            where = f"{el.tag} '{p}'"
            seg = p.split("/")
            body = "ground" if seg[1] == "ground" else seg[2]
            dims = {}
            for t in ("dimensions", "radius", "length", "inner_radius", "outer_radius"):
                v = ctx.floats(el, t, where, required=False)
                if v is not None:
                    dims[t] = v
            rot = ctx.floats(el, "xyz_body_rotation", where, 3, required=False)
            tr = ctx.floats(el, "translation", where, 3, required=False)
            model.wrap_objects[el.get("name")] = WrapObject(
                el.get("name"), el.tag, body, np.zeros(3) if tr is None else tr,
                np.zeros(3) if rot is None else rot, dims)

    # --- joints & coordinates -----------------------------------------------------------
    jointset = model_el.find("JointSet/objects")
    for j in (jointset if jointset is not None else []):
        nm = j.get("name")
        jp = f"/jointset/{nm}"
        where = f"{j.tag} '{nm}'"
        pf = _resolve(jp, ctx.text(j, "socket_parent_frame", where))
        cf = _resolve(jp, ctx.text(j, "socket_child_frame", where))
        for fr in (pf, cf):
            try:
                model.frame_in_body(fr)
            except OsimError:
                raise ctx.err(f"{where}: frame '{fr}' not found") from None
        coords: list[Coordinate] = []
        for c in j.findall("coordinates/Coordinate"):
            cw = f"{where} Coordinate '{c.get('name')}'"
            rng = ctx.floats(c, "range", cw, 2, required=False)
            dv = ctx.float1(c, "default_value", cw, required=False)
            co = Coordinate(c.get("name"), nm, 0.0 if dv is None else dv,
                            (-math.inf, math.inf) if rng is None else (float(rng[0]), float(rng[1])),
                            ctx.boolean(c, "locked", cw, False), ctx.boolean(c, "clamped", cw, False))
            coords.append(co)
            model.coordinates[co.name] = co
        axes: list[TransformAxis] = []
        if j.tag == "CustomJoint":
            st = j.find("SpatialTransform")
            if st is None:
                raise ctx.err(f"{where}: missing <SpatialTransform>")
            for ta in st.findall("TransformAxis"):
                tw = f"{where} TransformAxis '{ta.get('name')}'"
                cn = tuple((ta.findtext("coordinates") or "").split())
                fel = [ch for ch in ta if ch.tag not in ("coordinates", "axis")]
                if len(fel) != 1:
                    raise ctx.err(f"{tw}: expected exactly one function element")
                fn, ftype = _parse_function(ctx, fel[0], tw)
                if isinstance(fn, _Unsupported):
                    skipped.append(fn.message)
                if not cn and not isinstance(fn, (_Constant, _Multiplier, _Unsupported)):
                    fn = _Constant(fn(0.0))
                axes.append(TransformAxis(ta.get("name"), cn, ctx.floats(ta, "axis", tw, 3), fn, ftype))
            if [a.name for a in axes] != ["rotation1", "rotation2", "rotation3",
                                          "translation1", "translation2", "translation3"]:
                raise ctx.err(f"{where}: SpatialTransform must have rotation1-3, translation1-3")
        elif j.tag not in _SUPPORTED_JOINTS:
            skipped.append(f"{path}: {where}: joint type not supported for kinematics "
                           f"(parsed frames/coordinates only)")
        model.joints[nm] = Joint(nm, j.tag, pf, cf, coords, axes)

    # --- ligaments ----------------------------------------------------------------------
    for el, p in all_comps:
        if el.tag != _LIGAMENT_TAG:
            continue
        nm = el.get("name")
        where = f"{_LIGAMENT_TAG} '{nm}'"
        if nm in model.ligaments:
            raise ctx.err(f"{where}: duplicate name")
        props: dict[str, float] = {}
        present = []
        for key in ("linear_stiffness", "slack_length", "transition_strain", "damping_coefficient"):
            v = ctx.float1(el, key, where, required=key in ("linear_stiffness", "slack_length"))
            if v is None:
                v = BLANKEVOORT_DEFAULTS[key]
            else:
                present.append(key)
            props[key] = v
        if props["slack_length"] <= 0 or props["linear_stiffness"] < 0 or props["transition_strain"] <= 0:
            raise ctx.err(f"{where}: non-physical property values {props}")
        gp = el.find("GeometryPath")
        if gp is None:
            raise ctx.err(f"{where}: missing <GeometryPath>")
        gpp = f"{p}/{gp.get('name') or 'geometrypath'}"
        objs = gp.find("PathPointSet/objects")
        pts: list[PathPoint] = []
        notes: list[str] = []
        for pp in (objs if objs is not None else []):
            pw = f"{where} <{pp.tag}> '{pp.get('name')}'"
            if pp.tag in _SKIPPED_POINT_TAGS:
                notes.append(f"{path}: {pw}: skipped ({pp.tag} is coordinate dependent; "
                             f"only fixed PathPoints are used)")
                continue
            if pp.tag != "PathPoint":
                raise ctx.err(f"{pw}: unknown path point type")
            fr = _resolve(f"{gpp}/{pp.get('name')}", ctx.text(pp, "socket_parent_frame", pw))
            try:
                body, X = model.frame_in_body(fr)
            except OsimError:
                raise ctx.err(f"{pw}: parent frame '{fr}' not found") from None
            loc = ctx.floats(pp, "location", pw, 3)
            pts.append(PathPoint(pp.get("name"), fr, body, loc, _apply(X, loc)))
        if len(pts) < 2:
            raise ctx.err(f"{where}: fewer than 2 fixed path points")
        wraps = [w.findtext("wrap_object", "").strip() for w in gp.findall("PathWrapSet/objects/PathWrap")]
        for w in wraps:
            wo = model.wrap_objects.get(w)
            notes.append(f"{path}: {where}: PathWrap over '{w}'"
                         f"{' (' + wo.type + ' on ' + wo.body + ')' if wo else ' (wrap object not found)'}"
                         f" skipped: straight segments between fixed points are used")
        lig = Ligament(nm, props["linear_stiffness"], props["slack_length"], props["transition_strain"],
                       props["damping_coefficient"], ctx.boolean(el, "appliesForce", where, True),
                       pts, wraps, notes, tuple(present))
        model.ligaments[nm] = lig
        skipped.extend(notes)

    # --- contact meshes -------------------------------------------------------------------
    for el, p in all_comps:
        if el.tag != "Smith2018ContactMesh":
            continue
        nm = el.get("name")
        where = f"Smith2018ContactMesh '{nm}'"
        fr = _resolve(p, ctx.text(el, "socket_frame", where))
        try:
            body, _ = model.frame_in_body(fr)
        except OsimError:
            raise ctx.err(f"{where}: frame '{fr}' not found") from None
        loc = ctx.floats(el, "location", where, 3, required=False)
        ori = ctx.floats(el, "orientation", where, 3, required=False)
        model.contact_meshes[nm] = ContactMesh(
            nm, ctx.text(el, "mesh_file", where), ctx.text(el, "mesh_back_file", where, required=False),
            fr, body, np.zeros(3) if loc is None else loc, np.zeros(3) if ori is None else ori,
            ctx.float1(el, "thickness", where), ctx.float1(el, "elastic_modulus", where),
            ctx.float1(el, "poissons_ratio", where),
            ctx.boolean(el, "use_variable_thickness", where, False))
    return model


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


# --------------------------------------------------------------------------------------
# force law
# --------------------------------------------------------------------------------------
def blankevoort_force(length: float | np.ndarray, slack_length: float, linear_stiffness: float,
                      transition_strain: float = BLANKEVOORT_DEFAULTS["transition_strain"]
                      ) -> float | np.ndarray:
    """Elastic force [N] of OpenSim's Blankevoort1991Ligament (no damping).

    strain e = length/slack_length - 1 (length, slack_length in m); k = linear_stiffness
    [N per unit strain]; e_t = transition_strain [-]:
      e <= 0:        F = 0
      0 < e < e_t:   F = k e^2 / (2 e_t)
      e >= e_t:      F = k (e - e_t/2)
    Equals Blankevoort & Huiskes (1991) f = k e^2/(4 e_l), f = k (e - e_l) with
    e_l = e_t / 2 (their 'spring parameter' / half the transition strain).
    """
    from kneenlp.model.laws import NUMPY, BlankevoortLaw

    e = np.asarray(length, float) / slack_length - 1.0
    f = np.asarray(BlankevoortLaw().tension(e, linear_stiffness, transition_strain / 2, NUMPY))
    return float(f) if f.ndim == 0 else f


# --------------------------------------------------------------------------------------
# writers
# --------------------------------------------------------------------------------------
_WRITABLE = ("linear_stiffness", "slack_length", "transition_strain", "damping_coefficient")


def _fmt(v: float) -> str:
    return repr(float(v))


def write_calibrated(src_osim: str | os.PathLike, out_path: str | os.PathLike,
                     values: Mapping[str, Mapping[str, float]]) -> list[tuple[str, str, str, str]]:
    """Copy ``src_osim`` to ``out_path`` changing only the given ligament properties.

    ``values`` maps bundle name -> {property: value} with property in linear_stiffness
    [N/strain], slack_length [m], transition_strain [-], damping_coefficient.  The file is
    edited as text inside each named ``Blankevoort1991Ligament`` element: only the number
    between ``<prop>`` and ``</prop>`` changes (written with repr(), which round-trips
    exactly); if the property element is absent (OpenSim default in use) a new element is
    inserted before the ligament's closing tag with the indentation of its last child.
    All other bytes (comments, whitespace, line endings, encoding) are preserved.

    Returns a list of (bundle, property, old_text, new_text).  Raises OsimError for unknown
    bundles/properties, non-finite or non-positive values, or ``out_path == src_osim``.
    """
    src, out = os.fspath(src_osim), os.fspath(out_path)
    if os.path.abspath(src) == os.path.abspath(out):
        raise OsimError(f"{src}: write_calibrated refuses to overwrite its source")
    with open(src, "rb") as fh:
        raw = fh.read()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise OsimError(f"{src}: not UTF-8 ({e})") from None
    read_osim(src)  # validates the file and that all ligaments parse
    changes: list[tuple[str, str, str, str]] = []
    for bundle, props in values.items():
        pat = re.compile(r'<' + _LIGAMENT_TAG + r'\s+name\s*=\s*"' + re.escape(bundle) + r'"\s*>'
                         r'(?P<body>.*?)</' + _LIGAMENT_TAG + r'>', re.S)
        ms = list(pat.finditer(text))
        if len(ms) != 1:
            raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}' found {len(ms)} times (need 1)")
        m = ms[0]
        body, b0 = m.group("body"), m.start("body")
        # GeometryPath content is masked so that only direct property children are touched
        gp = re.search(r"<GeometryPath\b.*?</GeometryPath>", body, re.S)
        masked = body if gp is None else body[:gp.start()] + " " * (gp.end() - gp.start()) + body[gp.end():]
        edits: list[tuple[int, int, str]] = []
        for key, val in props.items():
            if key not in _WRITABLE:
                raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}': property '{key}' not writable "
                                f"(allowed: {', '.join(_WRITABLE)})")
            v = float(val)
            if not math.isfinite(v) or (v <= 0 and key != "damping_coefficient") or v < 0:
                raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}' <{key}>: invalid value {val!r}")
            occ = list(re.finditer(r"<" + key + r">(?P<v>[^<]*)</" + key + r">", masked))
            if len(occ) > 1:
                raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}': <{key}> appears {len(occ)} times")
            if occ:
                o = occ[0]
                old = o.group("v")
                lead = old[: len(old) - len(old.lstrip())]
                trail = old[len(old.rstrip()):]
                new = lead + _fmt(v) + trail
                edits.append((b0 + o.start("v"), b0 + o.end("v"), new))
                changes.append((bundle, key, old.strip(), _fmt(v)))
            else:
                # insert before closing tag, copying indentation of the last child element line
                close = m.end("body")
                line_start = text.rfind("\n", 0, close) + 1
                closing_indent = text[line_start:close]
                nl = "\r\n" if "\r\n" in body else "\n"
                child_indent = re.findall(r"\n([ \t]*)<", body)
                ind = child_indent[-1] if child_indent else closing_indent + "\t"
                ins = f"{ind}<{key}>{_fmt(v)}</{key}>{nl}"
                if closing_indent.strip() == "":
                    edits.append((line_start, line_start, ins))
                else:
                    edits.append((close, close, nl + ins))
                changes.append((bundle, key, "", _fmt(v)))
        for s, e, new in sorted(edits, reverse=True):
            text = text[:s] + new + text[e:]
    write_text_atomic(out, text)
    return changes


def write_opensim_loadable_copy(src_osim: str | os.PathLike, out_path: str | os.PathLike,
                                remove: Sequence[str] = JAM_ONLY_CLASSES) -> list[str]:
    """Write a copy of the model without the elements of the classes in ``remove``
    (default: the OpenSim JAM-only classes) so that the plain ``opensim`` package can
    load it.  Text-level removal of each ``<Class ...>...</Class>`` element (or
    self-closing ``<Class .../>``).  Returns the names of removed components.  Bodies,
    joints and ligaments are untouched, so their kinematics can be compared in OpenSim.
    Mesh files that are missing only produce OpenSim warnings."""
    with open(src_osim, "rb") as fh:
        text = fh.read().decode("utf-8")
    removed: list[str] = []
    for cls in remove:
        pat = re.compile(r"[ \t]*<" + cls + r'\b[^>]*?(/>|>.*?</' + cls + r">)[ \t]*\r?\n?", re.S)
        removed += [re.search(r'name="([^"]*)"', m.group(0)).group(1) if 'name="' in m.group(0) else cls
                    for m in pat.finditer(text)]
        text = pat.sub("", text)
    write_text_atomic(out_path, text)
    return removed
