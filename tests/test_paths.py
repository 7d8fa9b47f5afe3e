"""Ligament paths (kneenlp.model.paths): the wrapped length against an independent shortest-path
search, the force on the tibia against the length's own derivative (virtual work), continuity at
the switch from straight to wrapped, and a knee file's wrapping ligament."""

from __future__ import annotations

import itertools
import shutil
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import minimize, minimize_scalar
from scipy.spatial.transform import Rotation

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.model.elements import Pose
from kneenlp.model.paths import CylinderWrap, EllipsoidWrap, StraightPath, ViaPoints


def shortest_about(S: np.ndarray, E: np.ndarray, w: CylinderWrap) -> float:
    """The shortest path S -> T1 -> helix -> T2 -> E found by search over the tangent points'
    (angle, axial) coordinates, its straight parts kept out of the cylinder and the whole going
    round it on ``w.side`` (the turn about the axis equal to the gap on that side): no tangency or
    unrolling assumed."""
    c, a, r, side = w.centre, w.axis, w.radius, w.side
    e1, e2 = w.basis

    def across(X):  # the point across the axis, in the plane turned so that the side is counterclockwise
        v = X - c
        return np.array([v @ e1, side * (v @ e2)])

    def point(th, z):
        return c + r * np.cos(th) * e1 + side * r * np.sin(th) * e2 + z * a

    def clearance(P, Q):  # how far a straight part stays from the axis (exact, in the plane across it)
        p, q = across(P), across(Q)
        t = np.clip(-(p @ (q - p)) / max((q - p) @ (q - p), 1e-30), 0, 1)
        return np.linalg.norm(p + t * (q - p))

    def turn(P, Q):  # the angle a straight part sweeps about the axis (it never crosses the axis)
        p, q = across(P), across(Q)
        return np.arctan2(p[0] * q[1] - p[1] * q[0], p @ q)

    s, e = across(S), across(E)
    gap = (np.arctan2(e[1], e[0]) - np.arctan2(s[1], s[0])) % (2 * np.pi)

    def length(x):
        th1, z1, dth, z2 = x
        T1, T2 = point(th1, z1), point(th1 + abs(dth), z2)
        inside = max(r * (1 - 1e-12) - clearance(S, T1), 0) + max(r * (1 - 1e-12) - clearance(T2, E), 0)
        wrong_way = abs(turn(S, T1) + abs(dth) + turn(T2, E) - gap) > 1e-9
        return (np.linalg.norm(T1 - S) + np.hypot(r * dth, z2 - z1) + np.linalg.norm(E - T2)
                + 1e3 * inside + float(wrong_way))

    best = min((minimize(length, [th0, 0.0, dth0, 0.0], method="Nelder-Mead",
                         options={"xatol": 1e-12, "fatol": 1e-15, "maxiter": 20000, "maxfev": 40000})
                for th0 in np.linspace(-np.pi, np.pi, 6, endpoint=False) for dth0 in (0.3, 1.5)),
               key=lambda res: res.fun)
    return float(best.fun)


def identity() -> tuple[np.ndarray, np.ndarray]:
    return np.eye(3), np.zeros(3)


@pytest.mark.parametrize("case", range(3))
def test_the_wrapped_length_is_the_shortest_path_about_the_cylinder(case):
    """Random cylinders cut by the straight line, both sides: the closed form equals the searched
    shortest path to 1e-6 (0.1 % asked), and is longer than the straight line."""
    rng = np.random.default_rng(case)
    c = 0.002 * rng.normal(size=3)
    a = np.array([0.0, 0.0, 1.0]) + 0.2 * rng.normal(size=3)
    S = np.array([0.03, 0.002, -0.02]) + 0.005 * rng.normal(size=3)
    E = np.array([-0.03, -0.003, 0.03]) + 0.005 * rng.normal(size=3)
    for side in (1, -1):
        w = CylinderWrap(c, a, 0.01, "femur", side)
        length = w.length(E, S, *identity())
        assert length > np.linalg.norm(E - S) + 1e-4
        assert length == pytest.approx(shortest_about(S, E, w), rel=1e-6)


def planar_about(S: np.ndarray, E: np.ndarray, w: EllipsoidWrap, n: int = 200_000) -> float:
    """The shortest path from S to E over the ellipsoid among those in one plane through S and E,
    by brute force: each plane (turned about the line SE by a searched angle) cuts the ellipsoid in
    a section sampled at ``n`` points; the path runs S -> the section's extreme point seen from S
    -> along the sampled section -> the extreme point seen from E -> E, on the side away from the
    centre (no tangent formula, affine map or quadrature assumed)."""
    s, e = w.axes.T @ (S - w.centre), w.axes.T @ (E - w.centre)
    D = np.diag(1 / w.radii**2)
    u = (e - s) / np.linalg.norm(e - s)
    away = s - (s @ u) * u  # from the centre to its foot on the line: outwards
    away /= np.linalg.norm(away)
    span = np.linalg.norm(e - s)

    def length(psi: float, m: int) -> float:
        v = np.cos(psi) * away + np.sin(psi) * np.cross(u, away)
        Q = np.array([[u @ D @ u, u @ D @ v], [u @ D @ v, v @ D @ v]])
        b, k = np.array([s @ D @ u, s @ D @ v]), s @ D @ s - 1
        c = -np.linalg.solve(Q, b)
        size = c @ Q @ c - k
        if size <= 0:
            return span
        val, vec = np.linalg.eigh(Q)
        th = np.linspace(0, 2 * np.pi, m, endpoint=False)
        pts = (c[:, None] + vec @ (np.sqrt(size / val)[:, None] * np.array([np.cos(th), np.sin(th)]))).T
        pts = np.roll(pts, -int(np.argmin(pts[:, 1])), axis=0)  # in order round the section from its lowest point
        pts = pts[pts[:, 1] > 0]  # the side away from the centre: the path's
        seen_s = np.arctan2(pts[:, 1], pts[:, 0])
        seen_e = np.arctan2(pts[:, 1], span - pts[:, 0])
        i, j = int(np.argmax(seen_s)), int(np.argmax(seen_e))
        if seen_s[i] <= 0:
            return span
        lo, hi = sorted((i, j))
        arc = np.linalg.norm(np.diff(pts[lo:hi + 1], axis=0), axis=1).sum()
        return np.linalg.norm(pts[i]) + arc + np.linalg.norm(pts[j] - [span, 0])

    best = minimize_scalar(lambda psi: length(psi, 20_000), bounds=(-1.2, 1.2), method="bounded",
                           options={"xatol": 1e-7})
    return length(best.x, n)


ELLIPSOIDS = [EllipsoidWrap(np.array([0.001, -0.006, 0.002]), Rotation.from_rotvec(rv).as_matrix(), radii, "femur")
              for rv, radii in (((0.1, -0.3, 0.2), np.array([0.03, 0.018, 0.012])),
                                ((0.5, 0.2, -0.4), np.array([0.012, 0.016, 0.01])),
                                ((0.0, 0.0, 0.0), np.array([0.014, 0.014, 0.014])))]


@pytest.mark.parametrize("case", range(3))
def test_the_ellipsoid_path_is_the_shortest_planar_path_and_on_a_sphere_the_great_circle(case):
    """Three ellipsoids, the last a sphere: the closed form (affine tangents, quadrature, Newton on
    the plane) equals a brute-force search over planes and sampled sections to 1e-6; on the sphere
    it is the great circle's closed form to 1e-12."""
    w = ELLIPSOIDS[case]
    S, E = np.array([0.03, 0.002, -0.02]), np.array([-0.03, -0.003, 0.03])
    length = w.length(E, S, *identity())
    assert w.wraps(E, S, *identity()) and length > np.linalg.norm(E - S) + 1e-4
    assert length == pytest.approx(planar_about(S, E, w), rel=1e-6)
    if case == 2:  # a sphere: tangent lengths and the great circle's arc between the tangent points
        r, a, b = w.radii[0], S - w.centre, E - w.centre
        da, db = np.linalg.norm(a), np.linalg.norm(b)
        arc = np.arccos(a @ b / (da * db)) - np.arccos(r / da) - np.arccos(r / db)
        assert length == pytest.approx(np.sqrt(da**2 - r**2) + r * arc + np.sqrt(db**2 - r**2), rel=1e-12)


def test_via_points_sum_their_segments():
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    p, tibia, femur = np.array([0.001, -0.002, 0.0]), np.array([0.01, -0.03, 0.0]), np.array([0.0, 0.01, 0.02])
    path = ViaPoints(tibia=((0.01, -0.02, 0.005),), femur=((0.004, -0.004, 0.01),))
    chain = [p + R @ tibia, p + R @ np.array([0.01, -0.02, 0.005]), np.array([0.004, -0.004, 0.01]), femur]
    expected = sum(np.linalg.norm(b - a) for a, b in itertools.pairwise(chain))
    assert path.length(femur, tibia, R, p) == pytest.approx(expected, rel=1e-14)
    assert ViaPoints().length(femur, tibia, R, p) == pytest.approx(StraightPath().length(femur, tibia, R, p), rel=1e-15)


def test_a_path_clear_of_the_cylinder_is_the_straight_line():
    w = CylinderWrap(np.zeros(3), [0, 0, 1], 0.01, "femur", 1)
    S, E = np.array([0.03, 0.02, -0.02]), np.array([-0.03, 0.025, 0.03])
    assert w.length(E, S, *identity()) == pytest.approx(np.linalg.norm(E - S), rel=1e-15)


#: The tibia's rotation in the virtual-work test (0.3 rad about the femoral z axis).
ROTATED = Rotation.from_rotvec([0.0, 0.0, 0.3]).as_matrix()


def _symbolic(path, femur, tibia):
    """Length and force line of ``path`` as functions of the tibia's translation ``p`` and a small
    rotation ``w`` (R = exp([w]x) R0)."""
    p, w = ca.SX.sym("p", 3), ca.SX.sym("w", 3)
    W = ca.skew(w)
    R = (ca.DM.eye(3) + W + W @ W / 2) @ ca.DM(ROTATED)  # exp to second order: exact derivatives at w = 0
    route = path.route(ca.DM(femur), ca.DM(tibia), Pose(R, p, ca.SX.zeros(5), ca.SX(0)))
    force, moment = route.wrench(ca.DM(1))
    return ca.Function("f", [p, w], [route.length, ca.jacobian(route.length, p), ca.jacobian(route.length, w),
                                     force, moment])


PATHS = {"cylinder on the femur": CylinderWrap(np.array([0.001, 0.0, 0.002]), [0.1, 0.2, 1.0], 0.01, "femur", 1),
         "cylinder on the tibia": CylinderWrap(np.array([0.001, 0.0, 0.002]), [0.1, 0.2, 1.0], 0.01, "tibia", 1),
         "ellipsoid on the femur": ELLIPSOIDS[0],
         "ellipsoid on the tibia": EllipsoidWrap(ROTATED.T @ ELLIPSOIDS[1].centre, ROTATED.T @ ELLIPSOIDS[1].axes,
                                                 ELLIPSOIDS[1].radii, "tibia"),  # placed as on the femur at R0
         "via points": ViaPoints(tibia=((0.02, -0.01, -0.01),), femur=((0.0, 0.015, 0.0), (-0.02, 0.01, 0.02)))}


@pytest.mark.parametrize("name", PATHS)
def test_the_force_on_the_tibia_is_the_length_derivative(name):
    """Virtual work: a tension T pulls the tibia with the force -T dL/dp and the moment -T dL/dw,
    whichever bone carries the cylinder (the tibia's own cylinder moves with it) or the via points."""
    femur, tibia = np.array([-0.03, -0.003, 0.03]), np.array([0.03, 0.002, -0.02])
    path = PATHS[name]
    f = _symbolic(path, femur, tibia)
    for p in (np.zeros(3), np.array([0.002, -0.001, 0.001])):
        length, dl_dp, dl_dw, direction, moment = (np.asarray(v).ravel() for v in f(p, np.zeros(3)))
        assert length > np.linalg.norm(femur - (p + ROTATED @ tibia)) + 1e-4  # longer than the straight line
        # a planar path over an ellipsoid is not a geodesic: its tension along the free segments
        # (OpenSim's force) is its length's gradient to ~1e-3 of the tension; the others' exactly
        tol = 1e-3 if isinstance(path, EllipsoidWrap) else 1e-12
        np.testing.assert_allclose(direction, -dl_dp, atol=tol)
        np.testing.assert_allclose(moment, -dl_dw, atol=tol * 0.05)


def test_length_and_its_gradient_are_continuous_where_the_wrap_begins():
    """Moving the tibial attachment across the line where the straight path grazes the cylinder:
    the length and its gradient agree on both sides of the switch (C1)."""
    femur = np.array([-0.03, 0.0, 0.03])
    path = CylinderWrap(np.zeros(3), [0, 0, 1], 0.01, "femur", 1)
    t = ca.SX.sym("t")
    tibia_world = ca.vertcat(0.03, t, -0.02)
    route = path.route(ca.DM(femur), tibia_world, Pose(ca.DM.eye(3), ca.DM.zeros(3), ca.SX.zeros(5), ca.SX(0)))
    g = ca.Function("g", [t], [route.length, ca.jacobian(route.length, t)])
    ts = np.linspace(-0.02, 0.02, 4001)
    values = np.array([[float(v) for v in g(x)] for x in ts])
    jumps = np.abs(np.diff(values, axis=0))
    assert jumps[:, 0].max() < 2e-5 * 2 and jumps[:, 1].max() < 0.05  # no step in either
    assert values[0, 0] > np.linalg.norm(femur - np.array([0.03, -0.02, -0.02])) + 1e-4  # wrapped at one end


def _knee_with_wrap(tmp_path, wrap: str):
    """A copy of the synthetic knee (its folder, the parameter file it names) with ``wrap`` added to its MCL."""
    src = Path(kneenlp.Knee.named("synthetic").source)
    folder = tmp_path / "knee"
    shutil.copytree(src.parent, folder, dirs_exist_ok=True)
    text = (folder / src.name).read_text().replace("../../parameters/", f"{src.parent.parent.parent / 'parameters'}/")
    old = "[ligaments.MCL]\nfemur = [2.0, 8.0, -40.0]\ntibia = [6.0, -84.0, -26.0]\n"
    assert old in text
    (folder / src.name).write_text(text.replace(old, old + wrap))
    return kneenlp.Knee.load(folder / src.name)


RIM = ("\n[ligaments.MCL.wrap]\nbody = \"tibia\"\ncentre = [0.0, -10.0, -36.0]\naxis = [1.0, 0.0, 0.0]\n"
       "radius = 8.0\nside = \"{side}\"\n")


def test_a_knee_file_wraps_a_ligament_and_a_far_cylinder_changes_nothing(tmp_path):
    """The synthetic knee's MCL over a cylinder at the tibial plateau's medial rim: its reference
    length is the wrapped path's and valgus laxity changes; a cylinder far from the path gives the
    straight knee's laxity exactly."""
    straight = kneenlp.Knee.named("synthetic")
    base = kneenlp.simulate(straight, "set1").table()
    lengths = {}
    for side in ("positive", "negative"):
        (tmp_path / side).mkdir()
        knee = _knee_with_wrap(tmp_path / side, RIM.format(side=side))
        b = knee.ligaments["MCL"].bundles[0]
        assert isinstance(b.path, CylinderWrap) and b.path.body == "tibia"
        lengths[side] = knee.ligaments["MCL"].bundle_length(b)
    straight_length = straight.ligaments["MCL"].bundle_length(straight.ligaments["MCL"].bundles[0])
    assert min(lengths.values()) > straight_length + 1e-3
    knee = _knee_with_wrap(tmp_path / "positive", RIM.format(side="positive"))
    result = kneenlp.simulate(knee, "set1").table()
    assert result["converged"].all()
    assert not np.allclose(result["varus_rotation_deg"], base["varus_rotation_deg"], atol=0.05)
    (tmp_path / "far").mkdir()
    far = _knee_with_wrap(tmp_path / "far", RIM.format(side="positive").replace("[0.0, -10.0, -36.0]",
                                                                                 "[0.0, -10.0, -90.0]"))
    same = kneenlp.simulate(far, "set1").table()
    cols = ["varus_rotation_deg", "internal_rotation_deg", "anterior_translation_mm"]
    np.testing.assert_allclose(same[cols].to_numpy(), base[cols].to_numpy(), atol=1e-9)
    assert isinstance(StraightPath(), StraightPath)


def test_a_bad_wrap_is_named(tmp_path):
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap\.radius"):
        _knee_with_wrap(tmp_path, RIM.format(side="positive").replace("radius = 8.0", "radius = 0.0"))
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap\.side"):
        _knee_with_wrap(tmp_path, RIM.format(side="up"))


def test_the_nl_export_of_a_wrapping_knee_is_refused_in_one_line(tmp_path, capsys):
    """AMPL's .nl has no conditional: a knee whose path wraps is exported as CasADi or C, and
    --format nl says so (exit 2), where it was an internal error."""
    from kneenlp.cli import main

    knee = _knee_with_wrap(tmp_path, RIM.format(side="positive"))
    kneenlp.simulate(knee, "set1").measured("uniform:0.5", 1).to_csv(tmp_path / "m.csv", index=False)
    args = ["export", str(tmp_path / "m.csv"), "--knee", str(knee.source)]
    assert main([*args, "--format", "nl", "--out", str(tmp_path / "nl")]) == 2
    err = capsys.readouterr().err.strip()
    assert "the .nl format has no" in err and "--format casadi or c" in err and "\n" not in err
    assert main([*args, "--format", "casadi", "--out", str(tmp_path / "casadi")]) == 0


def test_a_path_at_a_discontinuity_says_why():
    """The long way round a cylinder (the straight line passes the axis on the other side), a
    straight line through an ellipsoid's centre, an attachment inside: each named; a smooth wrap not."""
    S, E = np.array([0.03, 0.002, -0.02]), np.array([-0.03, -0.003, 0.03])
    short, other = (CylinderWrap(np.zeros(3), [0, 0, 1], 0.01, "femur", side) for side in (1, -1))
    if short.length(E, S, *identity()) > other.length(E, S, *identity()):
        short, other = other, short
    assert short.jump(E, S, *identity()) == ""
    assert "long way round" in other.jump(E, S, *identity())
    w = ELLIPSOIDS[0]
    assert w.jump(E, S, *identity()) == ""
    through = EllipsoidWrap(0.5 * (S + E), w.axes, w.radii, "femur")  # centred on the straight line
    assert "switches sides" in through.jump(E, S, *identity())
    holding = EllipsoidWrap(S, w.axes, w.radii, "femur")
    assert "tibial attachment lies inside the wrapping ellipsoid" in holding.jump(E, S, *identity())


ELLIPSOID_RIM = ('\n[ligaments.MCL.wrap]\nshape = "ellipsoid"\nbody = "tibia"\ncentre = {centre}\n'
                 'axes = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\nradii = [10.0, 14.0, 8.0]\n')


def test_a_knee_file_wraps_an_ellipsoid_and_refuses_one_holding_an_attachment(tmp_path, capsys):
    """The synthetic MCL over an ellipsoid at the medial plateau's rim: wrapped, longer, simulated;
    an ellipsoid round the tibial attachment is refused in one line naming the bundle (exit 2);
    one the path never meets is noted; keys of the other shape are refused."""
    from kneenlp.cli import main

    (tmp_path / "a").mkdir()
    knee = _knee_with_wrap(tmp_path / "a", ELLIPSOID_RIM.format(centre="[0.0, -12.0, -36.0]"))
    mcl = knee.ligaments["MCL"]
    b = mcl.bundles[0]
    assert isinstance(b.path, EllipsoidWrap)
    assert mcl.bundle_length(b) > np.linalg.norm(b.femur - mcl.tibia_at_reference(b.tibia)) + 1e-3
    assert kneenlp.simulate(knee, "set1").table()["converged"].all()
    (tmp_path / "b").mkdir()
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap.*bundle 'MCL'.*tibial attachment lies inside"):
        _knee_with_wrap(tmp_path / "b", ELLIPSOID_RIM.format(centre="[6.0, -84.0, -26.0]"))
    assert main(["simulate", "--knee", str(tmp_path / "b" / "knee" / "knee.toml"), "--no-plots",
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "tibial attachment lies inside" in err and "\n" not in err
    (tmp_path / "c").mkdir()
    far = _knee_with_wrap(tmp_path / "c", ELLIPSOID_RIM.format(centre="[0.0, -12.0, -90.0]"))
    assert any("never meets its obstacle" in n for n in far.notes)
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap\.radius.*belongs to a cylinder"):
        _knee_with_wrap(tmp_path / "d", ELLIPSOID_RIM.format(centre="[0.0, -12.0, -36.0]") + "radius = 3.0\n")


def test_a_cylinder_passed_the_long_way_is_noted_in_the_solved_trials(tmp_path):
    """The rim cylinder declared on the side the path does not take (the longer one in the
    reference pose): simulate names the trials where the path goes the long way round."""
    knees = {}
    for side in ("positive", "negative"):
        (tmp_path / side).mkdir()
        knees[side] = _knee_with_wrap(tmp_path / side, RIM.format(side=side))
    length = {s: k.ligaments["MCL"].bundle_length(k.ligaments["MCL"].bundles[0]) for s, k in knees.items()}
    right, wrong = sorted(length, key=length.get)
    assert not any("long way" in n for n in kneenlp.simulate(knees[right], "set1").table()["note"])
    notes = kneenlp.simulate(knees[wrong], "set1").table()["note"]
    assert sum("MCL bundle 'MCL'" in n and "long way round" in n for n in notes) >= 2


def test_a_via_point_inside_a_bone_is_refused(tmp_path):
    """The default knee's MCL through a point inside its medial femoral condyle: the via
    point is checked against the bone as an attachment is, and named."""
    src = Path(kneenlp.Knee.named("default").source)
    text = src.read_text().replace('"../', f'"{src.parent}/../')
    text = text.replace("[ligaments.LCL]", "[ligaments.MCL.via]\nfemur = [[0.0, -0.008, -0.02]]\n\n[ligaments.LCL]")
    (tmp_path / "knee.toml").write_text(text)
    with pytest.raises(InputError, match=r"ligaments\.MCL\.via\.femur\[0\].*inside the femoral mesh"):
        kneenlp.Knee.load(tmp_path / "knee.toml")
