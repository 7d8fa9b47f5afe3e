"""SimTK kinematics primitives of an OpenSim model: body-fixed X-Y-Z rotations, homogeneous
transforms (``X_AB`` maps a point of frame B to frame A; 4 x 4, m) and the OpenSim functions a
``CustomJoint``'s ``TransformAxis`` evaluates (constant, linear, multiplier, piecewise linear,
SimmSpline).  Conventions: :mod:`kneenlp.io.osim`."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np


class OsimError(ValueError):
    """One-line error about an .osim file; the message names the file and the element."""


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

