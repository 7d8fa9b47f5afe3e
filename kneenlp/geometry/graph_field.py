"""The femoral distance field inside a CasADi graph: the same tricubic B-spline as
:class:`~kneenlp.geometry.sdf.DistanceField` and the compiled kernels, as MX expressions.

Each point's 64 coefficients are gathered from the field's coefficient array with an index that
is a (piecewise constant) function of the point, ``coeffs[floor(u) - 1 + (a, b, c)]`` with ``u =
(x - origin) / spacing``; the weights are the cubic B-spline polynomials of ``u - floor(u)``.  So
the value, the gradient and every derivative CasADi takes of them are those of the spline itself,
and the graph serialises and generates C (the coefficients become one constant array).  It is
what the exported NLP of a mesh knee evaluates (:mod:`kneenlp.io.export`); the solvers use the
compiled expansion instead (:mod:`kneenlp.model.mesh_contact`), which is ~100x faster.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from kneenlp.geometry.sdf import DistanceField


def _basis(t: ca.MX) -> tuple[list[ca.MX], list[ca.MX]]:
    """Cubic B-spline weights at fraction ``t`` (any shape) and their derivatives in ``t``
    (:func:`kneenlp.geometry.kernels._basis`, rows 0 and 1)."""
    s = 1 - t
    w = [s * s * s / 6, (3 * t * t * t - 6 * t * t + 4) / 6, (-3 * t * t * t + 3 * t * t + 3 * t + 1) / 6,
         t * t * t / 6]
    dw = [-s * s / 2, (3 * t * t - 4 * t) / 2, (-3 * t * t + 2 * t + 1) / 2, t * t / 2]
    return w, dw


def field_in_graph(field: DistanceField, X: ca.MX) -> tuple[ca.MX, ca.MX]:
    """Field value (1 x N, m) and gradient (3 x N) at the points ``X`` (3 x N, femoral frame, m).
    Points outside the grid are evaluated at the nearest cell of it (callers mask them)."""
    nx, ny, nz = field.shape
    coeffs = ca.MX(ca.DM(np.ascontiguousarray(field.coeffs, dtype=float).ravel()))  # C order: (i, j, k)
    u = (X - ca.DM(field.origin)) / field.spacing
    cell = ca.fmin(ca.fmax(ca.floor(u), 1), ca.DM([nx - 3, ny - 3, nz - 3]))
    t = u - cell
    base = (cell[0, :] - 1) * (ny * nz) + (cell[1, :] - 1) * nz + (cell[2, :] - 1)  # 1 x N
    offsets = np.array([a * ny * nz + b * nz + c for a in range(4) for b in range(4) for c in range(4)], float)
    n = X.shape[1]
    index = ca.repmat(base, 64, 1) + ca.repmat(ca.DM(offsets), 1, n)  # 64 x N
    c = ca.reshape(coeffs[ca.vec(index)], 64, n)
    (wx, dx), (wy, dy), (wz, dz) = (_basis(t[a, :]) for a in range(3))
    rows = [(a, b, k) for a in range(4) for b in range(4) for k in range(4)]

    def combine(fx, fy, fz) -> ca.MX:
        return ca.sum1(c * ca.vertcat(*[fx[a] * fy[b] * fz[k] for a, b, k in rows]))

    value = combine(wx, wy, wz)
    grad = ca.vertcat(combine(dx, wy, wz), combine(wx, dy, wz), combine(wx, wy, dz)) / field.spacing
    return value, grad
