import casadi as ca
import numpy as np
import pytest

from kneenlp.base.conventions import LOAD_SIZE, load_vector
from kneenlp.model.kinematics import tibial_pose


def pose(flexion_deg, q):
    qs = ca.SX.sym("q", 5)
    R, p, axes = tibial_pose(np.deg2rad(flexion_deg), qs)
    f = ca.Function("f", [qs], [R, p, *axes])
    return [np.asarray(v) for v in f(q)]


def test_reference_pose_is_identity():
    R, p, *_ = pose(0.0, np.zeros(5))
    assert np.allclose(R, np.eye(3)) and np.allclose(p, 0)


@pytest.mark.parametrize("flex", [0.0, 30.0, 60.0])
def test_rotation_is_proper_and_axes_are_grood_suntay(flex):
    q = np.array([0.1, -0.2, 0.001, 0.002, -0.003])
    R, p, e1, e2, e3 = pose(flex, q)
    assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(e3.ravel(), R[:, 1])  # tibial long axis
    assert abs(float(e2.ravel() @ e1.ravel())) < 1e-12 and abs(float(e2.ravel() @ e3.ravel())) < 1e-12
    assert np.allclose(p.ravel(), q[2] * e1.ravel() + q[3] * e2.ravel() + q[4] * e3.ravel())


def test_sign_conventions_right_knee():
    ankle = np.array([0.0, -0.4, 0.0])
    tuberosity = np.array([0.03, -0.04, 0.0])
    # flexion: the ankle moves posteriorly (-X)
    R, *_ = pose(30.0, np.zeros(5))
    assert (R @ ankle)[0] < 0
    # varus: the ankle moves medially (-Z for a right knee)
    R, *_ = pose(0.0, np.array([np.deg2rad(5), 0, 0, 0, 0]))
    assert (R @ ankle)[2] < 0
    # internal rotation: the tuberosity moves medially (-Z)
    R, *_ = pose(0.0, np.array([0, np.deg2rad(5), 0, 0, 0]))
    assert (R @ tuberosity)[2] < 0
    # translations move the tibial origin along +Z, +X, +Y at zero flexion
    for j, axis in ((2, 2), (3, 0), (4, 1)):
        q = np.zeros(5)
        q[j] = 1e-3
        _, p, *_ = pose(0.0, q)
        assert p.ravel()[axis] == pytest.approx(1e-3)


def test_residual_jacobian_matches_finite_differences(model):
    theta = model.theta()
    load = load_vector({"anterior_force": 50.0, "varus_moment": 2.0, "internal_moment": 0.5})
    q0 = np.array([0.01, 0.05, 0.0005, -0.001, 0.0003])
    flex = np.deg2rad(30)
    jac = np.asarray(model.jacobians(q0, theta, load, flex, model.working_set(q0, theta, flex)[1])[0])
    fd = np.zeros((5, 5))
    steps = np.array([1e-7, 1e-7, 1e-9, 1e-9, 1e-9])
    for j in range(5):
        dq = np.zeros(5)
        dq[j] = steps[j]
        rp = np.asarray(model.evaluate(q0 + dq, theta, load, flex)).ravel()
        rm = np.asarray(model.evaluate(q0 - dq, theta, load, flex)).ravel()
        fd[:, j] = (rp - rm) / (2 * steps[j])
    assert np.allclose(jac, fd, rtol=1e-4, atol=1e-4 * np.abs(jac).max())


def test_residual_is_virtual_work_of_a_pure_moment(model):
    # with no ligaments' or contact's change, a pure internal moment about femoral Y at 0 deg
    # flexion shows up 1:1 in the internal-rotation generalised force
    theta = model.theta()
    q = np.array([0.0, 0.0, 0.0, 0.0, -5e-3])  # far from contact
    r0 = np.asarray(model.evaluate(q, theta, np.zeros(LOAD_SIZE), 0.0)).ravel()
    r1 = np.asarray(model.evaluate(q, theta, load_vector({"internal_moment": 3.0}), 0.0)).ravel()
    assert np.allclose(r1 - r0, [0, 3.0, 0, 0, 0], atol=1e-9)


def test_jcs_loads_are_the_generalised_forces_and_femoral_ones_their_virtual_work(model):
    # a robot's joint loads ("jcs") enter the residual as they are, at any pose; the same loads
    # along the femoral axes at 0 deg flexion and zero varus/rotation give the same generalised
    # forces for the moments (the force acts at the tuberosity, so only its own component agrees)
    theta = model.theta()
    q = np.array([0.05, -0.1, 1e-3, 2e-3, -5e-3])
    loads = {"varus_moment": 2.0, "internal_moment": -1.5, "lateral_force": 10.0, "anterior_force": 50.0,
             "proximal_force": 40.0, "flexion_moment": 3.0}
    r0 = np.asarray(model.evaluate(q, theta, np.zeros(LOAD_SIZE), 0.4)).ravel()
    r1 = np.asarray(model.evaluate(q, theta, load_vector(loads, flexion=0.4, axes="jcs"), 0.4)).ravel()
    assert np.allclose(r1 - r0, [2.0, -1.5, 10.0, 50.0, 40.0], atol=1e-12)
    q0 = np.array([0.0, 0.0, 0.0, 0.0, -5e-3])
    moments = {"varus_moment": 2.0, "internal_moment": -1.5}
    r0 = np.asarray(model.evaluate(q0, theta, np.zeros(LOAD_SIZE), 0.0)).ravel()
    r1 = np.asarray(model.evaluate(q0, theta, load_vector(moments, axes="femoral"), 0.0)).ravel()
    assert np.allclose(r1 - r0, [2.0, -1.5, 0, 0, 0], atol=1e-12)


@pytest.mark.parametrize("element", ["tibial_origin", "femoral_origin"])
def test_a_moved_origin_reads_the_translations_of_the_moved_point(element):
    """``TibialOrigin``: the observed translations are the Grood-Suntay translations of the tibial
    point ``s`` (tibial frame), whatever the flexion: oracle ``joint_coordinates`` of ``p + R s``.
    ``FemoralOrigin``: those of the tibial origin from the femoral point ``s`` (femoral frame):
    oracle ``joint_coordinates`` of ``p - s``; they depend on the flexion (unlike a constant
    registration)."""
    import kneenlp
    from kneenlp.base.conventions import coords_to_user
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.model.kinematics import joint_coordinates, reference_transform

    model = KneeModel.of(kneenlp.Knee.named("synthetic"))
    rng = np.random.default_rng(7)
    for _ in range(5):
        shift = rng.uniform(-0.01, 0.01, 3)
        theta = model.theta({f"{element}.{a}": v for a, v in zip(("anterior", "proximal", "lateral"), shift,
                                                                  strict=True)})
        q = np.r_[rng.uniform(-0.4, 0.4, 2), rng.uniform(-0.01, 0.01, 2), rng.uniform(-0.03, -0.01)]
        flexions = rng.uniform(-0.1, 1.7, 3)
        seen = model.observe(np.tile(q, (3, 1)), theta, np.zeros(LOAD_SIZE), flexions)
        for flexion, y in zip(flexions, seen, strict=True):
            R, p = reference_transform(flexion, q)
            f_back, q_moved = joint_coordinates(R, p + R @ shift if element == "tibial_origin" else p - shift)
            assert f_back == pytest.approx(flexion, abs=1e-12)
            assert np.allclose(y, coords_to_user(q_moved), atol=1e-9)
        assert not np.allclose(seen, coords_to_user(q))  # the shift is seen
        turns = np.ptp(seen[:, 2:], axis=0).max()  # mm: how much the bias changes with the flexion
        assert turns > 0.1 if element == "femoral_origin" else turns < 1e-9


def test_turned_tibial_axes_make_the_coordinates_the_experiments():
    """``TibialAxes``: the model's coordinates are those of the experiment's tibial axes, turned by
    ``C = Rz(-flexion) Rx(varus)`` from the model's (oracle: scipy's rotations).  The tibia's own
    frame is ``R(q) C^T``: reading it in the experiment's axes gives back the prescribed flexion
    and ``q``; the observation is ``q`` itself; a force at the tuberosity does the virtual work of
    the turned tibia's point (oracle: central differences); the imaged pose is read the same way."""
    from scipy.spatial.transform import Rotation

    import kneenlp
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.model.kinematics import joint_coordinates, reference_transform

    model = KneeModel.of(kneenlp.Knee.named("synthetic"))
    varus, flex_turn = np.radians(4.0), np.radians(-3.0)
    theta = model.theta({"tibial_axes.varus": varus, "tibial_axes.flexion": flex_turn})
    C = (Rotation.from_rotvec([0.0, 0.0, -flex_turn]) * Rotation.from_rotvec([varus, 0.0, 0.0])).as_matrix()
    q, flexion = np.array([0.02, -0.3, 0.001, 0.002, -0.004]), 0.7
    R, p = (np.asarray(v, float) for v in model.pose(q, flexion, theta))
    f_back, q_back = joint_coordinates(R @ C, p)
    assert f_back == pytest.approx(flexion, abs=1e-12) and np.allclose(q_back, q, atol=1e-12)
    f_model, q_model = joint_coordinates(R, p)  # the model's own axes read another pose
    assert abs(f_model - flexion) > np.radians(1.0) and abs(q_model[0] - q[0]) > np.radians(2.0)
    unloaded = np.zeros(LOAD_SIZE)
    assert np.allclose(model.observe(q[None], theta, unloaded, flexion),
                       model.observe(q[None], model.theta(), unloaded, flexion))

    tub = np.asarray(model.knee.tuberosity, float)

    def point(qq):
        Rq, pq = reference_transform(flexion, qq)
        return Rq @ C.T @ tub + pq

    load = load_vector({"anterior_force": 120.0, "lateral_force": -30.0, "proximal_force": 50.0}, axes="femoral")
    ws = model.working_data(q, theta, flexion)
    extra = (np.asarray(model.residual(q, theta, load, flexion, ws)).ravel()
             - np.asarray(model.residual(q, theta, np.zeros(LOAD_SIZE), flexion, ws)).ravel())
    h = 1e-7
    oracle = np.array([load[0:3] @ (point(q + h * np.eye(5)[i]) - point(q - h * np.eye(5)[i])) / (2 * h)
                       for i in range(5)])
    assert np.allclose(extra, oracle, atol=1e-6 * np.abs(oracle).max())

    f_ref, q_ref = model.reference_coordinates(theta)
    R_ref, p_ref = model.knee.reference_transform
    R, p = (np.asarray(v, float) for v in model.pose(q_ref, f_ref, theta))
    assert np.allclose(R, R_ref, atol=1e-12) and np.allclose(p, p_ref, atol=1e-12)
    assert model.reference_coordinates(model.theta())[0] == model.knee.reference_pose[0]
