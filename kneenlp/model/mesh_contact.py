"""Elastic-foundation contact between a real femoral surface and tibial cartilage samples.

The femoral articular surface is a signed-distance field ``d(x)`` (:class:`~kneenlp.geometry.sdf.
DistanceField`: a tricubic B-spline of the exact distance to the mesh, femoral frame, metres,
negative inside the femur).  The tibial cartilage is sampled at its mesh vertices ``x_i`` (tibial
frame) with lumped areas ``A_i``.  At a pose ``(R, p)`` the point ``X_i = R x_i + p`` penetrates
the femur by ``s_i = -d(X_i)``; the pressure is ``K h(s_i)`` (the compartment's pressure law,
:mod:`kneenlp.model.laws`; by default the paper's elastic foundation, modulus ``K`` times
penetration depth through the C2 gate) and the force on the tibia ``f_i = K h(s_i) A_i n_i``
acts along the femoral surface normal ``n = grad d / |grad d|`` at ``X_i``; moments are about the
tibial origin.  Everything is summed in the femoral frame.

How it enters the CasADi model.  Evaluating and differentiating a 3-D spline at hundreds of points
inside CasADi costs ~60 us per point for an exact Hessian (measured), so the sums are done outside
it (compiled loops, :mod:`kneenlp.geometry.kernels`; :func:`wrench_expansion` here is the NumPy
reference they are tested against): at the pose being evaluated, :func:`wrench_expansion` returns the compartment's
wrench ``W`` (force and moment, 6), its first derivatives ``J`` (6 x 6) and second derivatives
``H`` (6 x 6 x 6) with respect to a rigid displacement ``xi = (u, w)`` of the tibia (translation
``u``; rotation ``exp([w]x)`` applied in the femoral frame), from the field's derivatives up to
third order at every penetrating point.  That expansion is the element's working-set input
(:mod:`kneenlp.model.workingsets` takes it at every pose a solver evaluates), and the residual
uses ``W + J xi + xi' H xi / 2`` with ``xi`` the displacement from the expansion pose (``u = p -
p0``, ``w = vee(R R0' - R0 R')/2``, exact to second order).  At the evaluated pose ``xi = 0``, so
the residual, its Jacobian and its Hessian are those of the contact sums themselves.  The cost in
CasADi is a few operations per compartment whatever the number of points, and no point can be
left out: every penetrating point inside the field counts.  A contact outside the represented
region (a tibial point penetrating the femoral mesh outside the field's grid) is detected and the
solve reported as failed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np
from scipy.spatial import cKDTree

from kneenlp.geometry import kernels
from kneenlp.geometry.graph_field import field_in_graph
from kneenlp.geometry.sdf import DistanceField
from kneenlp.model.contact import MODULUS
from kneenlp.model.elements import Output, Pose, StagedElement, share_out
from kneenlp.model.laws import CASADI, NUMPY, ElasticFoundation, PressureLaw
from kneenlp.model.parameters import Parameter

if TYPE_CHECKING:
    from kneenlp.model.articular import Compartment, FemoralSurface

#: Points that may be nearer the femoral surface than this (m) are the candidates the checks look at
#: (:meth:`MeshContact.candidates`; the contact sums themselves pass over every point that cannot
#: penetrate with one look-up, :func:`kneenlp.geometry.kernels.contact_batch`).
CANDIDATE_REACH = 2e-3

#: A trial is noted (solved, with a warning) when more than this share of a compartment's contact
#: force would come from beyond the femoral surface's open edge (:meth:`MeshContact.rim_batch`).
RIM_SHARE = 0.05

#: Layout of the working-set input: expansion pose R0 (9, column-major) and p0 (3), wrench W (6),
#: Jacobian J (36, column-major 6 x 6), Hessian H (216: H[c] 6 x 6 for each wrench component c,
#: column-major), largest penetration (1).  W, J and H are per unit modulus.
WS_SIZE = 9 + 3 + 6 + 36 + 216 + 1
#: Points times poses of the smallest share of a compiled pass that gets a thread of its own
#: (:func:`~kneenlp.model.elements.share_out`): below it, starting the thread costs more than it saves
#: (a pass timed on one thread and on two, 2 cores: S192803's 362-point tibia gains from two threads
#: from ~20 poses on, the default knee's 2201 points from ~5).
SHARE_POINTS = 8192


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x for every row of ``v`` (n x 3 -> n x 3 x 3)."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], 1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product along axis 1 (broadcasting the others)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def _pressure_derivatives(s: np.ndarray, law: PressureLaw, gate: float) -> tuple[np.ndarray, ...]:
    """The pressure law's value and first two depth derivatives per unit modulus at depths ``s`` (m)."""
    out = np.array([kernels.pressure_at(law.kernel, float(v), gate) for v in np.ravel(s)]).reshape(-1, 3)
    return out[:, 0], out[:, 1], out[:, 2]


def wrench_expansion(field: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                     arms: tuple[np.ndarray, np.ndarray], gate: float, law: PressureLaw | None = None,
                     weight: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wrench (6), Jacobian (6 x 6) and Hessian (6 x 6 x 6) per unit modulus of the contact of the
    points with ``field = (d, g, h, t3)``: field values, gradients, Hessians and third derivatives
    (n, n x 3, n x 3 x 3, n x 3 x 3 x 3; :meth:`~kneenlp.geometry.sdf.DistanceField.evaluate` with
    ``order=3`` at the femoral-frame positions ``X``), ``arms = (r, areas)``: arms ``r = X - p``
    from the tibial origin (m) and areas (m^2); ``gate`` the gate width (m); with respect to
    ``xi = (u, w)`` (see module docstring).

    Per point, ``f = A q n`` with the weighted pressure ``q = w(X) g(s)``, ``s = -d``, ``n = grad d /
    |grad d|``; ``m = r x f``; ``weight``: the rim weight's value, gradient and Hessian at the points
    (n, n x 3, n x 3 x 3; default 1, a surface without an open edge).  The
    derivatives of ``f`` with respect to ``X`` follow from the field's (``dn/dX = P H / rho`` with
    ``P = I - n n'`` and ``rho = |grad d|``), those of ``X`` and ``r`` with respect to ``xi`` from
    ``X(xi) = X + u + w x r + w x (w x r) / 2``.
    """
    d, g, h, t3 = field
    r, areas = arms
    n_pts = len(d)
    if n_pts == 0:
        return np.zeros(6), np.zeros((6, 6)), np.zeros((6, 6, 6))
    gam, gam1, gam2 = _pressure_derivatives(-d, law or ElasticFoundation(), gate)
    rho = np.linalg.norm(g, axis=1)
    n = g / rho[:, None]
    P = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    N = P @ h / rho[:, None, None]  # dn_j/dX_k
    Hn = (h @ n[:, :, None])[:, :, 0]
    NtH = np.swapaxes(N, 1, 2) @ h
    PT = (P @ t3.reshape(n_pts, 3, 9)).reshape(n_pts, 3, 3, 3)
    dN = (PT - N[:, :, None, :] * Hn[:, None, :, None] - n[:, :, None, None] * np.swapaxes(NtH, 1, 2)[:, None]
          - N[:, :, :, None] * Hn[:, None, None, :]) / rho[:, None, None, None]  # dN_jk/dX_l
    wv, wg, wh = weight if weight is not None else (np.ones(n_pts), np.zeros((n_pts, 3)), np.zeros((n_pts, 3, 3)))
    # q = w gam and its derivatives in X (ds/dX = -g)
    q = wv * gam
    dq = wg * gam[:, None] - (wv * gam1)[:, None] * g
    gg = g[:, :, None] * g[:, None, :]
    wgg = wg[:, :, None] * g[:, None, :]
    d2q = (wh * gam[:, None, None] - gam1[:, None, None] * (wgg + np.swapaxes(wgg, 1, 2))
           + wv[:, None, None] * (gam2[:, None, None] * gg - gam1[:, None, None] * h))
    A, Q = areas[:, None, None], q[:, None, None]
    f = (areas * q)[:, None] * n
    Df = A * (Q * N + n[:, :, None] * dq[:, None, :])  # df_j/dX_k
    D2f = A[..., None] * (n[:, :, None, None] * d2q[:, None] + dq[:, None, :, None] * N[:, :, None, :]
                          + dq[:, None, None, :] * N[:, :, :, None] + Q[..., None] * dN)  # d2f_j/dX_k dX_l
    # X(xi) and r(xi): first derivatives B = [I, -[r]x], second derivatives (rotation block only)
    rx = _skew(r)
    B = np.concatenate([np.broadcast_to(np.eye(3), (n_pts, 3, 3)), -rx], axis=2)  # n x 3 x 6
    Br = np.concatenate([np.zeros((n_pts, 3, 3)), -rx], axis=2)
    eye = np.eye(3)
    Xw = 0.5 * (eye[None, :, :, None] * r[:, None, None, :] + eye[None, :, None, :] * r[:, None, :, None]
                - 2 * r[:, :, None, None] * eye[None, None, :, :])  # d2X_j/dw_a dw_b (the only non-zero block)
    f1 = Df @ B  # df/dxi, n x 3 x 6
    f2 = np.swapaxes(np.swapaxes(D2f, 2, 3) @ B[:, None], 2, 3) @ B[:, None]
    f2[:, :, 3:, 3:] += (Df @ Xw.reshape(n_pts, 3, 9)).reshape(n_pts, 3, 3, 3)
    m = _cross(r, f)
    m1 = _cross(Br, f[:, :, None]) + _cross(r[:, :, None], f1)
    m2 = _cross(Br[:, :, :, None], f1[:, :, None, :]) + _cross(Br[:, :, None, :], f1[:, :, :, None])
    m2 += _cross(r[:, :, None, None], f2)
    m2[:, :, 3:, 3:] += _cross(Xw, f[:, :, None, None])
    W = np.concatenate([f.sum(axis=0), m.sum(axis=0)])
    J = np.concatenate([f1.sum(axis=0), m1.sum(axis=0)])
    H = np.concatenate([f2.sum(axis=0), m2.sum(axis=0)])
    return W, J, H


class MeshContact(StagedElement):
    """Contact of one compartment: a femoral distance field against tibial cartilage samples.

    ``field`` femoral frame, m; the ``compartment``'s tibial ``points`` (N x 3) tibial frame, m,
    ``areas`` (N,) m^2 and pressure law; ``gate`` m; the ``femur``'s mesh vertices (femoral frame,
    m) with its ``offset`` (m) bound the gap of points outside the field's grid (None: no bound,
    such points never touch).  A cropped surface ends at its rim (its open edges): every
    pressure is multiplied by the field's rim weight (:attr:`~kneenlp.geometry.sdf.DistanceField.
    weights`, 1 on the surface, 0 beyond the rim), and a pose is noted where more than
    :data:`RIM_SHARE` of a compartment's force would come from beyond it (:meth:`rim_batch`).
    Parameter: ``contact.modulus``.  Outputs: contact force (N) and largest penetration (mm).
    """

    ws_width = WS_SIZE
    wrench_frame = "femoral"
    working_set_size = 1  # one expansion per compartment and trial

    def __init__(self, compartment: Compartment, field: DistanceField, gate: float,
                 femur: FemoralSurface | None = None):
        self.name, self.compartment = f"contact_{compartment.name}", compartment.name
        self.law = compartment.law or ElasticFoundation()
        self.field = field
        self.points, self.areas = np.asarray(compartment.points, float), np.asarray(compartment.areas, float)
        self.gate = float(gate)
        self.description = f"{compartment.name} compartment: femoral surface (distance field) vs tibial cartilage"
        femur_vertices, offset = (femur.mesh.vertices, femur.offset) if femur is not None else (None, 0.0)
        self._outside = (cKDTree(np.asarray(femur_vertices)), float(offset)) if femur_vertices is not None else None
        #: where a point outside the field's grid can be within reach of a femoral vertex (an empty box without them)
        reach = float(offset) + self.field.spacing + self.field.band
        self._near = ((np.min(femur_vertices, axis=0) - reach, np.max(femur_vertices, axis=0) + reach)
                      if femur_vertices is not None else (np.full(3, np.inf), np.full(3, -np.inf)))

    def parameters(self) -> list[Parameter]:
        return [MODULUS]

    def probe(self, pose: Pose, values: dict) -> ca.SX:
        return ca.vertcat(ca.vec(pose.R), pose.p, values[MODULUS.name])

    def unpack(self, ws, n):
        return ws

    def surface_wrench(self, probe, data):
        R, p, K = ca.reshape(probe[0:9], 3, 3), probe[9:12], probe[12]
        R0, p0 = ca.reshape(data[0:9], 3, 3), data[9:12]
        W0, J0 = data[12:18], ca.reshape(data[18:54], 6, 6)
        A = R @ R0.T
        xi = ca.vertcat(p - p0, 0.5 * (A[2, 1] - A[1, 2]), 0.5 * (A[0, 2] - A[2, 0]), 0.5 * (A[1, 0] - A[0, 1]))
        quad = ca.vertcat(*[ca.bilin(ca.reshape(data[54 + 36 * c: 90 + 36 * c], 6, 6), xi, xi) for c in range(6)])
        w = K * (W0 + J0 @ xi + 0.5 * quad)
        return w[0:3], w[3:6]

    def exact_wrench(self, probe, layout="vector"):
        """The contact's force and moment (femoral frame, about the tibial origin) summed over every
        tibial point in the graph, with the field evaluated there (:func:`~kneenlp.geometry.graph_field.
        field_in_graph`): a point counts where :meth:`select` takes it (inside the field's box,
        penetrating by less than the field's depth).  At every pose it equals the residual with the
        working sets of that pose."""
        R, p, K = ca.reshape(probe[0:9], 3, 3), probe[9:12], probe[12]
        X = R @ ca.DM(self.points.T) + ca.repmat(p, 1, len(self.points))
        d, g = field_in_graph(self.field, X, layout)
        lo, hi = self.field.bounds
        inside = ca.DM.ones(1, len(self.points))
        for a in range(3):
            inside = inside * (X[a, :] >= lo[a]) * (X[a, :] <= hi[a])
        active = inside * (d < 0) * (d > -0.99 * self.field.depth)
        rho = ca.if_else(active, ca.sqrt(ca.sum1(g * g)), 1.0)
        pressure = ca.if_else(active, self.law.pressure(-d, K, self.gate, CASADI), 0.0)
        if self.field.weight_spline is not None:  # the surface ends at its open edge
            pressure = pressure * field_in_graph(self.field.weight_spline, X, layout)[0]
        f = g * ca.repmat(pressure * ca.DM(self.areas).T / rho, 3, 1)
        return ca.sum2(f), ca.sum2(ca.cross(X - ca.repmat(p, 1, len(self.points)), f))

    # ------------------------------------------------------------------ numeric side
    def _femoral(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        return self.points @ np.asarray(R).T + np.asarray(p).ravel()

    def clearance(self, R, p, values, indices: np.ndarray | None = None):
        """Gap (m) of every point (or of ``indices``) at pose ``(R, p)``."""
        X = self._femoral(R, p) if indices is None else self.points[indices] @ np.asarray(R).T + np.asarray(p).ravel()
        d = self.field.evaluate(X)[0]
        if self._outside is not None:
            out = ~self.in_field(X)
            if np.any(out):  # nearest-vertex distance minus the offset, less one facet: never overstated
                tree, offset = self._outside
                reach = offset + self.field.spacing + self.field.band
                dist, _ = tree.query(X[out], distance_upper_bound=reach)  # bounded: fast, inf beyond
                d[out] = np.minimum(dist - offset - self.field.spacing, self.field.band)
        return d

    def in_field(self, X: np.ndarray) -> np.ndarray:
        """Mask of femoral-frame points inside the field's grid."""
        lo, hi = self.field.bounds
        return np.all((X >= lo) & (X <= hi), axis=1)

    def candidates(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Indices of the points that may be within :data:`CANDIDATE_REACH` of the femoral surface at
        pose ``(R, p)`` (a superset: the field is at least its cell's smallest coefficient,
        :attr:`~kneenlp.geometry.sdf.DistanceField.cell_min`) and of those outside the field's grid."""
        X = self._femoral(R, p)
        inside = self.in_field(X)
        near = np.ones(len(X), dtype=bool)
        cell = np.floor((X[inside] - self.field.origin) / self.field.spacing).astype(np.int64)
        near[inside] = self.field.cell_min[cell[:, 0], cell[:, 1], cell[:, 2]] < CANDIDATE_REACH
        return np.flatnonzero(near)

    def clearance_near(self, R: np.ndarray, p: np.ndarray, values: dict) -> tuple[np.ndarray, np.ndarray]:
        """Gaps (m) of the :meth:`candidates` only: every other point is farther than half the
        candidate reach from the surface."""
        idx = self.candidates(R, p)
        return idx, self.clearance(R, p, values, idx)

    def select(self, R, p, values):
        """The penetrating points inside the field (all of them count), but for points deeper than
        the field represents (its clip, 3 mm: absurd poses a line search may try), which have no
        surface normal there and are left out (their penetration still fails the pose's checks)."""
        cand = self.candidates(R, p)
        X = self.points[cand] @ np.asarray(R).T + np.asarray(p).ravel()
        d = self.field.evaluate(X)[0]
        return cand[(d < 0) & (d > -0.99 * self.field.depth) & self.in_field(X)]

    def _compartment(self) -> tuple:
        """The compartment as the compiled passes read it (:func:`kneenlp.geometry.kernels.compartment`)."""
        return kernels.compartment(self.field, self.points, self.areas)

    @property
    def min_share(self) -> int:
        """The fewest poses of a compiled pass's share that get a thread (:data:`SHARE_POINTS`)."""
        return max(1, SHARE_POINTS // len(self.points))

    def working_data_batch(self, R: np.ndarray, p: np.ndarray, values: dict, threads: int = 1,
                           order: int = 2) -> np.ndarray:
        """The working-set rows (T x :data:`WS_SIZE`) at the poses ``R`` (T x 3 x 3), ``p`` (T x 3):
        the contact's expansion over every penetrating point inside the field, one compiled pass per
        share of the poses (``threads`` shares run at once; the kernel releases the GIL).  ``order``: the
        wrench's derivatives included (0: the wrench only, the residual's value at the pose; 1: its
        Jacobian too; 2: its Hessian too)."""
        R = np.ascontiguousarray(R, dtype=float).reshape(-1, 3, 3)
        p = np.ascontiguousarray(p, dtype=float).reshape(-1, 3)
        out = np.empty((len(R), WS_SIZE))
        compartment, law = self._compartment(), (self.law.kernel, self.gate)

        def run(first: int, last: int) -> None:
            kernels.contact_batch(compartment, (R, p, first, last), law, order, out)

        share_out(run, len(R), threads, self.min_share)
        return out

    def left_out_batch(self, R: np.ndarray, p: np.ndarray, threads: int = 1) -> np.ndarray:
        """Per pose (``R`` T x 3 x 3, ``p`` T x 3), the largest penetration (m) of a point the contact
        pass leaves out (-inf if none penetrates): deeper than the field represents, or outside its
        grid (there measured from the femoral vertices, :meth:`clearance`)."""
        R = np.ascontiguousarray(R, dtype=float).reshape(-1, 3, 3)
        p = np.ascontiguousarray(p, dtype=float).reshape(-1, 3)
        fld = self.field
        deep, outside = np.empty(len(R)), np.empty((len(R), len(self.points)), dtype=np.bool_)
        compartment = self._compartment()

        def run(first: int, last: int) -> None:
            kernels.left_out_batch(compartment, (R, p, first, last), self._near, deep, outside)

        share_out(run, len(R), threads, self.min_share)
        trial, point = np.nonzero(outside)
        if len(trial) and self._outside is not None:  # all poses' outside points in one bounded tree query
            X = np.einsum("nij,nj->ni", R[trial], self.points[point]) + p[trial]
            tree, offset = self._outside
            dist, _ = tree.query(X, distance_upper_bound=offset + fld.spacing + fld.band)
            np.maximum.at(deep, trial, offset + fld.spacing - dist)  # never understated: see clearance
        return deep

    def rim_batch(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Per pose (``R`` T x 3 x 3, ``p`` T x 3), the share of the compartment's contact force that
        would come from beyond the femoral surface's open edge: the force the rim weight takes away
        over the force of every counted point unweighted (0 without an open edge or without
        contact).  Beyond the rim the field's distance is the distance to the edge line, so that
        share is no contact; a pose where it is above :data:`RIM_SHARE` is refused."""
        R, p = np.asarray(R, float).reshape(-1, 3, 3), np.asarray(p, float).reshape(-1, 3)
        share = np.zeros(len(R))
        fld = self.field
        if fld.weight_spline is None:
            return share
        counted = np.empty((len(R), len(self.points)), dtype=np.bool_)  # the points the contact counts
        kernels.counted_batch(self._compartment(), (np.ascontiguousarray(R), np.ascontiguousarray(p), 0, len(R)),
                              counted)
        trial, point = np.nonzero(counted)
        if not len(trial):
            return share
        X = np.einsum("nij,nj->ni", R[trial], self.points[point]) + p[trial]
        force = self.areas[point] * self.law.pressure(-fld.evaluate(X)[0], 1.0, self.gate, NUMPY)
        total, removed = np.zeros(len(R)), np.zeros(len(R))
        np.add.at(total, trial, force)
        np.add.at(removed, trial, force * (1.0 - fld.weight_spline.evaluate(X)[0]))
        return np.divide(removed, total, out=share, where=total > 0)

    def pack(self, indices, R, p, values):
        """The expansion of the contact at pose ``(R, p)`` over the points :meth:`select` chooses
        there (``indices``, from the same pose, are not needed: one compiled pass selects and sums)."""
        return self.working_data_batch(R, p, values)[0]

    def working_data(self, R: np.ndarray, p: np.ndarray, values: dict) -> np.ndarray:
        """The working-set input at pose ``(R, p)`` (:meth:`pack` without a separate selection)."""
        return self.working_data_batch(R, p, values)[0]

    def pressure(self, R: np.ndarray, p: np.ndarray, modulus: float) -> dict[str, np.ndarray]:
        """The contact at a pose (numeric, every point): per-point penetration (m) and pressure (Pa),
        the force on the tibia (N) and its moment about the tibial origin (N m), both in the femoral
        frame, and the centre of pressure (femoral frame, m; NaN without contact)."""
        X = self._femoral(R, p)
        d, g = self.field.evaluate(X, order=1)
        pen = -d
        pres = self.law.pressure(pen, modulus, self.gate, NUMPY)
        if self.field.weight_spline is not None:  # the surface ends at its open edge
            pres = pres * self.field.weight_spline.evaluate(X)[0]
        norm = np.linalg.norm(g, axis=1)
        n = np.divide(g, norm[:, None], out=np.zeros_like(g), where=norm[:, None] > 0)
        f = n * (pres * self.areas)[:, None]
        w = pres * self.areas
        cop = (X * w[:, None]).sum(axis=0) / w.sum() if w.sum() > 0 else np.full(3, np.nan)
        return {"penetration": pen, "pressure": pres, "force": f.sum(axis=0),
                "moment": np.cross(X - np.asarray(p).ravel(), f).sum(axis=0), "cop": cop}

    def outputs(self) -> list[Output]:
        return [Output("force", f"contact_{self.compartment}_N", "N"),
                Output("penetration", f"penetration_{self.compartment}_mm", "mm", 1e3)]

    def report(self, probe, data, force):
        return [ca.norm_2(force), data[WS_SIZE - 1]]  # the penetration of the expansion pose
