"""Compiled per-point loops of the mesh contact (numba): the contact wrench's expansion, summed
over the penetrating points, and the passes over a compartment's poses (the field's spline itself:
:mod:`kneenlp.geometry.spline_kernels`).

The same mathematics as the NumPy reference implementations
(:meth:`kneenlp.geometry.sdf.DistanceField.evaluate` with ``order=3`` and
:func:`kneenlp.model.mesh_contact.wrench_expansion`), fused into one loop over points so that no
per-point tensor is ever materialised: ~20x faster, which is what makes identification on a real
knee take seconds.  Tests compare the two to 1e-12.  Compiled once per machine (``cache=True``:
numba keeps the machine code in the user's cache, :mod:`kneenlp.base.cache`, or in
``$NUMBA_CACHE_DIR``; never in the package directory).

The passes take the pressure law's ``kernel`` (:class:`kneenlp.model.laws.PressureLaw`) as an
argument, in one of two forms (:func:`pressure`):

* a number ``n``: the power family ``p / K = d_r (g(d) / d_r)^n`` (``g`` the gate of
  :mod:`kneenlp.geometry.ramp`, ``d_r`` = :data:`REFERENCE_DEPTH`; ``n = 1`` is the paper's linear
  law, exactly ``g``): the passes are compiled for a float once per machine and loaded from the cache;
* a compiled function ``(depth, gate) -> (h, h', h'')`` (any law): numba cannot keep machine code
  specialised on a function argument, so the passes are compiled for it again in every process
  (~15 s on the default knee's first contact evaluation).  Before the number form, every command
  paid that.

The passes read a compartment as the tuple ``compartment = (femur, tibia)`` (:func:`compartment`):
``femur = (spline, cmin, rim, box, deepest)`` (the field's spline ``(coeffs, origin, spacing)``,
its cells' lower bounds, the rim weight ``(coefficients, their cell minimum)`` (empty: 1), the box
``(lo, hi)`` in which it is evaluated and the deepest penetration it counts, m) and ``tibia =
(points, areas)`` (tibial frame, m; m^2); the poses as ``poses = (R, p, first, last)`` (the
poses ``first..last-1`` of ``R`` T x 3 x 3 and ``p`` T x 3); the law as ``law = (kernel, gate)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit, types
from numba.extending import overload

from kneenlp.geometry.ramp import gate_derivatives

# it points numba's cache at the user's cache before the decorators below read it
from kneenlp.geometry.spline_kernels import cell_min_at, field_derivatives, field_values, value_at, value_gradient

if TYPE_CHECKING:
    from kneenlp.geometry.sdf import DistanceField

#: Depth (m) at which every member of the power family equals the paper's linear law.
REFERENCE_DEPTH = 1e-3


@njit(cache=True, nogil=True)
def power_pressure(s: float, width: float, n: float) -> tuple[float, float, float]:
    """``d_r (g / d_r)^n`` per unit modulus and its first two depth derivatives at depth ``s`` (m),
    ``g`` the gate of width ``width`` (m); ``n = 1``: the gate itself, the paper's law."""
    g, g1, g2 = gate_derivatives(s, width)
    if n == 1.0 or g <= 0.0:
        return g, g1, g2
    r = (g / REFERENCE_DEPTH) ** (n - 1.0)  # (g / d_r)^(n - 1)
    return g * r, n * r * g1, n * (n - 1.0) * r * g1 * g1 / g + n * r * g2


def pressure(law, s, width):
    """The pressure law ``law`` (an exponent of the power family or a compiled function) at depth
    ``s`` (m) per unit modulus, with its first two depth derivatives: inside compiled loops only
    (module docstring); from Python use :func:`pressure_at`."""
    raise NotImplementedError("kneenlp.geometry.kernels.pressure is for compiled loops: use pressure_at")


@overload(pressure)
def _pressure_overload(law, s, width):
    if isinstance(law, (types.Float, types.Integer)):
        return lambda law, s, width: power_pressure(s, width, float(law))
    return lambda law, s, width: law(s, width)


@njit(cache=True, nogil=True)
def pressure_at(law, s: float, width: float) -> tuple[float, float, float]:
    """:func:`pressure` callable from Python."""
    return pressure(law, s, width)


@njit(cache=True, nogil=True)
def wrench_expansion(field: tuple, arms: tuple[np.ndarray, np.ndarray], weight: tuple, law: tuple,
                     order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """See :func:`kneenlp.model.mesh_contact.wrench_expansion` (the same ``field = (d, g, h, t3)``
    and ``arms = (r, areas)``, same results): wrench (6), Jacobian (6 x 6), Hessian (6 x 6 x 6) per
    unit modulus.  ``law = (kernel, gate)``.  ``order=1``: the Hessian is left zero (``t3`` and
    ``wh`` are not read), at about half the cost.  ``weight = (wv, wg, wh)`` (n, n x 3, n x 3 x 3):
    the rim weight's value, gradient and Hessian at the points (1, 0, 0 on a surface without an
    open edge): the pressure is ``w(X) h(s)``."""
    d, g, h, t3 = field
    r, areas = arms
    wv, wg, wh = weight
    kernel, gate = law
    W = np.zeros(6)
    J = np.zeros((6, 6))
    H = np.zeros((6, 6, 6))
    nv = np.empty(3)
    N = np.empty((3, 3))
    Hn = np.empty(3)
    NtH = np.empty((3, 3))
    dN = np.empty((3, 3, 3))
    f = np.empty(3)
    Df = np.empty((3, 3))
    D2f = np.empty((3, 3, 3))
    B = np.empty((3, 6))
    Xw = np.empty((3, 3, 3))
    f1 = np.empty((3, 6))
    f2 = np.empty((3, 6, 6))
    tmp = np.empty((3, 3, 6))
    for p in range(d.shape[0]):
        s = -d[p]
        if s <= 0.0:
            continue
        gam, gam1, gam2 = pressure(kernel, s, gate)  # the pressure law's value and depth derivatives, per unit modulus
        # the weighted pressure w gam: the terms of w's derivatives come last, so that with w = 1 and
        # zero derivatives every number is the unweighted one, bit for bit
        w = wv[p]
        gamw, gam1w, gam2w = w * gam, w * gam1, w * gam2
        gx, gy, gz = g[p, 0], g[p, 1], g[p, 2]
        rho = np.sqrt(gx * gx + gy * gy + gz * gz)
        nv[0], nv[1], nv[2] = gx / rho, gy / rho, gz / rho
        a = areas[p]
        # N = (I - n n') H / rho, Hn = H n, NtH = N' H
        for j in range(3):
            Hn[j] = h[p, j, 0] * nv[0] + h[p, j, 1] * nv[1] + h[p, j, 2] * nv[2]
        for j in range(3):
            for k in range(3):
                N[j, k] = (h[p, j, k] - nv[j] * Hn[k]) / rho  # (P H)_jk = H_jk - n_j (n' H)_k, H symmetric
        for l_ in range(3):
            for k in range(3):
                NtH[l_, k] = N[0, l_] * h[p, 0, k] + N[1, l_] * h[p, 1, k] + N[2, l_] * h[p, 2, k]
        for j in range(3):
            for k in range(3):
                for l_ in range(3 if order >= 2 else 0):
                    pt = t3[p, j, k, l_] - nv[j] * (nv[0] * t3[p, 0, k, l_] + nv[1] * t3[p, 1, k, l_]
                                                    + nv[2] * t3[p, 2, k, l_])
                    dN[j, k, l_] = (pt - N[j, l_] * Hn[k] - nv[j] * NtH[l_, k] - N[j, k] * Hn[l_]) / rho
        for j in range(3):
            f[j] = a * gamw * nv[j]
            for k in range(3):
                Df[j, k] = a * (gamw * N[j, k] - gam1w * nv[j] * g[p, k] + nv[j] * wg[p, k] * gam)
                for l_ in range(3 if order >= 2 else 0):
                    D2f[j, k, l_] = a * (gam2w * nv[j] * g[p, k] * g[p, l_]
                                         - gam1w * (nv[j] * h[p, k, l_] + g[p, k] * N[j, l_] + g[p, l_] * N[j, k])
                                         + gamw * dN[j, k, l_]
                                         + nv[j] * (wh[p, k, l_] * gam
                                                    - gam1 * (wg[p, k] * g[p, l_] + wg[p, l_] * g[p, k]))
                                         + gam * (wg[p, k] * N[j, l_] + wg[p, l_] * N[j, k]))
        rx, ry, rz = r[p, 0], r[p, 1], r[p, 2]
        # B = [I, -[r]x]: dX/dxi (w x r = -[r]x w)
        B[:, :] = 0.0
        B[0, 0] = B[1, 1] = B[2, 2] = 1.0
        B[0, 4], B[0, 5] = rz, -ry
        B[1, 3], B[1, 5] = -rz, rx
        B[2, 3], B[2, 4] = ry, -rx
        for j in range(3):
            for c in range(6):
                f1[j, c] = Df[j, 0] * B[0, c] + Df[j, 1] * B[1, c] + Df[j, 2] * B[2, c]
        # force and moment (m = r x f, Br = the rotation columns of B) and their first derivatives
        W[0] += f[0]
        W[1] += f[1]
        W[2] += f[2]
        W[3] += ry * f[2] - rz * f[1]
        W[4] += rz * f[0] - rx * f[2]
        W[5] += rx * f[1] - ry * f[0]
        for c in range(6):
            b0, b1, b2 = (B[0, c], B[1, c], B[2, c]) if c >= 3 else (0.0, 0.0, 0.0)
            for j in range(3):
                J[j, c] += f1[j, c]
            J[3, c] += b1 * f[2] - b2 * f[1] + ry * f1[2, c] - rz * f1[1, c]
            J[4, c] += b2 * f[0] - b0 * f[2] + rz * f1[0, c] - rx * f1[2, c]
            J[5, c] += b0 * f[1] - b1 * f[0] + rx * f1[1, c] - ry * f1[0, c]
        if order < 2:
            continue
        rv = (rx, ry, rz)
        for j in range(3):
            for u in range(3):
                for v in range(3):
                    Xw[j, u, v] = 0.5 * ((1.0 if j == u else 0.0) * rv[v] + (1.0 if j == v else 0.0) * rv[u]
                                         - 2.0 * rv[j] * (1.0 if u == v else 0.0))
        for j in range(3):
            for l_ in range(3):
                for c in range(6):
                    tmp[j, l_, c] = D2f[j, 0, l_] * B[0, c] + D2f[j, 1, l_] * B[1, c] + D2f[j, 2, l_] * B[2, c]
        # f2 and H are symmetric in (c, e) (second derivatives): the upper triangle here, mirrored at the end
        for j in range(3):
            for c in range(6):
                for e in range(c, 6):
                    f2[j, c, e] = tmp[j, 0, c] * B[0, e] + tmp[j, 1, c] * B[1, e] + tmp[j, 2, c] * B[2, e]
            for u in range(3):
                for v in range(u, 3):
                    f2[j, 3 + u, 3 + v] += Df[j, 0] * Xw[0, u, v] + Df[j, 1] * Xw[1, u, v] + Df[j, 2] * Xw[2, u, v]
        for c in range(6):
            b0, b1, b2 = (B[0, c], B[1, c], B[2, c]) if c >= 3 else (0.0, 0.0, 0.0)
            for e in range(c, 6):
                for j in range(3):
                    H[j, c, e] += f2[j, c, e]
                c0, c1, c2 = (B[0, e], B[1, e], B[2, e]) if e >= 3 else (0.0, 0.0, 0.0)
                H[3, c, e] += (b1 * f1[2, e] - b2 * f1[1, e] + c1 * f1[2, c] - c2 * f1[1, c]
                               + ry * f2[2, c, e] - rz * f2[1, c, e])
                H[4, c, e] += (b2 * f1[0, e] - b0 * f1[2, e] + c2 * f1[0, c] - c0 * f1[2, c]
                               + rz * f2[0, c, e] - rx * f2[2, c, e])
                H[5, c, e] += (b0 * f1[1, e] - b1 * f1[0, e] + c0 * f1[1, c] - c1 * f1[0, c]
                               + rx * f2[1, c, e] - ry * f2[0, c, e])
        for u in range(3):
            for v in range(u, 3):
                x0, x1, x2 = Xw[0, u, v], Xw[1, u, v], Xw[2, u, v]
                H[3, 3 + u, 3 + v] += x1 * f[2] - x2 * f[1]
                H[4, 3 + u, 3 + v] += x2 * f[0] - x0 * f[2]
                H[5, 3 + u, 3 + v] += x0 * f[1] - x1 * f[0]
    for c in range(6):
        for e in range(c + 1, 6):
            for a in range(6):
                H[a, e, c] = H[a, c, e]
    return W, J, H


def compartment(field: DistanceField, points: np.ndarray, areas: np.ndarray) -> tuple:
    """The compartment of the femoral distance ``field`` against the tibial ``points`` (N x 3,
    tibial frame, m) with their ``areas`` (N, m^2) as the passes read it (module docstring): the
    points inside the field's box that penetrate by less than 0.99 of its depth count."""
    rim = ((field.weights, field.weight_spline.cell_min) if field.weight_spline is not None
           else (np.zeros((0, 0, 0)),) * 2)
    femur = (field.spline, field.cell_min, rim, tuple(field.bounds), 0.99 * field.depth)
    return femur, (points, areas)


@njit(cache=True, inline="always")
def _placed(pose: tuple[np.ndarray, np.ndarray], point: np.ndarray, x: np.ndarray,
            box: tuple[np.ndarray, np.ndarray]) -> bool:
    """The tibial ``point`` placed by the pose ``(Rt, pt)`` into ``x`` (femoral frame); whether it
    lies in the box ``(lo, hi)``."""
    Rt, pt = pose
    lo, hi = box
    inside = True
    for a in range(3):
        x[a] = Rt[a, 0] * point[0] + Rt[a, 1] * point[1] + Rt[a, 2] * point[2] + pt[a]
        if x[a] < lo[a] or x[a] > hi[a]:
            inside = False
    return inside


@njit(cache=True, nogil=True)
def _weight_derivatives(weight: tuple, wmin: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rim weight's value, gradient and Hessian at the points ``X``: exactly 1, 0, 0 without a
    weight (the spline ``weight``'s coefficients empty) and in a cell whose 64 coefficients are all
    1 (``wmin``, the cells' :func:`~kneenlp.geometry.spline_kernels.cell_minimum`: the surface away
    from its rim, no spline evaluated)."""
    m = X.shape[0]
    wv, wg, wh = np.ones(m), np.zeros((m, 3)), np.zeros((m, 3, 3))
    if not weight[0].shape[0]:
        return wv, wg, wh
    t3 = np.empty((1, 3, 3, 3))
    for i in range(m):
        if cell_min_at(wmin, weight, X[i]) < 1.0:
            field_derivatives(weight, X[i:i + 1], (wv[i:i + 1], wg[i:i + 1], wh[i:i + 1], t3))
    return wv, wg, wh


@njit(cache=True, nogil=True)
def contact_batch(compartment: tuple, poses: tuple, law: tuple, order: int, out: np.ndarray) -> None:
    """One ``compartment`` at the ``poses`` (module docstring), fused: every tibial point (tibial
    frame) mapped to the femoral frame, passed over where its cell's lower bound says it cannot
    penetrate, else its field value; the points inside the field's box that penetrate by less than
    ``deepest`` (m) make the contact.  Writes each pose's working-set row (``out[t]``, the layout
    of :data:`kneenlp.model.mesh_contact.WS_SIZE`: the pose, then per unit modulus the wrench, its
    Jacobian and Hessian (:func:`wrench_expansion`), and the largest penetration).  The rim weight
    (:attr:`kneenlp.geometry.sdf.DistanceField.weights`, empty: 1) multiplies every pressure.
    ``law = (kernel, gate)``: the pressure law's kernel (an exponent or a compiled function: module
    docstring) and its gate width (m).  ``order``: the wrench's derivatives written (0: none, the
    residual's value at the pose itself, at a fraction of the cost; 1: the Jacobian, what Newton and
    first-order sensitivities need; 2: the Hessian too; the parts not written are zero)."""
    (spline, cmin, (wcoeffs, wmin), box, deepest), (points, areas) = compartment
    R, p, first, last = poses
    kernel, gate = law
    weight = (wcoeffs, spline[1], spline[2])  # the rim weight's spline, on the field's grid
    n_pts = points.shape[0]
    X = np.empty((n_pts, 3))
    keep = np.empty(n_pts, dtype=np.int64)
    g1, w4 = np.empty(3), (np.empty(4), np.empty(4), np.empty(4))
    for t in range(first, last):
        Rt, pt = R[t], p[t]
        k = 0
        for i in range(n_pts):
            if not _placed((Rt, pt), points[i], X[k], box) or cell_min_at(cmin, spline, X[k]) >= 0.0:
                continue
            keep[k] = i
            k += 1
        d = np.empty(k)
        field_values(spline, X[:k], d)
        m = 0
        for i in range(k):
            if d[i] < 0.0 and d[i] > -deepest:
                X[m] = X[i]
                keep[m] = keep[i]
                m += 1
        row = out[t]
        row[:] = 0.0
        for a in range(3):
            for b in range(3):
                row[3 * b + a] = Rt[a, b]
            row[9 + a] = pt[a]
        depth = 0.0
        if order >= 1:
            dd, g, h, t3 = np.empty(m), np.empty((m, 3)), np.empty((m, 3, 3)), np.empty((m, 3, 3, 3))
            field_derivatives(spline, X[:m], (dd, g, h, t3))
            wv, wg, wh = _weight_derivatives(weight, wmin, X[:m])
            r = np.empty((m, 3))
            a_ = np.empty(m)
            for i in range(m):
                for a in range(3):
                    r[i, a] = X[i, a] - pt[a]
                a_[i] = areas[keep[i]]
                depth = max(depth, -dd[i])
            W, J, H = wrench_expansion((dd, g, h, t3), (r, a_), (wv, wg, wh), (kernel, gate), order)
            for a in range(6):
                row[12 + a] = W[a]
                for b in range(6):
                    row[18 + 6 * b + a] = J[a, b]
                    for c in range(6):
                        row[54 + 36 * c + 6 * b + a] = H[c, a, b]
        else:
            for i in range(m):
                v = value_gradient(spline, X[i], g1)
                s = -v
                depth = max(depth, s)
                gam = pressure(kernel, s, gate)[0]
                if wcoeffs.shape[0] and cell_min_at(wmin, spline, X[i]) < 1.0:
                    gam *= value_at(weight, X[i], w4)
                rho = np.sqrt(g1[0] * g1[0] + g1[1] * g1[1] + g1[2] * g1[2])
                w = areas[keep[i]] * gam / rho
                fx, fy, fz = w * g1[0], w * g1[1], w * g1[2]
                rx, ry, rz = X[i, 0] - pt[0], X[i, 1] - pt[1], X[i, 2] - pt[2]
                row[12] += fx
                row[13] += fy
                row[14] += fz
                row[15] += ry * fz - rz * fy
                row[16] += rz * fx - rx * fz
                row[17] += rx * fy - ry * fx
        row[out.shape[1] - 1] = depth


@njit(cache=True, nogil=True)
def counted_batch(compartment: tuple, poses: tuple, counted: np.ndarray) -> None:
    """Which points :func:`contact_batch` counts at the ``poses``: ``counted[t, i]`` is true where
    point ``i`` lies inside the field's box and penetrates by less than ``deepest`` (m), with the
    same cell-bound rejection."""
    (spline, cmin, _, box, deepest), (points, _) = compartment
    R, p, first, last = poses
    x, w4 = np.empty(3), (np.empty(4), np.empty(4), np.empty(4))
    for t in range(first, last):
        pose = (R[t], p[t])
        for i in range(points.shape[0]):
            counted[t, i] = False
            if not _placed(pose, points[i], x, box) or cell_min_at(cmin, spline, x) >= 0.0:
                continue
            d = value_at(spline, x, w4)
            counted[t, i] = d < 0.0 and d > -deepest


@njit(cache=True, nogil=True)
def left_out_batch(compartment: tuple, poses: tuple, near: tuple[np.ndarray, np.ndarray], deep: np.ndarray,
                   outside: np.ndarray) -> None:
    """What :func:`contact_batch` leaves out at the ``poses``: into ``deep[t]`` the largest
    penetration (m) of a point deeper than ``deepest`` (-inf if none), into ``outside[t, i]``
    whether point ``i`` lies outside the field's box but inside the box ``near = (near_lo,
    near_hi)`` (the caller measures those otherwise; beyond that box a point cannot touch)."""
    (spline, cmin, _, box, deepest), (points, _) = compartment
    R, p, first, last = poses
    near_lo, near_hi = near
    x, w4 = np.empty(3), (np.empty(4), np.empty(4), np.empty(4))
    for t in range(first, last):
        pose = (R[t], p[t])
        worst = -np.inf
        for i in range(points.shape[0]):
            inside = _placed(pose, points[i], x, box)
            if not inside:
                outside[t, i] = (near_lo[0] <= x[0] <= near_hi[0] and near_lo[1] <= x[1] <= near_hi[1]
                                 and near_lo[2] <= x[2] <= near_hi[2])
                continue
            outside[t, i] = False
            if cell_min_at(cmin, spline, x) > -deepest:
                continue
            d = value_at(spline, x, w4)
            if d <= -deepest:
                worst = max(worst, -d)
        deep[t] = worst
