"""The taut string over a body's signed distance (kneenlp.geometry.taut_path) against independent
oracles: the closed-form geodesic about a cylinder (kneenlp.model.paths.CylinderWrap, Garner & Pandy),
finite differences of the solved lengths for the Lagrangian's gradient and Hessian, and (slow) a
brute-force shortest path over the S192803 tibia's mesh (kneenlp.testing.shortest_path)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from kneenlp.geometry.taut_path import data_size, lagrangian, taut_path
from kneenlp.model.paths import CylinderWrap

RADIUS = 0.01


class Cylinder:
    """The exact signed distance to the cylinder of :data:`RADIUS` about the z axis (m), with its
    gradient and Hessian: a field with the interface of :class:`~kneenlp.geometry.sdf.DistanceField`."""

    def evaluate(self, points, order=0):
        x = np.asarray(points, float).reshape(-1, 3)
        rho = np.linalg.norm(x[:, :2], axis=1)
        n = np.zeros_like(x)
        n[:, :2] = x[:, :2] / rho[:, None]
        out = [rho - RADIUS, n]
        across = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
        across[:, 2, :] = across[:, :, 2] = 0
        out.append(across / rho[:, None, None])
        return tuple(out[: order + 1])


ENDS = np.array([[[-0.03, 0.004, 0.0], [0.025, 0.002, 0.01]],     # wraps
                 [[-0.03, 0.012, -0.01], [0.03, 0.011, 0.02]],    # misses the cylinder
                 [[-0.02, -0.006, 0.01], [0.03, -0.003, -0.015]]])  # wraps the other side


def closed_form(s, e) -> float:
    """The shortest path about the cylinder, on whichever side is shorter (CylinderWrap, m)."""
    return min(CylinderWrap(np.zeros(3), np.array([0.0, 0.0, 1.0]), RADIUS, "femur", side).length(
        e, s, np.eye(3), np.zeros(3)) for side in (1, -1))


def test_the_taut_path_about_a_cylinder_is_the_closed_form_geodesic():
    """To 3e-4 of the length where it wraps (the chords of 24 nodes: module docstring), exactly the
    chord where it misses; the multipliers say which."""
    sol = taut_path(Cylinder(), ENDS[:, 0], ENDS[:, 1])
    assert sol.converged.all()
    assert list(sol.wrapped) == [True, False, True]
    for (s, e), length in zip(ENDS, sol.length, strict=True):
        exact = closed_form(s, e)
        assert length == pytest.approx(exact, rel=3e-4) and length <= exact + 1e-12


def test_the_lagrangian_has_the_shortest_lengths_gradient_and_hessian():
    """Where its data were taken, :func:`lagrangian` is the solved length, and its gradient and
    Hessian in (s, e) are those of the solved length (central differences of solves)."""
    s0, e0 = ENDS[0]
    x0 = np.r_[s0, e0]
    S, E, D = ca.SX.sym("s", 3), ca.SX.sym("e", 3), ca.SX.sym("d", data_size())
    L = lagrangian(S, E, D)
    x = ca.vertcat(S, E)
    f = ca.Function("f", [x, D], [L, ca.gradient(L, x), ca.hessian(L, x)[0]])

    def length(v):
        return taut_path(Cylinder(), v[None, :3], v[None, 3:]).length[0]

    value, grad, hess = (np.asarray(v) for v in f(x0, taut_path(Cylinder(), s0[None], e0[None]).data()[0]))
    assert value.item() == pytest.approx(length(x0), rel=1e-14)
    h, I6 = 1e-6, np.eye(6)
    fd = np.array([(length(x0 + h * I6[i]) - length(x0 - h * I6[i])) / (2 * h) for i in range(6)])
    assert np.abs(grad.ravel() - fd).max() < 1e-8
    h = 1e-5
    fd2 = np.array([[(length(x0 + h * (I6[i] + I6[j])) - length(x0 + h * (I6[i] - I6[j]))
                      - length(x0 - h * (I6[i] - I6[j])) + length(x0 - h * (I6[i] + I6[j]))) / (4 * h * h)
                     for j in range(6)] for i in range(6)])
    assert np.abs(hess - fd2).max() < 1e-3 * np.abs(fd2).max()


def test_a_path_that_misses_is_the_chord_and_moves_with_its_ends():
    s, e = ENDS[1]
    sol = taut_path(Cylinder(), s[None], e[None])
    t = np.arange(1, 25) / 25
    assert np.allclose(sol.nodes[0], s + t[:, None] * (e - s), atol=1e-14)
    J = sol.dnodes[0]
    assert np.allclose(J[:, :, :3], (1 - t)[:, None, None] * np.eye(3), atol=1e-10)
    assert np.allclose(J[:, :, 3:], t[:, None, None] * np.eye(3), atol=1e-10)


@pytest.mark.slow
def test_a_path_over_a_real_bone_is_the_brute_force_shortest_path(tmp_path):
    """S192803's superficial MCL over its tibia (the straight line cuts the bone 2-6 mm in every pose):
    the taut path over the bone's distance field is, at poses of three flexions, the shortest path
    over the bone's mesh found by brute force (kneenlp.testing.shortest_path) to 0.1 % of its length
    (measured: 0.8-1.6e-4), and longer than the straight line by more than that."""
    import shutil

    import kneenlp
    from kneenlp.base.resources import resource
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.model.knee_file import KneeFile
    from kneenlp.testing.shortest_path import shortest_over_mesh

    folder = tmp_path / "knee"
    shutil.copytree(resource("knees", "s192803"), folder)
    with open(folder / "knee.toml", "a") as f:
        f.write("".join(f'\n[ligaments.{g}.wrap]\nshape = "bone"\nbody = "tibia"\n' for g in ("MCLa", "MCLm", "MCLp")))
    knee = kneenlp.Knee.load(folder / "knee.toml")
    reader = KneeFile(folder / "knee.toml")
    mesh = reader.frame.mesh(reader.mesh(reader.spec.bones.tibia, "bones.tibia"))
    model = KneeModel.of(knee)
    theta = model.theta()
    values = dict(zip(model.parameter_names, theta, strict=True))
    for name, flexion, q in [("MCLa", 30, [-2, 0.3, -0.7, 0.2, -21.7]), ("MCLm", 60, [-4, 8, -2, 4, -20]),
                             ("MCLp", 0, [-1, -12, 1, 5, -20])]:
        q = np.r_[np.radians(q[:2]), np.array(q[2:]) * 1e-3]
        R, p = (np.asarray(v) for v in model.pose(q, np.radians(flexion), theta))
        ligament = knee.ligaments[name]
        bundle = ligament.bundles[0]
        s, e = bundle.path.ends(*ligament.attachments(bundle, values), R[None], p[None])
        sol = taut_path(bundle.path.field, s, e)
        touching = np.flatnonzero(sol.lam[0] > 0)
        oracle = shortest_over_mesh(mesh, s[0], e[0], sol.nodes[0, touching[0]], sol.nodes[0, touching[-1]],
                                    reach=4e-3, edge=0.5e-3, crop=15e-3)
        assert sol.converged[0] and sol.length[0] == pytest.approx(oracle, rel=1e-3), name
        assert oracle > np.linalg.norm(e - s) * (1 + 1.5e-3), name


def test_a_step_that_would_push_a_free_node_in_is_cut_where_it_meets_the_body():
    """The primal active-set cut (``_blocking``): along a step the gap of a free node falls linearly
    (its gradient along the step); the step is cut where the first one reaches zero and that node
    joins the active set; active nodes and nodes moving away never cut it."""
    from kneenlp.geometry.taut_path import _blocking

    gap = np.array([[2e-3, 1e-3, 0.0, 5e-4]])
    grads = np.tile([0.0, 0.0, 1.0], (1, 4, 1))
    dY = np.array([[[0, 0, -4e-3], [0, 0, -4e-3], [0, 0, -1e-3], [0, 0, 1e-3]]], float)
    active = np.array([[False, False, True, False]])  # the third is on the body already; the fourth moves away
    alpha, blocking = _blocking(gap, grads, dY, active, np.array([1.0]))
    assert alpha[0] == pytest.approx(0.25) and blocking.tolist() == [[False, True, False, False]]
    alpha, blocking = _blocking(gap, grads, dY, active, np.array([0.1]))  # a shorter step meets nothing
    assert alpha[0] == 0.1 and not blocking.any()
