"""The shortest path outside a body given by its signed distance: a taut string over a bone.

A ligament that wraps a bone runs straight from its attachment to where it meets the surface,
along the surface, and straight again to its other attachment: the shortest path from ``s`` to
``e`` that stays outside the body, on or beyond the level ``d = clearance`` of its signed
distance ``d`` (m, negative inside; :class:`~kneenlp.geometry.sdf.DistanceField`).  It is
discretised as a polyline through :data:`NODES` nodes with segments of equal length (so the nodes
never bunch, wherever the path turns, and a path that misses the body is the chord itself):

    minimise    F(Y) = sum_j |a_j|,   a_j = y_{j+1} - y_j     (y_0 = s, y_{K+1} = e)
    subject to  h_k = |a_k|^2 - |a_{k-1}|^2 = 0                (equal segments, k = 1..K)
                g_k = d(y_k) - clearance >= 0                  (outside the body).

Chords of a curved contact shorten it by about ``r beta^3 / (24 n^2)`` over an arc of angle beta
and radius r split ``n`` ways: with 24 nodes a 90 deg wrap loses 2e-4 of its arc.  (Nodes on
planes across the chord, the first design, failed where the bone faces along the chord: on
S192803's tibial flare 2-11 % of poses; equal segments converge at all of them.)

:func:`taut_path` solves it, batched over many ``(s, e)``, by sequential quadratic steps on the
KKT conditions with an active set, from the chord's nodes pushed out of the body; then the
implicit function theorem gives the nodes' first-order response to ``s`` and ``e``.
:meth:`TautPath.data` packs what :func:`lagrangian` needs: the Lagrangian ``F - mu . h - lambda .
g`` with the nodes moving linearly with ``s`` and ``e`` and ``d`` expanded to second order about
each node.  As a function of ``s`` and ``e`` it equals the shortest length at the solution, with
the same first and second derivatives there (the envelope theorem: the Lagrangian's derivatives,
not the length's, since the constraints move with ``s`` and ``e``) - so a model that takes these
data at every pose it evaluates sees the path's exact length, gradient and Hessian.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.linalg

#: Nodes of the discretised path (module docstring: 2e-4 of a 90 deg arc).
NODES = 24
#: Iterations at most (S192803's superficial MCL over its tibia at 600 poses: 6.3 on average, at most 21).
MAX_ITER = 80
#: Converged when the stationarity (unit vectors) and the constraints (m) are below this.
TOLERANCE = 1e-11
#: Newton's steps (the Hessian of the Lagrangian) once the KKT residual is below this; a node is
#: released from the active set only then (:func:`taut_path`).
NEAR = 5e-2
#: A step that leaves the KKT residual above this share of the last one has stalled on its active set.
STALL = 0.9
#: Weight of a node's depth inside the body in the line search's merit (above any multiplier: a
#: contact multiplier is the path's turn at the node, at most 2).
PENALTY = 10.0
#: Numbers per node in :meth:`TautPath.data`: node (3), its response to (s, e) (18), the spacing's and
#: the contact's multipliers (2), the contact's gap (1), the distance's gradient (3) and Hessian (9).
PER_NODE = 36
#: The longest step of a node (m): the distance's second-order model holds over it.
STEP = 5e-3


def data_size(nodes: int = NODES) -> int:
    """Length of one path's :meth:`TautPath.data`: ``s`` and ``e`` (6) and :data:`PER_NODE` a node."""
    return 6 + PER_NODE * nodes


@dataclass(frozen=True)
class TautPath:
    """Solved paths (T of them, K nodes; m): ends, nodes, the nodes' response ``dnodes`` to ``(s, e)``
    (T x K x 3 x 6), the spacing's multipliers ``mu`` and the contacts' ``lam`` (T x K), the gap
    ``gap`` of each node and the distance's ``grad`` and ``hess`` there, the polyline's ``length``
    (T), whether each solve ``converged`` and its ``iterations`` (T)."""

    start: np.ndarray
    end: np.ndarray
    nodes: np.ndarray
    dnodes: np.ndarray
    mu: np.ndarray
    lam: np.ndarray
    gap: np.ndarray
    grad: np.ndarray
    hess: np.ndarray
    length: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray

    @property
    def wrapped(self) -> np.ndarray:
        """Whether each path touches the body (T, bool)."""
        return np.any(self.lam > 0, axis=1)

    def data(self) -> np.ndarray:
        """The packed inputs of :func:`lagrangian` (T x :func:`data_size`); NaN for a path whose solve
        did not converge (the model's residual is then NaN: a failed solve, not a wrong number)."""
        T, K = self.mu.shape
        per = np.concatenate([self.nodes, self.dnodes.reshape(T, K, 18), self.mu[..., None], self.lam[..., None],
                              self.gap[..., None], self.grad, self.hess.reshape(T, K, 9)], axis=2)
        out = np.concatenate([self.start, self.end, per.reshape(T, -1)], axis=1)
        out[~self.converged] = np.nan
        return out


def lagrangian(s: ca.SX, e: ca.SX, data: ca.SX, nodes: int = NODES) -> ca.SX:
    """The path's length as a CasADi expression of its ends ``s`` and ``e`` (m, the body's frame)
    from its :meth:`TautPath.data` (module docstring: exact value, gradient and Hessian where the
    data were taken)."""
    K = nodes
    s0, e0 = data[0:3], data[3:6]
    shift = ca.vertcat(s - s0, e - e0)
    chain, mus, total, contact = [s], [], 0, 0
    for k in range(K):
        block = data[6 + PER_NODE * k: 6 + PER_NODE * (k + 1)]
        y0, J = block[0:3], ca.reshape(block[3:21], 6, 3).T  # (row-major in the data)
        mu, lam, gap, grad, hess = block[21], block[22], block[23], block[24:27], ca.reshape(block[27:36], 3, 3)
        y = y0 + J @ shift
        dy = y - y0
        contact += lam * (gap + ca.dot(grad, dy) + 0.5 * ca.dot(dy, hess @ dy))
        chain.append(y)
        mus.append(mu)
    chain.append(e)
    segments = [b - a for a, b in itertools.pairwise(chain)]
    total = sum(ca.norm_2(a) for a in segments)
    spacing = sum(mu * (ca.dot(segments[k + 1], segments[k + 1]) - ca.dot(segments[k], segments[k]))
                  for k, mu in enumerate(mus))
    return total - spacing - contact


def _segments(start, end, Y):
    """Unit vectors (T x K+1 x 3) and lengths (T x K+1) of the polyline's segments."""
    chain = np.concatenate([start[:, None], Y, end[:, None]], axis=1)
    seg = np.diff(chain, axis=1)
    length = np.linalg.norm(seg, axis=2)
    return seg / np.maximum(length, 1e-300)[..., None], length


def _kkt(start, end, Y, mu, lam, active, values, grads, hessians, curvature: bool | np.ndarray, jacobian: bool = True):
    """The KKT residual (T x 5K) and its Jacobian (T x 5K x 5K; None without ``jacobian``) in
    (nodes, mu, lam), and the segments' unit vectors and lengths; ``curvature`` (T, bool): whether
    the Jacobian's Hessian is the Lagrangian's (Newton's) or the length's own."""
    T, K = mu.shape
    u, ell = _segments(start, end, Y)
    a = np.diff(np.concatenate([start[:, None], Y, end[:, None]], axis=1), axis=1)  # T x K+1 x 3
    n = 5 * K
    r = np.zeros((T, n))
    m = np.concatenate([np.zeros((T, 1)), mu, np.zeros((T, 1))], axis=1)  # mu_0 = mu_K+1 = 0
    dm_prev, dm_next = (m[:, 1:-1] - m[:, :-2]), (m[:, 1:-1] - m[:, 2:])
    stat = (u[:, :-1] - u[:, 1:] + 2 * dm_prev[..., None] * a[:, :-1] + 2 * dm_next[..., None] * a[:, 1:]
            - lam[..., None] * grads)
    r[:, : 3 * K] = stat.reshape(T, -1)
    r[:, 3 * K: 4 * K] = np.sum(a[:, 1:] ** 2, axis=2) - np.sum(a[:, :-1] ** 2, axis=2)
    r[:, 4 * K:] = np.where(active, values, lam)
    if not jacobian:
        return r, None, u, ell
    B = (np.eye(3) - u[..., :, None] * u[..., None, :]) / np.maximum(ell, 1e-300)[..., None, None]  # T x K+1 x 3 x 3
    on = np.asarray(curvature, float).reshape(-1, 1) * np.ones((T, 1))
    eye = np.eye(3)
    M = np.zeros((T, K, 3, K, 3))  # the nodes' block: block tridiagonal
    k = np.arange(K)
    diag = (B[:, :-1] + B[:, 1:] + (on * 2 * (m[:, 2:] - m[:, :-2]))[..., None, None] * eye
            - (on * lam)[..., None, None] * hessians)
    M[:, k, :, k, :] = diag.transpose(1, 0, 2, 3)
    off = -B[:, 1:-1] + (on * 2 * (mu[:, :-1] - mu[:, 1:]))[..., None, None] * eye  # (k, k+1) and (k+1, k)
    M[:, k[:-1], :, k[1:], :] = off.transpose(1, 0, 2, 3)
    M[:, k[1:], :, k[:-1], :] = off.transpose(1, 0, 2, 3)
    out = np.zeros((T, n, n))
    out[:, : 3 * K, : 3 * K] = M.reshape(T, 3 * K, 3 * K)
    rows = 3 * k[:, None] + np.arange(3)  # K x 3
    # d(stat_k)/d(mu_j) = -grad_{y_k} h_j; the h rows are grad h (the KKT matrix is symmetric)
    grad_own = -2 * (a[:, 1:] + a[:, :-1])  # d h_k / d y_k
    out[:, rows, 3 * K + k[:, None]] = -grad_own
    out[:, 3 * K + k[:, None], rows] = grad_own
    out[:, rows[1:], 3 * K + k[:-1, None]] = -2 * a[:, 1:-1]  # d h_{k-1} / d y_k = 2 a_{k-1}
    out[:, 3 * K + k[:-1, None], rows[1:]] = 2 * a[:, 1:-1]
    out[:, rows[:-1], 3 * K + k[1:, None]] = -2 * a[:, 1:-1]  # d h_{k+1} / d y_k = 2 a_k
    out[:, 3 * K + k[1:, None], rows[:-1]] = 2 * a[:, 1:-1]
    out[:, rows, 4 * K + k[:, None]] = -grads
    out[:, 4 * K + k[:, None], rows] = np.where(active[..., None], grads, 0.0)
    out[:, 4 * K + k, 4 * K + k] = np.where(active, 0.0, 1.0)
    return r, out, u, ell


#: Half-bandwidth of the KKT matrix with the unknowns node by node (node k's position, mu_k, lambda_k):
#: a node's stationarity reaches the next node's mu (5 + 3 places on), its spacing the last node's position.
BANDWIDTH = 8


_GBSV = scipy.linalg.get_lapack_funcs("gbsv", dtype=np.float64)  # called directly: scipy's wrapper cost 9x the solve


@functools.cache
def _node_major(K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The permutation to node-by-node unknowns and the (row, column) pairs of its band."""
    order = np.array([[3 * k, 3 * k + 1, 3 * k + 2, 3 * K + k, 4 * K + k] for k in range(K)]).ravel()
    rows, cols = np.nonzero(np.abs(np.subtract.outer(np.arange(5 * K), np.arange(5 * K))) <= BANDWIDTH)
    return order, rows, cols


def _solve(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``M^-1 b`` for a batch of KKT systems (T x 5K x 5K, T x 5K x m): banded LU with partial
    pivoting (LAPACK gbsv; node by node the matrix is banded, :data:`BANDWIDTH`): as fast as a dense
    solve on one thread, and never spread over BLAS threads (a dense batch of 25 paths took 40-500 ms
    against 5 on two busy cores).  A singular system (a contact
    whose normal lies along its segments, a node with no distance gradient) gets its least-squares
    step, and a path that keeps needing it ends unconverged (its data NaN), not as an exception."""
    T, n = M.shape[0], M.shape[1]
    order, rows, cols = _node_major(n // 5)
    band = np.zeros((T, 3 * BANDWIDTH + 1, n))  # LAPACK's layout: BANDWIDTH rows for the factors' fill
    band[:, 2 * BANDWIDTH + rows - cols, cols] = M[:, order[rows], order[cols]]
    rhs = np.ascontiguousarray(b[:, order])
    out = np.empty_like(b)
    for t in range(T):
        _, _, x, info = _GBSV(BANDWIDTH, BANDWIDTH, band[t], rhs[t], overwrite_ab=True)
        if info == 0 and np.all(np.isfinite(x)):
            out[t, order] = x
        else:
            out[t] = np.linalg.lstsq(M[t], b[t], rcond=None)[0]
    return out


def _push_out(field, start, end, Y, clearance: float, steps: int = 40) -> np.ndarray:
    """The chord's nodes inside the body moved out to its surface in their planes: Newton steps on
    ``d`` along the distance's gradient in the plane, every node on the side the inside nodes leave
    by together (their in-plane gradients weighed by depth; so a chord near the body's middle does
    not split round both sides, and a node deeper than the field's clip follows the others)."""
    T, K, _ = Y.shape
    chord = end - start
    unit = chord / np.linalg.norm(chord, axis=1, keepdims=True)
    plane = np.eye(3) - unit[:, :, None] * unit[:, None, :]  # T x 3 x 3
    for _ in range(steps):
        d, grad = field.evaluate(Y.reshape(-1, 3), order=1)
        gap = d.reshape(T, K) - clearance
        inside = gap < -1e-9
        if not inside.any():
            break
        gp = np.einsum("tij,tkj->tki", plane, grad.reshape(T, K, 3))
        way = np.einsum("tk,tki->ti", np.where(inside, -gap, 0.0), gp)
        way = way / np.maximum(np.linalg.norm(way, axis=1, keepdims=True), 1e-300)
        against = np.einsum("tkj,tj->tk", gp, way) <= 0.2 * np.linalg.norm(gp, axis=2)
        gp = np.where(against[..., None], way[:, None] * np.maximum(np.linalg.norm(gp, axis=2), 0.5)[..., None], gp)
        step = -gap[..., None] * gp / np.maximum(np.sum(gp * gp, axis=2), 1e-12)[..., None]
        size = np.linalg.norm(step, axis=2, keepdims=True)
        step *= np.minimum(1.0, 2e-3 / np.maximum(size, 1e-300))  # at most 2 mm a step
        Y = Y + np.where(inside[..., None], step, 0.0)
    return Y


def _merit(field, start, end, Y, clearance: float, spacing: np.ndarray) -> np.ndarray:
    """The l1 merit of :func:`taut_path`'s line search: the polyline's length plus :data:`PENALTY`
    times the depth of every node inside the body and the segments' departure from equal
    lengths (``spacing``: the chord's share, m) (T)."""
    T, K, _ = Y.shape
    _, ell = _segments(start, end, Y)
    gap = field.evaluate(Y.reshape(-1, 3))[0].reshape(T, K) - clearance
    unequal = np.abs(np.diff(ell**2, axis=1)).sum(axis=1) / (2 * spacing)
    return ell.sum(axis=1) + PENALTY * (np.maximum(-gap, 0.0).sum(axis=1) + unequal)


def _blocking(gap, grads, dY, active, alpha):
    """The step lengths (T) cut to where the first node off the body meets it (its gap linearised
    along the step), and the nodes that meet it there (T x K): a primal active-set step, which adds
    a node the step would push in instead of shrinking the step to nothing before it."""
    rate = np.einsum("tki,tki->tk", grads, dY)  # d gap / d alpha
    reach = np.where(~active & (rate < 0), np.maximum(gap, 0.0) / np.maximum(-rate, 1e-300), np.inf)
    first = reach.min(axis=1)
    cut = first < alpha
    blocking = cut[:, None] & (reach <= first[:, None] * (1 + 1e-9))
    return np.where(cut, first, alpha), blocking


def _backtrack(field, start, end, Y, dY, alpha: np.ndarray, clearance: float, spacing: np.ndarray) -> np.ndarray:
    """Step lengths from ``alpha`` (T), halved until the step ``dY`` lowers :func:`_merit` (30 halvings at most)."""
    before = _merit(field, start, end, Y, clearance, spacing)
    for _ in range(30):
        worse = _merit(field, start, end, Y + alpha[:, None, None] * dY, clearance, spacing) > before + 1e-15
        if not worse.any():
            break
        alpha = np.where(worse, alpha / 2, alpha)
    return alpha


def taut_path(field, start: np.ndarray, end: np.ndarray, clearance: float = 0.0, nodes: int = NODES,
              max_iter: int = MAX_ITER) -> TautPath:
    """The shortest paths from each ``start`` to its ``end`` (T x 3, m, the field's frame) outside the
    body of ``field`` (``.evaluate(points, order)``: signed distance, gradient, Hessian) by at least
    ``clearance`` (m), and their first-order response (module docstring).

    The method: sequential quadratic steps on the nodes touching the body (the active set), from
    the chord's nodes pushed out to the surface.  Far from a solution a step models the length by
    its own Hessian only (convex: a descent direction of the l1 merit :func:`_merit`, which a
    backtracking line search decreases); a node the step would push in is added where it meets the
    body (the step is cut there: a primal active-set step), and a node pulling away
    (negative multiplier) is released, the most negative one at a time once the others are in
    balance; near the solution the Hessian of the Lagrangian makes the steps Newton's."""
    start = np.atleast_2d(np.asarray(start, float))
    end = np.atleast_2d(np.asarray(end, float))
    T, K = len(start), int(nodes)
    t = np.arange(1, K + 1) / (K + 1)
    c = end - start
    Y = start[:, None] + t[None, :, None] * c[:, None]
    Y = _push_out(field, start, end, Y, clearance)
    spacing = np.linalg.norm(c, axis=1) / (K + 1)
    mu, lam = np.zeros((T, K)), np.zeros((T, K))
    d = field.evaluate(Y.reshape(-1, 3))[0].reshape(T, K)
    active = d - clearance < 1e-9
    converged = np.zeros(T, bool)
    iterations = np.zeros(T, int)
    scale = np.linalg.norm(c, axis=1)
    previous = np.full(T, np.inf)
    for _ in range(max_iter):
        todo = np.flatnonzero(~converged)  # a converged path stays as it is: only the others are worked on
        if not len(todo):
            break
        s, e, y, m, la, act = start[todo], end[todo], Y[todo], mu[todo], lam[todo], active[todo]
        n = len(todo)
        vals, grads, hessians = field.evaluate(y.reshape(-1, 3), order=2)
        gap = vals.reshape(n, K) - clearance
        grads, hessians = grads.reshape(n, K, 3), hessians.reshape(n, K, 3, 3)
        r, _, _, _ = _kkt(s, e, y, m, la, act, gap, grads, hessians, curvature=True, jacobian=False)
        norm = np.maximum(np.abs(r[:, : 3 * K]).max(axis=1), np.abs(r[:, 3 * K: 4 * K]).max(axis=1) / scale[todo]**2)
        norm = np.maximum(norm, np.abs(np.where(act, gap, 0.0)).max(axis=1))
        violated = (gap < -1e-12) & ~act
        # in balance on the active set, or no longer getting there: release the node pulling away most
        balanced = (norm < NEAR) | (norm > STALL * previous[todo])
        previous[todo] = norm
        pulling = act & (la < 0) & balanced[:, None]
        release = np.zeros_like(act)
        worst = np.argmin(np.where(pulling, la, np.inf), axis=1)
        release[np.arange(n), worst] = pulling.any(axis=1)
        changed = violated.any(axis=1) | release.any(axis=1)
        done = (norm < TOLERANCE) & ~changed & ~pulling.any(axis=1)
        converged[todo] = done
        if done.all():
            break
        go = ~done
        iterations[todo[go]] += 1
        todo, s, e, y, m, la = todo[go], s[go], e[go], y[go], m[go], la[go]
        act, gap, grads, hessians = ((act | violated) & ~release)[go], gap[go], grads[go], hessians[go]
        newton = ((norm < NEAR) & ~changed)[go]  # near a solution on an unchanged active set: Newton's steps
        la = np.where(act, la, 0.0)
        r, M, _, _ = _kkt(s, e, y, m, la, act, gap, grads, hessians, curvature=newton)
        step = -_solve(M, r[..., None])[..., 0]
        dY = step[:, : 3 * K].reshape(-1, K, 3)
        size = np.linalg.norm(dY, axis=2).max(axis=1)
        alpha = np.minimum(1.0, STEP / np.maximum(size, 1e-300))  # at most STEP
        alpha, blocking = _blocking(gap, grads, dY, act, alpha)
        search = ~newton
        if search.any():
            alpha[search] = _backtrack(field, s[search], e[search], y[search], dY[search], alpha[search], clearance,
                                       spacing[todo][search])
        Y[todo] = y + alpha[:, None, None] * dY
        mu[todo] = m + alpha[:, None] * step[:, 3 * K: 4 * K]
        lam[todo] = np.where(act, la + alpha[:, None] * step[:, 4 * K:], 0.0)
        active[todo] = act | blocking
    vals, grads, hessians = field.evaluate(Y.reshape(-1, 3), order=2)
    gap = vals.reshape(T, K) - clearance
    grads, hessians = grads.reshape(T, K, 3), hessians.reshape(T, K, 3, 3)
    lam = np.where(active, lam, 0.0)
    _, M, u, ell = _kkt(start, end, Y, mu, lam, active, gap, grads, hessians, curvature=True)
    dnodes = _response(M, u, ell, start, end, Y, mu)
    return TautPath(start, end, Y, dnodes, mu, lam, gap, grads, hessians, ell.sum(axis=1), converged, iterations)


def _response(M, u, ell, start, end, Y, mu) -> np.ndarray:
    """dY/d(s, e) (T x K x 3 x 6) by the implicit function theorem on the KKT conditions."""
    T, K = mu.shape
    n = 5 * K
    dP = np.zeros((T, n, 6))
    B = (np.eye(3) - u[..., :, None] * u[..., None, :]) / np.maximum(ell, 1e-300)[..., None, None]
    eye = np.eye(3)
    dP[:, 0:3, 0:3] -= B[:, 0] + 2 * mu[:, 0, None, None] * eye  # u_0 and 2 mu_1 a_0, a_0 = y_1 - s
    dP[:, 3 * K - 3: 3 * K, 3:6] += -B[:, K] + 2 * mu[:, K - 1, None, None] * eye  # -u_K and 2 mu_K a_K, a_K = e - y_K
    dP[:, 3 * K, 0:3] = 2 * (Y[:, 0] - start)  # h_1 = |a_1|^2 - |a_0|^2
    dP[:, 4 * K - 1, 3:6] = 2 * (end - Y[:, -1])  # h_K = |a_K|^2 - |a_K-1|^2
    dz = -_solve(M, dP)
    return dz[:, : 3 * K].reshape(T, K, 3, 6)
