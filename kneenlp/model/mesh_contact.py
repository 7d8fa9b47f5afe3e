"""Elastic-foundation contact between a real femoral surface and tibial cartilage samples.

The femoral articular surface is a signed-distance field ``d(x)`` (:class:`~kneenlp.geometry.sdf.
DistanceField`: a tricubic B-spline of the exact distance to the mesh, femoral frame, metres,
negative inside the femur).  The tibial cartilage is sampled at its mesh vertices ``x_i`` (tibial
frame) with lumped areas ``A_i``.  At a pose ``(R, p)`` the point ``X_i = R x_i + p`` penetrates
the femur by ``-d(X_i)``; the pressure is ``K g(-d)`` (the paper's elastic foundation: modulus
``K`` times penetration depth, with the C2 gate ``g`` of :func:`kneenlp.model.contact.smooth_gate`)
and the force on the tibia ``K g(-d) A_i n_i`` acts along the femoral surface normal
``n = grad d / |grad d|`` at ``X_i``; moments about the tibial origin.  Everything is summed in
the femoral frame.

Cost.  Evaluating and differentiating a 3-D spline inside CasADi costs ~60 us per point for an
exact Hessian (measured); instead each working-set point carries the field's second-order
expansion at its position when the working set was taken, ``b_i``:
``d(X) = d(b) + g . (X - b) + (X - b)' H (X - b) / 2`` with normal ``g + H (X - b)``.  Its value,
normal and their first derivatives equal the field's at ``X = b``, so at a solution whose working
sets were taken at the solution itself the residual, its Jacobian (hence every sensitivity and
covariance) and the KKT conditions are those of the field.  The solvers retake the working sets
at each solution and solve again until that holds (:meth:`KneeModel.working_set`); the expansion
is exact to third order, so two or three rounds suffice.  The per-point arithmetic is a few dense
vector operations whatever the number of points (like :mod:`kneenlp.model.contact`).

Working set: the points whose gap at the pose is below ``margin`` (nearest first, at most
``n_working``; unused slots have zero area).  A point outside the set that penetrates at the
solution, or a contact outside the represented region, makes the solve fail with that reason.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
from scipy.spatial import cKDTree

from kneenlp.geometry.sdf import DistanceField
from kneenlp.model.contact import MODULUS, gate_numpy, smooth_gate
from kneenlp.model.elements import Output, Pose, StagedElement
from kneenlp.model.parameters import Parameter

#: Rows of one working-set slot: tibial point (3), area, expansion point (3), d, gradient (3),
#: Hessian (xx, yy, zz, xy, xz, yz).
WS_ROWS = 17


class MeshContact(StagedElement):
    """Contact of one compartment: a femoral distance field against tibial cartilage samples.

    ``field`` femoral frame, m; ``points`` (N x 3) tibial frame, m; ``areas`` (N,) m^2; ``gate``
    and ``margin`` m; ``femur_vertices`` (femoral frame, m) with ``offset`` (m) bound the gap of
    points outside the field's grid.  Parameter: ``contact.modulus``.  Outputs: contact force
    (N) and largest penetration (mm).
    """

    ws_width = WS_ROWS
    wrench_frame = "femoral"

    def __init__(self, compartment: str, field: DistanceField, points: np.ndarray, areas: np.ndarray, gate: float,
                 working_set_size: int, margin: float = 1e-4, femur_vertices: np.ndarray | None = None,
                 offset: float = 0.0):
        self.name, self.compartment = f"contact_{compartment}", compartment
        self.field = field
        self.points, self.areas = np.asarray(points, float), np.asarray(areas, float)
        self.gate, self.margin = float(gate), float(margin)
        self.working_set_size = int(min(max(1, working_set_size), len(self.points) - 1))
        self.description = f"{compartment} compartment: femoral surface (distance field) vs tibial cartilage"
        self._outside = (cKDTree(np.asarray(femur_vertices)), float(offset)) if femur_vertices is not None else None

    def parameters(self) -> list[Parameter]:
        return [MODULUS]

    def probe(self, pose: Pose, values: dict) -> ca.SX:
        return ca.vertcat(ca.vec(pose.R), pose.p, values[MODULUS.name])

    def unpack(self, ws, n):
        return ca.reshape(ws, n, WS_ROWS)  # field-major: each field one contiguous column

    def surface_wrench(self, probe, data):
        R, p, K = ca.reshape(probe[0:9], 3, 3), probe[9:12], probe[12]
        col = [data[:, i] for i in range(WS_ROWS)]
        x, y, z, area, bx, by, bz, d0, g0x, g0y, g0z, hxx, hyy, hzz, hxy, hxz, hyz = col
        # arm: tibial origin -> point, femoral frame; e: the point's offset from its expansion point
        ax = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
        ay = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
        az = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z
        ex, ey, ez = ax + (p[0] - bx), ay + (p[1] - by), az + (p[2] - bz)
        gx = g0x + hxx * ex + hxy * ey + hxz * ez
        gy = g0y + hxy * ex + hyy * ey + hyz * ez
        gz = g0z + hxz * ex + hyz * ey + hzz * ez
        d = d0 + 0.5 * ((g0x + gx) * ex + (g0y + gy) * ey + (g0z + gz) * ez)
        s = K * area * smooth_gate(-d, self.gate) / ca.sqrt(gx * gx + gy * gy + gz * gz + 1e-24)  # no 0/0 where clipped
        fx, fy, fz = s * gx, s * gy, s * gz
        force = ca.vertcat(ca.sum1(fx), ca.sum1(fy), ca.sum1(fz))
        moment = ca.vertcat(ca.sum1(ay * fz - az * fy), ca.sum1(az * fx - ax * fz), ca.sum1(ax * fy - ay * fx))
        return force, moment

    # ------------------------------------------------------------------ numeric side
    def _femoral(self, R: np.ndarray, p: np.ndarray, indices=None) -> np.ndarray:
        pts = self.points if indices is None else self.points[indices]
        return pts @ np.asarray(R).T + np.asarray(p).ravel()

    def clearance(self, R, p, values):
        X = self._femoral(R, p)
        d = self.field.evaluate(X)[0]
        if self._outside is not None:
            lo, hi = self.field.bounds
            out = ~np.all((X >= lo) & (X <= hi), axis=1)
            if np.any(out):  # nearest-vertex distance minus the offset, less one facet: never overstated
                tree, offset = self._outside
                reach = offset + self.field.spacing + self.field.band
                dist, _ = tree.query(X[out], distance_upper_bound=reach)  # bounded: fast, inf beyond
                d[out] = np.minimum(dist - offset - self.field.spacing, self.field.band)
        return d

    def in_field(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Mask of the sample points inside the field's grid at pose ``(R, p)``."""
        lo, hi = self.field.bounds
        X = self._femoral(R, p)
        return np.all((X >= lo) & (X <= hi), axis=1)

    def select(self, R, p, values):
        gap = self.clearance(R, p, values)
        candidates = np.flatnonzero((gap < self.margin) & self.in_field(R, p))
        if len(candidates) > self.n_working:
            candidates = candidates[np.argsort(gap[candidates], kind="stable")[: self.n_working]]
        return np.sort(candidates)

    def pack(self, indices, R, p, values):
        idx = np.asarray(indices, dtype=int)
        X = self._femoral(R, p, idx)
        d, g, h = self.field.evaluate(X, order=2)
        data = np.zeros((WS_ROWS, self.n_working))
        m = len(idx)
        data[0:3, :m], data[3, :m], data[4:7, :m], data[7, :m], data[8:11, :m] = \
            self.points[idx].T, self.areas[idx], X.T, d, g.T
        data[11:17, :m] = np.stack([h[:, 0, 0], h[:, 1, 1], h[:, 2, 2], h[:, 0, 1], h[:, 0, 2], h[:, 1, 2]])
        data[7, m:] = self.field.band  # empty slots: far away, zero area, unit normal
        data[9, m:] = 1.0
        return data.ravel()  # field-major (see unpack)

    def pressure(self, R: np.ndarray, p: np.ndarray, modulus: float) -> dict[str, np.ndarray]:
        """The contact at a pose from the field itself (no expansion): per-point penetration (m)
        and pressure (Pa), the force on the tibia (N) and its moment about the tibial origin (N m),
        both in the femoral frame, and the centre of pressure (femoral frame, m; NaN without
        contact)."""
        X = self._femoral(R, p)
        d, g, _ = self.field.evaluate(X, order=1)
        pen = -d
        pres = modulus * gate_numpy(pen, self.gate)
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
        R, p = ca.reshape(probe[0:9], 3, 3), probe[9:12]
        e = data[:, 0:3] @ R.T + ca.repmat(p.T, data.shape[0], 1) - data[:, 4:7]
        d = data[:, 7] + ca.sum2(data[:, 8:11] * e)  # first order: the penetration report only
        return [ca.norm_2(force), -ca.mmin(d)]
