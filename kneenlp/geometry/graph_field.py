"""The femoral distance field inside a CasADi graph: the same tricubic B-spline as
:class:`~kneenlp.geometry.sdf.DistanceField` and the compiled kernels, as MX expressions.

Each point's 64 coefficients are gathered from the field's coefficient array with an index that
is a (piecewise constant) function of the point, ``coeffs[floor(u) - 1 + (a, b, c)]`` with ``u =
(x - origin) / spacing``; the weights are the cubic B-spline polynomials of ``u - floor(u)``.  So
the value, the gradient and every derivative CasADi takes of them are those of the spline itself,
and the graph serialises and generates C (the coefficients become one constant array).  It is
what the exported NLP of a mesh knee evaluates (:mod:`kneenlp.io.export`); the solvers use the
compiled expansion instead (:mod:`kneenlp.model.mesh_contact`), which is ~100x faster.

Two layouts of the same spline (:data:`LAYOUTS`), which differ only in the graph's shape:

* ``"vector"``: every step one MX operation over all points.  Fast in CasADi's virtual machine
  (the CasADi-file export), but CasADi differentiates it direction by direction, so the C of its
  second derivatives is one function of ~10^5 vector operations that gcc does not compile in
  practice (default knee: not within 15 min);
* ``"loop"``: the spline of one point as an SX function (:func:`spline_function`, its
  coefficients a non-differentiated input) mapped over the points.  Its C is a loop around
  straight-line code (the default knee's NLP compiles in 11-21 s at ``-O0``); 3-9x slower in
  the virtual machine (``benchmarks/bench_export.py``).
"""

from __future__ import annotations

from functools import cache

import casadi as ca
import numpy as np

from kneenlp.base.modes import Layout, names
from kneenlp.geometry.sdf import DistanceField

LAYOUTS = names(Layout)
#: (a, b, c) of the 64 coefficients of a cell, in the order of the gathered columns
_ROWS = [(a, b, c) for a in range(4) for b in range(4) for c in range(4)]


def _basis(t):
    """Cubic B-spline weights at fraction ``t`` (any shape, MX or SX) and their derivatives in
    ``t`` (:func:`kneenlp.geometry.spline_kernels._basis`, rows 0 and 1)."""
    s = 1 - t
    w = [s * s * s / 6, (3 * t * t * t - 6 * t * t + 4) / 6, (-3 * t * t * t + 3 * t * t + 3 * t + 1) / 6,
         t * t * t / 6]
    dw = [-s * s / 2, (3 * t * t - 4 * t) / 2, (-3 * t * t + 2 * t + 1) / 2, t * t / 2]
    return w, dw


def _combine(c, t):
    """Spline value and gradient in cell units (per unit of ``t``) from the coefficients ``c``
    (64 x N) at fractions ``t`` (3 x N)."""
    (wx, dx), (wy, dy), (wz, dz) = (_basis(t[a, :]) for a in range(3))

    def dot(fx, fy, fz):
        return ca.sum1(c * ca.vertcat(*[fx[a] * fy[b] * fz[k] for a, b, k in _ROWS]))

    return dot(wx, wy, wz), ca.vertcat(dot(dx, wy, wz), dot(wx, dy, wz), dot(wx, wy, dz))


@cache
def spline_function() -> ca.Function:
    """``(c[64], t[3]) -> (value, gradient[3] per unit of t)``: one point's spline, SX; ``c`` is
    declared not differentiable (it is gathered at a piecewise constant index).  One instance, so
    every field and compartment shares its code."""
    c, t = ca.SX.sym("c", 64), ca.SX.sym("t", 3)
    value, grad = _combine(c, t)
    return ca.Function("field_spline", [c, t], [value, grad], ["c", "t"], ["value", "gradient"],
                       {"is_diff_in": [False, True]})


def field_in_graph(field: DistanceField, X: ca.MX, layout: Layout = "vector") -> tuple[ca.MX, ca.MX]:
    """Field value (1 x N, m) and gradient (3 x N) at the points ``X`` (3 x N, femoral frame, m),
    in either :data:`LAYOUTS` (module docstring).  Points outside the grid are evaluated at the
    nearest cell of it (callers mask them)."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, not {layout!r}")
    nx, ny, nz = field.shape
    coeffs = ca.MX(ca.DM(np.ascontiguousarray(field.coeffs, dtype=float).ravel()))  # C order: (i, j, k)
    u = (X - ca.DM(field.origin)) / field.spacing
    cell = ca.fmin(ca.fmax(ca.floor(u), 1), ca.DM([nx - 3, ny - 3, nz - 3]))
    t = u - cell
    base = (cell[0, :] - 1) * (ny * nz) + (cell[1, :] - 1) * nz + (cell[2, :] - 1)  # 1 x N
    offsets = np.array([a * ny * nz + b * nz + c for a, b, c in _ROWS], float)
    n = X.shape[1]
    index = ca.repmat(base, 64, 1) + ca.repmat(ca.DM(offsets), 1, n)  # 64 x N
    c = ca.reshape(coeffs[ca.vec(index)], 64, n)
    value, grad = _combine(c, t) if layout == "vector" else spline_function().map(n)(c, t)
    return value, grad / field.spacing
