"""The tricubic B-spline of a distance field, compiled (numba): its value and derivatives up to
third order at points, and per grid cell a lower bound (what lets the contact passes of
:mod:`kneenlp.geometry.kernels` pass over a point that cannot penetrate with one look-up).

A spline is passed to the compiled functions as the tuple ``spline = (coeffs, origin, spacing)``
(:attr:`kneenlp.geometry.sdf.DistanceField.spline`): the coefficients (nx x ny x nz, m) on the grid
``origin + spacing * (i, j, k)`` (m).  Compiled once per machine into the user's cache
(:mod:`kneenlp.geometry.kernels`).
"""

from __future__ import annotations

import os

import numba
import numpy as np
from numba import njit

from kneenlp.base.cache import cache_dir

# numba keeps compiled loops next to the module unless told otherwise: into the user's cache
# instead (a user's own NUMBA_CACHE_DIR wins).  Set before the decorators below (and those of
# kneenlp.geometry.kernels, which imports this module first) read it.
if not os.environ.get("NUMBA_CACHE_DIR") and (_where := cache_dir("numba")) is not None:
    numba.config.CACHE_DIR = str(_where)

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
def _cell(spline: tuple, x: np.ndarray, w: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[int, int, int]:
    """Grid cell of point ``x`` (its lower node's indices) and the basis weights along each axis,
    into ``w = (wx, wy, wz)`` (4 x 4 each, :func:`_basis`)."""
    _, origin, spacing = spline
    wx, wy, wz = w
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
def value_at(spline: tuple, x: np.ndarray, w: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
    """The tricubic B-spline's value at ``x`` (3, inside the grid); ``w = (wx, wy, wz)`` are scratch (4 each)."""
    coeffs, origin, spacing = spline
    wx, wy, wz = w
    ix = _weights((x[0] - origin[0]) / spacing, wx)
    iy = _weights((x[1] - origin[1]) / spacing, wy)
    iz = _weights((x[2] - origin[2]) / spacing, wz)
    v = 0.0
    for a in range(4):
        va = 0.0
        for b in range(4):
            col = coeffs[ix - 1 + a, iy - 1 + b]
            va += wy[b] * (col[iz - 1] * wz[0] + col[iz] * wz[1] + col[iz + 1] * wz[2] + col[iz + 2] * wz[3])
        v += wx[a] * va
    return v


@njit(cache=True, nogil=True)
def field_values(spline: tuple, X: np.ndarray, d: np.ndarray) -> None:
    """Values of the tricubic B-spline ``spline`` at the points ``X`` (all inside the grid), into ``d``."""
    w = (np.empty(4), np.empty(4), np.empty(4))
    for n in range(X.shape[0]):
        d[n] = value_at(spline, X[n], w)


@njit(cache=True, nogil=True)
def field_derivatives(spline: tuple, X: np.ndarray,
                      out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> None:
    """Value, gradient, Hessian and third derivatives of the tricubic B-spline ``spline`` at the
    points ``X`` (all inside the grid), into ``out = (d, g, h, t3)``: ``d`` (n), ``g`` (n x 3),
    ``h`` (n x 3 x 3), ``t3`` (n x 3 x 3 x 3)."""
    coeffs, _, spacing = spline
    d, g, h, t3 = out
    wx = np.empty((4, 4))
    wy = np.empty((4, 4))
    wz = np.empty((4, 4))
    acc = np.empty((4, 4, 4))  # acc[kx, ky, kz]: derivative orders per axis, kx + ky + kz <= 3
    for n in range(X.shape[0]):
        ix, iy, iz = _cell(spline, X[n], (wx, wy, wz))
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



def cell_minimum(coeffs: np.ndarray) -> np.ndarray:
    """Per grid cell, the smallest of the 64 coefficients that shape the spline in it: ``out[i, j, k]
    = min(coeffs[i-1:i+3, j-1:j+3, k-1:k+3])`` (``+inf`` where that block leaves the grid).  A
    B-spline is a convex combination of its coefficients, so the field is at least ``out`` in the
    cell whose lower node is ``(i, j, k)``: a point there with ``out >= 0`` cannot penetrate, and is
    passed over with one look-up (:func:`kneenlp.geometry.kernels.contact_batch`)."""
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
    spacing clear (:func:`kneenlp.geometry.kernels.contact_batch`)."""
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
def value_gradient(spline: tuple, x: np.ndarray, g: np.ndarray) -> float:
    """Value of the tricubic B-spline at ``x`` (inside the grid); its gradient into ``g``."""
    coeffs, _, spacing = spline
    wx = np.empty((4, 4))
    wy = np.empty((4, 4))
    wz = np.empty((4, 4))
    ix, iy, iz = _cell(spline, x, (wx, wy, wz))
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
def cell_min_at(cmin: np.ndarray, spline: tuple, x: np.ndarray) -> float:
    """:func:`cell_minimum` (or :func:`cell_lower_bound`) ``cmin`` of the spline's cell holding ``x``
    (inside the grid)."""
    _, origin, spacing = spline
    return cmin[int(np.floor((x[0] - origin[0]) / spacing)), int(np.floor((x[1] - origin[1]) / spacing)),
                int(np.floor((x[2] - origin[2]) / spacing))]
