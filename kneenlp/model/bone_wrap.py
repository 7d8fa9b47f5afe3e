"""A ligament path over a bone's own surface: the taut string outside its signed distance field.

:class:`BoneWrap` is the shortest path from the tibial to the femoral attachment that stays
outside a bone (the femur's or the tibia's mesh of the knee file's ``[bones]``, as a
:class:`~kneenlp.geometry.sdf.DistanceField` in that bone's frame), by at least a ``clearance``
(the bundle's half-thickness).  The path is solved outside CasADi at every pose a solver evaluates
(:func:`~kneenlp.geometry.taut_path.taut_path`, its nodes' first-order response included) and
enters the model as pose data (:class:`~kneenlp.model.elements.PoseData`): :meth:`BoneWrap.route`
reads them from ``pose.data["path"]`` and gives the length as the path's Lagrangian
(:func:`~kneenlp.geometry.taut_path.lagrangian`), whose value, gradient and Hessian at the pose are
the shortest path's own.  So the equilibrium, the one NLP and the sensitivities keep exact
derivatives, as with the analytic obstacles of :mod:`kneenlp.model.paths`.

The tension acts on the tibia as the length's gradient says (the envelope theorem): for a path
over the femur, at the tibial attachment along ``-dL/ds`` (the first segment's direction); over
the tibia, the bone carrying the path, along ``dL/de`` through the femoral attachment (the last
segment's line), so the force the bone takes from the path acts on it.

A self-contained graph of the residual (``export --contact exact``, AMPL ``.nl``) cannot carry a
path solved outside it: those exports refuse such a knee with one line; the working sets' form
(the data taken at the trials' poses) carries it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from kneenlp.geometry.sdf import DistanceField, cached_field
from kneenlp.geometry.taut_path import NODES, data_size, lagrangian, taut_path
from kneenlp.model.elements import Pose
from kneenlp.model.paths import Route, WrapPath, _check_body

#: Deepest an attachment may lie inside the bone its path wraps (m): the knee file's tolerance of an
#: attachment inside a mesh (docs/inputs.md), deeper is a slip.
ATTACHMENT_DEPTH = 2.5e-3
#: The key of a path's own data in the pose its ligament routes it with (``pose.data``).
PATH_DATA = "path"
#: A straight line through the bone within this distance (m) of its middle (where the distance's
#: gradient across the line turns round) is near where the path switches sides and its length
#: jumps (:meth:`BoneWrap.side_switch`).
NEAR_MIDDLE = 1e-3


#: A bone's field for paths over it (m): a 1 mm grid (its error on S192803's bones: 16-24 um RMS,
#: :attr:`DistanceField.info`), exact 5 mm outside and 10 mm inside the surface (where a chord through
#: the bone is pushed out from), over the mesh's box padded by 5 mm and cut to within
#: :data:`BONE_REACH` of the frame's origin at the knee: the superficial MCL attaches 60-75 mm below
#: the joint line (S192803: 67-70 mm), and an attachment outside the field is refused
#: (:meth:`BoneWrap.uncovered`), since beyond it the path would cut through the bone unseen.
BONE_FIELD = {"spacing": 1e-3, "band": 5e-3, "depth": 10e-3}
BONE_PAD = 5e-3
BONE_REACH = 0.08
#: Path solves a :class:`BoneWrap` keeps, by their exact inputs (:meth:`BoneWrap.take`): the reference
#: pose's path is asked for at every evaluation and changes only with the attachments.
MEMO_SIZE = 32


def bone_field(mesh) -> DistanceField:
    """The signed distance field of a bone's closed mesh (m, its frame) for paths over it, built
    once per mesh and kept in the cache (:func:`~kneenlp.geometry.sdf.cached_field`)."""
    box = np.asarray(mesh.bounds, float) + np.array([[-BONE_PAD] * 3, [BONE_PAD] * 3])
    box = np.clip(box, -BONE_REACH, BONE_REACH)
    return cached_field(mesh, box, **BONE_FIELD)


@dataclass(frozen=True, eq=False)
class BoneWrap(WrapPath):
    """The shortest path over the surface of a bone fixed to ``body`` (``field``: its signed distance
    in that body's frame, m; ``bone``: the mesh's name in messages), at least ``clearance`` (m) off
    it, discretised with ``nodes`` nodes (module docstring)."""

    field: DistanceField
    body: str = "femur"
    clearance: float = 0.0
    bone: str = "bone"
    nodes: int = NODES

    shape = "bone surface"

    def __post_init__(self) -> None:
        _check_body(self.body, "bone surface")
        if not self.clearance >= 0 or self.nodes < 2:
            raise ValueError("a path over a bone needs a clearance >= 0 and at least 2 nodes")

    @property
    def data_size(self) -> int:
        """Numbers of its pose data (:func:`~kneenlp.geometry.taut_path.data_size`)."""
        return data_size(self.nodes)

    def ends(self, femur: np.ndarray, tibia: np.ndarray, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The attachments in the bone's frame at T poses (rotations T x 3 x 3, origins T x 3): the
        tibial one ``s`` and the femoral one ``e`` (T x 3 each, m)."""
        R, p = np.asarray(R, float).reshape(-1, 3, 3), np.asarray(p, float).reshape(-1, 3)
        femur, tibia = np.asarray(femur, float).ravel(), np.asarray(tibia, float).ravel()
        if self.body == "femur":
            return R @ tibia + p, np.broadcast_to(femur, p.shape).copy()
        return np.broadcast_to(tibia, p.shape).copy(), np.einsum("tji,tj->ti", R, femur - p)

    def solve(self, femur, tibia, R, p):
        """The taut paths at T poses (:class:`~kneenlp.geometry.taut_path.TautPath`)."""
        s, e = self.ends(femur, tibia, R, p)
        return taut_path(self.field, s, e, self.clearance, self.nodes)

    def take(self, femur: np.ndarray, tibia: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The pose data at T poses: T x :attr:`data_size` (NaN where the path's solve failed).  The
        last :data:`MEMO_SIZE` solves are kept by the bytes of their inputs, so an answer is the
        same whether it was solved or kept (a function of the inputs, not of the calls before)."""
        key = b"".join(np.ascontiguousarray(v, float).tobytes() for v in (femur, tibia, R, p))
        if key not in self._memo:
            if len(self._memo) >= MEMO_SIZE:
                del self._memo[next(iter(self._memo))]
            self._memo[key] = self.solve(femur, tibia, R, p).data()
        return self._memo[key].copy()

    def length(self, femur, tibia, R, p) -> float:
        return float(self.solve(femur, tibia, R, p).length[0])

    def uncovered(self, femur, tibia, R, p) -> list[str]:
        """Which attachments (``"femoral"``, ``"tibial"``) lie beyond where the field was cut at
        :data:`BONE_REACH` (at ``R``, ``p``): there the bone may go on unseen, and a path near them
        would cut through it.  (Beyond the mesh's own box the field's ``band`` is right: no bone.)"""
        s, e = (v[0] for v in self.ends(femur, tibia, R, p))
        lo, hi = self.field.bounds
        cut_lo, cut_hi = lo <= -BONE_REACH + 2 * self.field.spacing, hi >= BONE_REACH - 2 * self.field.spacing
        return [name for name, x in (("tibial", s), ("femoral", e)) if np.any(cut_lo & (x < lo) | cut_hi & (x > hi))]

    def level(self, point, R, p) -> float:
        """Below 1 for a point deeper in the bone than an attachment may lie (:data:`ATTACHMENT_DEPTH`:
        a ligament attaches to the bone it wraps, a little inside its mesh), in mm of depth."""
        x = np.asarray(point, float) if self.body == "femur" else np.asarray(R).T @ (np.asarray(point, float) - p)
        return 1.0 + (float(self.field.evaluate(x[None])[0][0]) - self.clearance + ATTACHMENT_DEPTH) * 1e3

    def side_switch(self, femur, tibia, R, p) -> str:
        """The straight line runs through the bone within :data:`NEAR_MIDDLE` of its middle: the
        distance's gradient across the line points the other way that far on the other side of its
        deepest point (the side the path goes round flips there, and its length jumps)."""
        s, e = (v[0] for v in self.ends(femur, tibia, R, p))
        t = np.linspace(0, 1, 4 * self.nodes + 2)[1:-1]
        points = s + t[:, None] * (e - s)
        d = self.field.evaluate(points)[0]
        deepest = int(np.argmin(d))
        if d[deepest] >= self.clearance:
            return ""
        u = (e - s) / np.linalg.norm(e - s)

        def across(x):
            g = self.field.evaluate(x[None], order=1)[1][0]
            return g - (g @ u) * u

        out = across(points[deepest])
        if not np.linalg.norm(out) > 0:
            return self._middle()
        out /= np.linalg.norm(out)
        if across(points[deepest] - NEAR_MIDDLE * out) @ out < 0:
            return self._middle()
        return ""

    def _middle(self) -> str:
        return (f"its straight line runs through the {self.bone} near its middle, where the path switches the side "
                "it goes round and its length jumps")

    @functools.cached_property
    def _function(self) -> ca.Function:
        """``(s, e, data) -> (L, dL/ds, dL/de)`` (built once per path; not pickled)."""
        s, e, data = ca.SX.sym("s", 3), ca.SX.sym("e", 3), ca.SX.sym("data", self.data_size)
        L = lagrangian(s, e, data, self.nodes)
        return ca.Function("bone_path", [s, e, data], [L, ca.gradient(L, s), ca.gradient(L, e)])

    @functools.cached_property
    def _memo(self) -> dict[bytes, np.ndarray]:
        """Kept solves (:meth:`take`; not pickled)."""
        return {}

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("_function", "_memo")}

    def route(self, femur, tibia, pose: Pose) -> Route:
        data = pose.data[PATH_DATA]
        arm = pose.R @ tibia
        if self.body == "femur":
            length, d_s, _ = self._function(pose.p + arm, femur, data)
            return Route(length, arm, -d_s)
        length, _, d_e = self._function(tibia, pose.R.T @ (femur - pose.p), data)
        return Route(length, femur - pose.p, pose.R @ d_e)
