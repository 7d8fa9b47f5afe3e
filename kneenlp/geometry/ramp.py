"""The smooth ramp of contact: a C2 ``max(s, 0)`` that is exactly ``s`` beyond a small width.

``g(s) = 0`` for ``s <= 0``, ``g(s) = s`` for ``s >= delta`` and, in between,
``g = delta h(s / delta)`` with ``h(x) = 6 x^3 - 8 x^4 + 3 x^5``: value, slope and curvature meet
both pieces (``h(0) = h'(0) = h''(0) = 0``, ``h(1) = h'(1) = 1``, ``h''(1) = 0``), and ``h' > 0``
inside, so ``g`` is monotone.  Beyond the width the elastic-foundation pressure ``K g(s)`` is
exactly the paper's ``K s`` (the earlier polynomial left it ``delta / 2`` short).

The polynomial pieces take the clamped penetration ``t = min(max(s, 0), delta)`` and use only
arithmetic, so the same functions serve floats, NumPy arrays, CasADi symbols and compiled (numba)
kernels; the callers add the linear part ``max(s, delta) - delta``.
"""

from __future__ import annotations

from numba.extending import register_jitable


@register_jitable
def ramp_inner(t, delta):
    """``delta h(t / delta)`` for ``0 <= t <= delta`` (m)."""
    x = t / delta
    return delta * x * x * x * (6.0 - 8.0 * x + 3.0 * x * x)


@register_jitable
def ramp_inner_slope(t, delta):
    """``h'(t / delta)``: the ramp's slope for ``0 <= t <= delta`` (1 at ``t = delta``)."""
    x = t / delta
    return x * x * (18.0 - 32.0 * x + 15.0 * x * x)


@register_jitable
def ramp_inner_curvature(t, delta):
    """``h''(t / delta) / delta``: the ramp's curvature for ``0 <= t <= delta`` (1/m)."""
    x = t / delta
    return x * (36.0 - 96.0 * x + 60.0 * x * x) / delta


@register_jitable
def gate_derivatives(s: float, delta: float) -> tuple[float, float, float]:
    """The ramp ``g(s)`` (m) and its first two derivatives at one depth ``s`` (m), for compiled loops."""
    if s <= 0.0:
        return 0.0, 0.0, 0.0
    if s < delta:
        return ramp_inner(s, delta), ramp_inner_slope(s, delta), ramp_inner_curvature(s, delta)
    return s, 1.0, 0.0
