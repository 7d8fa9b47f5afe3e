"""Compiled per-point loops of the mesh contact (numba): the tricubic field's derivatives and the
contact wrench's expansion, summed over the penetrating points.

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
"""

from __future__ import annotations

import os

import numba
import numpy as np
from numba import njit, types
from numba.extending import overload

from kneenlp.base.cache import cache_dir
from kneenlp.geometry.ramp import gate_derivatives

# numba keeps compiled loops next to the module unless told otherwise: into the user's cache
# instead (a user's own NUMBA_CACHE_DIR wins).  Set before the decorators below read it.
if not os.environ.get("NUMBA_CACHE_DIR") and (_where := cache_dir("numba")) is not None:
    numba.config.CACHE_DIR = str(_where)

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


@njit(cache=True, inline="always")
def _basis(t: float, out: np.ndarray) -> None:
    """Cubic B-spline weights and their first three derivatives at fraction ``t``: out[k, i]."""
    s = 1.0 - t
    out[0, 0] = s * s * s / 6.0
    out[0, 1] = (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0
    out[0, 2] = (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) / 6.0
    out[0, 3] = t * t * t / 6.0
    out[1, 0] = -s * s / 2.0
    out[1, 1] = (3.0 * t * t - 4.0 * t) / 2.0
    out[1, 2] = (-3.0 * t * t + 2.0 * t + 1.0) / 2.0
    out[1, 3] = t * t / 2.0
    out[2, 0] = s
    out[2, 1] = 3.0 * t - 2.0
    out[2, 2] = 1.0 - 3.0 * t
    out[2, 3] = t
    out[3, 0] = -1.0
    out[3, 1] = 3.0
    out[3, 2] = -3.0
    out[3, 3] = 1.0


@njit(cache=True, inline="always")
def _cell(origin: np.ndarray, spacing: float, x: np.ndarray, wx: np.ndarray, wy: np.ndarray,
          wz: np.ndarray) -> tuple[int, int, int]:
    """Grid cell of point ``x`` (its lower node's indices) and the basis weights along each axis."""
    ux, uy, uz = (x[0] - origin[0]) / spacing, (x[1] - origin[1]) / spacing, (x[2] - origin[2]) / spacing
    ix, iy, iz = int(np.floor(ux)), int(np.floor(uy)), int(np.floor(uz))
    _basis(ux - ix, wx)
    _basis(uy - iy, wy)
    _basis(uz - iz, wz)
    return ix, iy, iz


@njit(cache=True, inline="always")
def _weights(u: float, w: np.ndarray) -> int:
    """The value weights of the cubic B-spline (:func:`_basis` row 0) at grid coordinate ``u``,
    into ``w`` (4); returns the cell's lower node index."""
    i = int(np.floor(u))
    t = u - i
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    w[0] = s * s * s / 6.0
    w[1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
    w[2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
    w[3] = t3 / 6.0
    return i


@njit(cache=True, inline="always")
def _value(coeffs: np.ndarray, origin: np.ndarray, spacing: float, x0: float, x1: float, x2: float,
           wx: np.ndarray, wy: np.ndarray, wz: np.ndarray) -> float:
    """The tricubic B-spline's value at ``(x0, x1, x2)`` (inside the grid); ``w*`` are scratch (4)."""
    ix = _weights((x0 - origin[0]) / spacing, wx)
    iy = _weights((x1 - origin[1]) / spacing, wy)
    iz = _weights((x2 - origin[2]) / spacing, wz)
    v = 0.0
    for a in range(4):
        va = 0.0
        for b in range(4):
            col = coeffs[ix - 1 + a, iy - 1 + b]
            va += wy[b] * (col[iz - 1] * wz[0] + col[iz] * wz[1] + col[iz + 1] * wz[2] + col[iz + 2] * wz[3])
        v += wx[a] * va
    return v


@njit(cache=True, nogil=True)
def field_values(coeffs: np.ndarray, origin: np.ndarray, spacing: float, X: np.ndarray, d: np.ndarray) -> None:
    """Values of the tricubic B-spline ``coeffs`` at the points ``X`` (all inside the grid), into ``d``."""
    wx, wy, wz = np.empty(4), np.empty(4), np.empty(4)
    for n in range(X.shape[0]):
        d[n] = _value(coeffs, origin, spacing, X[n, 0], X[n, 1], X[n, 2], wx, wy, wz)


@njit(cache=True, nogil=True)
def field_derivatives(coeffs: np.ndarray, origin: np.ndarray, spacing: float, X: np.ndarray,
                      d: np.ndarray, g: np.ndarray, h: np.ndarray, t3: np.ndarray) -> None:
    """Value, gradient, Hessian and third derivatives of the tricubic B-spline ``coeffs`` (grid
    ``origin + spacing * index``) at the points ``X`` (all inside the grid), into ``d`` (n),
    ``g`` (n x 3), ``h`` (n x 3 x 3), ``t3`` (n x 3 x 3 x 3)."""
    wx = np.empty((4, 4))
    wy = np.empty((4, 4))
    wz = np.empty((4, 4))
    acc = np.empty((4, 4, 4))  # acc[kx, ky, kz]: derivative orders per axis, kx + ky + kz <= 3
    for n in range(X.shape[0]):
        ix, iy, iz = _cell(origin, spacing, X[n], wx, wy, wz)
        acc[:] = 0.0
        for a in range(4):
            for b in range(4):
                # contract z first: one coefficient column, four derivative orders
                cz0 = cz1 = cz2 = cz3 = 0.0
                for c in range(4):
                    v = coeffs[ix - 1 + a, iy - 1 + b, iz - 1 + c]
                    cz0 += v * wz[0, c]
                    cz1 += v * wz[1, c]
                    cz2 += v * wz[2, c]
                    cz3 += v * wz[3, c]
                for kx in range(4):
                    wa = wx[kx, a]
                    for ky in range(4 - kx):
                        wab = wa * wy[ky, b]
                        acc[kx, ky, 0] += wab * cz0
                        if kx + ky <= 2:
                            acc[kx, ky, 1] += wab * cz1
                        if kx + ky <= 1:
                            acc[kx, ky, 2] += wab * cz2
                        if kx + ky == 0:
                            acc[kx, ky, 3] += wab * cz3
        d[n] = acc[0, 0, 0]
        s1, s2, s3 = 1.0 / spacing, 1.0 / spacing**2, 1.0 / spacing**3
        for i in range(3):  # derivative along axes i (j, m): orders per axis are the counts of each axis
            g[n, i] = acc[int(i == 0), int(i == 1), int(i == 2)] * s1
            for j in range(3):
                h[n, i, j] = acc[int(i == 0) + int(j == 0), int(i == 1) + int(j == 1), int(i == 2) + int(j == 2)] * s2
                for m in range(3):
                    t3[n, i, j, m] = acc[int(i == 0) + int(j == 0) + int(m == 0), int(i == 1) + int(j == 1)
                                         + int(m == 1), int(i == 2) + int(j == 2) + int(m == 2)] * s3


@njit(cache=True, nogil=True)
def wrench_expansion(d: np.ndarray, g: np.ndarray, h: np.ndarray, t3: np.ndarray, r: np.ndarray,
                     areas: np.ndarray, law, gate: float, order: int, wv: np.ndarray, wg: np.ndarray,
                     wh: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """See :func:`kneenlp.model.mesh_contact.wrench_expansion` (same arguments but ``X``, same
    results): wrench (6), Jacobian (6 x 6), Hessian (6 x 6 x 6) per unit modulus.  ``order=1``:
    the Hessian is left zero (``t3`` and ``wh`` are not read), at about half the cost.  ``wv``,
    ``wg``, ``wh`` (n, n x 3, n x 3 x 3): the rim weight's value, gradient and Hessian at the points
    (1, 0, 0 on a surface without an open edge): the pressure is ``w(X) h(s)``."""
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
        gam, gam1, gam2 = pressure(law, s, gate)  # the pressure law's value and depth derivatives, per unit modulus
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


def cell_minimum(coeffs: np.ndarray) -> np.ndarray:
    """Per grid cell, the smallest of the 64 coefficients that shape the spline in it: ``out[i, j, k]
    = min(coeffs[i-1:i+3, j-1:j+3, k-1:k+3])`` (``+inf`` where that block leaves the grid).  A
    B-spline is a convex combination of its coefficients, so the field is at least ``out`` in the
    cell whose lower node is ``(i, j, k)``: a point there with ``out >= 0`` cannot penetrate, and is
    passed over with one look-up (:func:`contact_batch`)."""
    m = np.asarray(coeffs, dtype=np.float64)
    for axis in range(3):
        n = m.shape[axis]
        pad = [(0, 0)] * 3
        pad[axis] = (1, 2)
        padded = np.pad(m, pad, constant_values=np.inf)  # node i of m is node i + 1 of padded
        m = np.minimum.reduce([np.take(padded, np.arange(s, s + n), axis=axis) for s in range(4)])
    return m


def cell_lower_bound(coeffs: np.ndarray) -> np.ndarray:
    """Per grid cell, a lower bound of the tricubic B-spline in it, at least :func:`cell_minimum`:
    in the cells whose 64 coefficients lie inside the grid also the value at the cell's centre less
    half the largest coefficient difference along each axis, summed (the spline's derivative along an
    axis is a B-spline of the differences over the spacing, and no point of the cell is farther than
    half a spacing from the centre along any axis).  Near a surface the smallest coefficient is
    negative for points up to two spacings away; this bound passes over those more than about half a
    spacing clear (:func:`contact_batch`)."""
    c = np.asarray(coeffs, dtype=np.float64)
    out = cell_minimum(c)
    if min(c.shape) < 4:
        return out
    w = np.array([1.0, 23.0, 23.0, 1.0]) / 48.0  # the cubic B-spline's weights at the cell's centre
    centre = c
    for axis in range(3):
        n = centre.shape[axis] - 3
        centre = sum(w[s] * np.take(centre, np.arange(s, s + n), axis=axis) for s in range(4))
    change = np.zeros_like(centre)
    for axis in range(3):
        block = np.abs(np.diff(c, axis=axis))
        for other in range(3):  # the block's largest difference: 3 differences along the axis, 4 nodes across
            width = 3 if other == axis else 4
            n = block.shape[other] - width + 1
            block = np.maximum.reduce([np.take(block, np.arange(s, s + n), axis=other) for s in range(width)])
        change += 0.5 * block
    inner = (slice(1, -2),) * 3  # lower nodes 1 .. n-3: the cells whose coefficients lie inside the grid
    out[inner] = np.maximum(out[inner], centre - change)
    return out


@njit(cache=True, nogil=True)
def _value_gradient(coeffs: np.ndarray, origin: np.ndarray, spacing: float, x: np.ndarray,
                    g: np.ndarray) -> float:
    """Value of the tricubic B-spline at ``x`` (inside the grid); its gradient into ``g``."""
    wx = np.empty((4, 4))
    wy = np.empty((4, 4))
    wz = np.empty((4, 4))
    ix, iy, iz = _cell(origin, spacing, x, wx, wy, wz)
    v = gx = gy = gz = 0.0
    for a in range(4):
        for b in range(4):
            cz0 = cz1 = 0.0
            for c in range(4):
                co = coeffs[ix - 1 + a, iy - 1 + b, iz - 1 + c]
                cz0 += co * wz[0, c]
                cz1 += co * wz[1, c]
            v += wx[0, a] * wy[0, b] * cz0
            gx += wx[1, a] * wy[0, b] * cz0
            gy += wx[0, a] * wy[1, b] * cz0
            gz += wx[0, a] * wy[0, b] * cz1
    g[0], g[1], g[2] = gx / spacing, gy / spacing, gz / spacing
    return v


@njit(cache=True, inline="always")
def _placed(Rt: np.ndarray, pt: np.ndarray, point: np.ndarray, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """The tibial ``point`` placed by the pose ``(Rt, pt)`` into ``x`` (femoral frame); whether it
    lies in the box ``lo..hi``."""
    inside = True
    for a in range(3):
        x[a] = Rt[a, 0] * point[0] + Rt[a, 1] * point[1] + Rt[a, 2] * point[2] + pt[a]
        if x[a] < lo[a] or x[a] > hi[a]:
            inside = False
    return inside


@njit(cache=True, inline="always")
def _cell_min_at(cmin: np.ndarray, origin: np.ndarray, spacing: float, x: np.ndarray) -> float:
    """:func:`cell_minimum` of the cell holding ``x`` (inside the grid)."""
    return cmin[int(np.floor((x[0] - origin[0]) / spacing)), int(np.floor((x[1] - origin[1]) / spacing)),
                int(np.floor((x[2] - origin[2]) / spacing))]


@njit(cache=True, nogil=True)
def _weight_derivatives(wcoeffs: np.ndarray, wmin: np.ndarray, origin: np.ndarray, spacing: float,
                        X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rim weight's value, gradient and Hessian at the points ``X``: exactly 1, 0, 0 without a
    weight (``wcoeffs`` empty) and in a cell whose 64 coefficients are all 1 (``wmin``, the cells'
    :func:`cell_minimum`: the surface away from its rim, no spline evaluated)."""
    m = X.shape[0]
    wv, wg, wh = np.ones(m), np.zeros((m, 3)), np.zeros((m, 3, 3))
    if not wcoeffs.shape[0]:
        return wv, wg, wh
    t3 = np.empty((1, 3, 3, 3))
    for i in range(m):
        if _cell_min_at(wmin, origin, spacing, X[i]) < 1.0:
            field_derivatives(wcoeffs, origin, spacing, X[i:i + 1], wv[i:i + 1], wg[i:i + 1], wh[i:i + 1], t3)
    return wv, wg, wh


@njit(cache=True, nogil=True)
def contact_batch(coeffs: np.ndarray, cmin: np.ndarray, wcoeffs: np.ndarray, wmin: np.ndarray, origin: np.ndarray,
                  spacing: float, lo: np.ndarray, hi: np.ndarray, deepest: float, points: np.ndarray,
                  areas: np.ndarray, R: np.ndarray, p: np.ndarray, law, gate: float, order: int, first: int,
                  last: int, out: np.ndarray) -> None:
    """One compartment at the poses ``first..last-1`` of ``R`` (T x 3 x 3) and ``p`` (T x 3), fused:
    every tibial point (tibial frame) mapped to the femoral frame, passed over where the cell's
    :func:`cell_minimum` says it cannot penetrate, else its field value; the points inside the box
    ``lo..hi`` that penetrate by less than ``deepest`` (m) make the contact.  Writes each pose's
    working-set row (``out[t]``, the layout of :data:`kneenlp.model.mesh_contact.WS_SIZE`: the pose,
    then per unit modulus the wrench, its Jacobian and Hessian (:func:`wrench_expansion`), and the
    largest penetration).  ``wcoeffs``, ``wmin``: the rim weight (:attr:`kneenlp.geometry.sdf.
    DistanceField.weights`, empty: 1) and its :func:`cell_minimum`; it multiplies every pressure.
    ``law`` is the pressure law's kernel (an exponent or a compiled function: module docstring),
    ``gate`` its gate width (m).  ``order``: the wrench's derivatives written (0: none, the
    residual's value at the pose itself, at a fraction of the cost; 1: the Jacobian, what Newton and
    first-order sensitivities need; 2: the Hessian too; the parts not written are zero)."""
    n_pts = points.shape[0]
    X = np.empty((n_pts, 3))
    keep = np.empty(n_pts, dtype=np.int64)
    g1, wx, wy, wz = np.empty(3), np.empty(4), np.empty(4), np.empty(4)
    for t in range(first, last):
        Rt, pt = R[t], p[t]
        k = 0
        for i in range(n_pts):
            if not _placed(Rt, pt, points[i], X[k], lo, hi) or _cell_min_at(cmin, origin, spacing, X[k]) >= 0.0:
                continue
            keep[k] = i
            k += 1
        d = np.empty(k)
        field_values(coeffs, origin, spacing, X[:k], d)
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
            field_derivatives(coeffs, origin, spacing, X[:m], dd, g, h, t3)
            wv, wg, wh = _weight_derivatives(wcoeffs, wmin, origin, spacing, X[:m])
            r = np.empty((m, 3))
            a_ = np.empty(m)
            for i in range(m):
                for a in range(3):
                    r[i, a] = X[i, a] - pt[a]
                a_[i] = areas[keep[i]]
                depth = max(depth, -dd[i])
            W, J, H = wrench_expansion(dd, g, h, t3, r, a_, law, gate, order, wv, wg, wh)
            for a in range(6):
                row[12 + a] = W[a]
                for b in range(6):
                    row[18 + 6 * b + a] = J[a, b]
                    for c in range(6):
                        row[54 + 36 * c + 6 * b + a] = H[c, a, b]
        else:
            for i in range(m):
                v = _value_gradient(coeffs, origin, spacing, X[i], g1)
                s = -v
                depth = max(depth, s)
                gam = pressure(law, s, gate)[0]
                if wcoeffs.shape[0] and _cell_min_at(wmin, origin, spacing, X[i]) < 1.0:
                    gam *= _value(wcoeffs, origin, spacing, X[i, 0], X[i, 1], X[i, 2], wx, wy, wz)
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
def counted_batch(coeffs: np.ndarray, cmin: np.ndarray, origin: np.ndarray, spacing: float, lo: np.ndarray,
                  hi: np.ndarray, deepest: float, points: np.ndarray, R: np.ndarray, p: np.ndarray, first: int,
                  last: int, counted: np.ndarray) -> None:
    """Which points :func:`contact_batch` counts at the poses ``first..last-1``: ``counted[t, i]``
    is true where point ``i`` lies inside the box ``lo..hi`` and penetrates by less than
    ``deepest`` (m), with the same cell-minimum rejection."""
    x, wx, wy, wz = np.empty(3), np.empty(4), np.empty(4), np.empty(4)
    for t in range(first, last):
        Rt, pt = R[t], p[t]
        for i in range(points.shape[0]):
            counted[t, i] = False
            if not _placed(Rt, pt, points[i], x, lo, hi) or _cell_min_at(cmin, origin, spacing, x) >= 0.0:
                continue
            d = _value(coeffs, origin, spacing, x[0], x[1], x[2], wx, wy, wz)
            counted[t, i] = d < 0.0 and d > -deepest


@njit(cache=True, nogil=True)
def left_out_batch(coeffs: np.ndarray, cmin: np.ndarray, origin: np.ndarray, spacing: float, lo: np.ndarray,
                   hi: np.ndarray, deepest: float, points: np.ndarray, R: np.ndarray, p: np.ndarray, first: int,
                   last: int, near_lo: np.ndarray, near_hi: np.ndarray, deep: np.ndarray, outside: np.ndarray) -> None:
    """What :func:`contact_batch` leaves out at the poses ``first..last-1``: into ``deep[t]`` the
    largest penetration (m) of a point deeper than ``deepest`` (-inf if none), into ``outside[t, i]``
    whether point ``i`` lies outside the field's box but inside the box ``near_lo..near_hi`` (the
    caller measures those otherwise; beyond that box a point cannot touch)."""
    x, wx, wy, wz = np.empty(3), np.empty(4), np.empty(4), np.empty(4)
    for t in range(first, last):
        Rt, pt = R[t], p[t]
        worst = -np.inf
        for i in range(points.shape[0]):
            inside = _placed(Rt, pt, points[i], x, lo, hi)
            if not inside:
                outside[t, i] = (near_lo[0] <= x[0] <= near_hi[0] and near_lo[1] <= x[1] <= near_hi[1]
                                 and near_lo[2] <= x[2] <= near_hi[2])
                continue
            outside[t, i] = False
            if _cell_min_at(cmin, origin, spacing, x) > -deepest:
                continue
            d = _value(coeffs, origin, spacing, x[0], x[1], x[2], wx, wy, wz)
            if d <= -deepest:
                worst = max(worst, -d)
        deep[t] = worst
