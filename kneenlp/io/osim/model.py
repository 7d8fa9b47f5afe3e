"""The in-memory OpenSim model (what :func:`~kneenlp.io.osim.read.read_osim` returns): bodies,
frames, joints, coordinates, ligaments, contact meshes, wrap objects, and their kinematics
(``body_transforms``, ``transform``, ``point_in_body``, ``frame_in_body``; SI as stored in the
file); OpenSim's Blankevoort1991Ligament force (N).  Conventions: :mod:`kneenlp.io.osim`."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from kneenlp.io.osim.kinematics import OsimError, _apply, _axis_rot, _Function, _inv, _xform, rot_body_xyz

#: OpenSim 4.x defaults of Blankevoort1991Ligament properties that may be omitted in a file
#: (transition_strain [-], damping_coefficient [N*s per unit strain rate], i.e. force/strain-rate).
BLANKEVOORT_DEFAULTS: dict[str, float] = {"transition_strain": 0.06, "damping_coefficient": 0.003}

#: Classes that exist only in the OpenSim JAM plugin (not in the opensim wheel).
JAM_ONLY_CLASSES: tuple[str, ...] = ("Smith2018ArticularContactForce", "Smith2018ContactMesh")

_LIGAMENT_TAG = "Blankevoort1991Ligament"
_SUPPORTED_JOINTS = ("CustomJoint", "WeldJoint", "PinJoint", "SliderJoint")


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
    XYZ rotation [rad], raw dimension properties (m) and the ``quadrant`` it is constrained to
    (``all``: unconstrained)."""
    name: str
    type: str
    body: str
    translation: np.ndarray
    xyz_body_rotation: np.ndarray
    dimensions: dict[str, np.ndarray]
    quadrant: str = "all"


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

