import casadi as ca
import numpy as np
import pytest
import trimesh

import kneenlp
from kneenlp.base.conventions import LOAD_SIZE
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.geometry import kernels
from kneenlp.model.contact import compartment_function, sphere_plane_force
from kneenlp.model.laws import CASADI, NUMPY, ElasticFoundation, PowerFoundation, gate

K = 10e9  # N/m^3


def plane_samples(half=0.012, spacing=0.0002):
    g = np.arange(-half, half + 1e-12, spacing)
    x, z = np.meshgrid(g, g, indexing="ij")
    verts = np.column_stack([x.ravel(), np.zeros(x.size), z.ravel()])
    n = len(g)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    mesh = trimesh.Trimesh(verts, np.vstack([np.column_stack([a, d, b]), np.column_stack([b, d, c])]))
    areas = np.zeros(len(verts))
    np.add.at(areas, mesh.faces.ravel(), np.repeat(mesh.area_faces / 3, 3))
    return verts, areas


@pytest.mark.parametrize("depth", [0.1e-3, 0.3e-3, 0.6e-3])
def test_sphere_pressed_into_plane_matches_closed_form(depth):
    radius = 0.022
    pts, areas = plane_samples()
    fn = compartment_function("test", pts, areas, delta=1e-7)
    centre = np.array([0.0, radius - depth, 0.0])  # sphere above the plane y = 0
    force, moment = (np.asarray(v).ravel() for v in fn(centre, K, radius))
    exact = sphere_plane_force(K, radius, depth)
    assert -force[1] == pytest.approx(exact, rel=5e-3)  # the plane is pushed down (-Y)
    assert abs(force[0]) < 1e-6 * exact and abs(force[2]) < 1e-6 * exact  # symmetric
    # moment about the origin of a force through (0, 0, 0) along -Y: zero
    assert np.allclose(moment, 0.0, atol=1e-6 * exact * radius)
    # the classic cap-volume law agrees to O(d/R)
    cap = np.pi * K * depth**2 * (radius - depth / 3)
    assert exact == pytest.approx(cap, rel=depth / radius)


def test_offset_contact_moment_is_r_cross_f():
    radius = 0.022
    pts, areas = plane_samples()
    fn = compartment_function("test", pts, areas, delta=1e-7)
    centre = np.array([0.004, radius - 0.3e-3, -0.003])
    force, moment = (np.asarray(v).ravel() for v in fn(centre, K, radius))
    contact_point = np.array([0.004, 0.0, -0.003])
    assert np.allclose(moment, np.cross(contact_point, force), rtol=1e-3, atol=1e-6)


def test_gate_is_exactly_zero_without_penetration_and_c2():
    d = ca.SX.sym("d")
    delta = 1e-5
    g = gate(d, delta)
    f = ca.Function("g", [d], [g, ca.jacobian(g, d), ca.hessian(g, d)[0]])
    assert float(f(-1e-3)[0]) == 0.0
    for depth in (delta, 2 * delta, 1e-4, 1e-3):  # the paper's linear law beyond the width, exactly
        assert float(f(depth)[0]) == pytest.approx(depth, rel=1e-12)
    for x in (0.0, delta):
        lo, hi = f(x - 1e-14), f(x + 1e-14)
        for a, b in zip(lo, hi, strict=True):
            assert float(a) == pytest.approx(float(b), abs=1e-6 / delta)  # curvature scale 1/delta


@pytest.mark.parametrize("law", [ElasticFoundation(), PowerFoundation()], ids=lambda law: law.name)
def test_every_form_of_a_pressure_law_is_the_same_function(law):
    """A pressure law's CasADi form, its NumPy form and the compiled kernel's value, slope and
    curvature agree (slope and curvature the CasADi derivatives), through and beyond the gate;
    the paper's law is exactly K d beyond the gate, the power law K d_r (d / d_r)^1.5."""
    from kneenlp.model.laws import REFERENCE_DEPTH

    d = ca.SX.sym("d")
    delta = 1e-5
    g = law.pressure(d, 1.0, delta, CASADI)
    f = ca.Function("g", [d], [g, ca.jacobian(g, d), ca.hessian(g, d)[0]])
    s = np.concatenate([np.linspace(-0.5 * delta, 3 * delta, 41), [1e-4, 5e-4, 2e-3]])
    ref = np.array([[float(v) for v in f(x)] for x in s])
    kernel = np.array([kernels.pressure_at(law.kernel, float(x), delta) for x in s])
    assert np.allclose(law.pressure(s, 1.0, delta, NUMPY), ref[:, 0], rtol=1e-12, atol=1e-20)
    assert np.allclose(kernel[:, 0], ref[:, 0], rtol=1e-12, atol=1e-20)
    assert np.allclose(kernel[:, 1], np.where(s > 0, ref[:, 1], 0.0), rtol=1e-9, atol=1e-12)
    assert np.allclose(kernel[:, 2], np.where(s > 0, ref[:, 2], 0.0), rtol=1e-9, atol=1e-6)
    assert np.all(np.diff(kernel[:41, 0]) >= 0)  # monotone
    beyond = s[-3:]
    expected = beyond if law.name == "elastic_foundation" else REFERENCE_DEPTH * (beyond / REFERENCE_DEPTH) ** 1.5
    assert np.allclose(kernel[-3:, 0], expected, rtol=1e-12)


def test_contact_is_differentiable(model):
    # jacobian of the contact-laden residual exists and is finite at a penetrated pose
    q = np.array([0.0, 0.0, 0.0, 0.0, 0.3e-3])
    ws = model.working_set(q, model.theta(), 0.0)[1]
    jac = np.asarray(model.jacobians(q, model.theta(), np.zeros(LOAD_SIZE), 0.0, ws)[0])
    assert np.all(np.isfinite(jac)) and np.linalg.matrix_rank(jac) == 5


def test_working_sets_reproduce_the_full_contact():
    """With 300 of ~1000 points per compartment in each trial's working set, Set 3 solves to the
    poses of the full contact; too small a working set is reported, never silently kept."""
    import dataclasses

    import kneenlp

    knee = kneenlp.Knee.named("synthetic")
    full = kneenlp.simulate(knee, "set3")
    ws = kneenlp.simulate(dataclasses.replace(knee, working_set=300), "set3")
    assert ws.converged == len(full.solutions)
    assert np.abs(ws.q - full.q).max() < 1e-9
    tiny = kneenlp.simulate(dataclasses.replace(knee, working_set=5), "set3")
    assert tiny.failed and all(not np.isfinite(s.max_residual) or s.max_residual > 1e-6 for s in tiny.failed)


def test_left_out_batch_agrees_with_the_per_pose_check():
    """The compiled check of what the contact pass leaves out (points deeper than the field's depth,
    points outside its grid) says what the per-pose check says, pose by pose: at equilibrium poses
    nothing penetrates unrepresented; pushed 3.5 mm into the femur, points beyond the field's depth do."""
    knee = kneenlp.Knee.named("default")
    model = KneeModel.of(knee)
    res = kneenlp.simulate(knee, "set1")
    q, theta = np.asarray(res.q), model.theta()
    flex = np.array([t.flexion for t in res.protocol.trials])
    for shift in (0.0, 3.5e-3):
        qs = q + np.array([0, 0, 0, 0, shift])
        batch = model.left_out_batch(qs, theta, flex, threads=2)
        single = np.array([model.left_out_penetration(qi, theta, f) for qi, f in zip(qs, flex, strict=True)])
        assert np.array_equal(batch > 0, single > 0)
        assert np.allclose(batch[single > 0], single[single > 0])
        assert np.all(batch > 0) if shift else np.all(batch <= 0)


@pytest.mark.parametrize("where, field", [("[contact]\n", "contact.law"),
                                          ("[contact.lateral]\n", "contact.lateral.law")])
def test_unknown_pressure_law_is_named(tmp_path, where, field):
    import shutil

    from kneenlp.base.errors import InputError
    from kneenlp.base.resources import resource
    from kneenlp.model.knee import Knee
    from kneenlp.model.knee_file import knee_file

    shutil.copytree(knee_file("synthetic").parent, tmp_path / "k")
    toml = tmp_path / "k" / "knee.toml"
    toml.write_text(toml.read_text().replace("../../parameters/table1.toml", str(resource("parameters", "table1.toml")))
                    .replace(where, f'{where}law = "hertz"\n', 1))
    with pytest.raises(InputError, match=r"unknown law 'hertz'; built in: elastic_foundation, power_1\.5") as err:
        Knee.load(toml)
    assert err.value.field == field
