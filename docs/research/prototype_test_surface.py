"""Tests of surface.py (run: python -m pytest -q test_surface.py).  SI units throughout.

The Lenhart 2015 data (Apache-2.0, see the data README) are read from LENHART_DIR; the tests
that need them are skipped when it is absent.  The B-spline surface is built once per session
(h = 0.5 mm, ~35 s on a 2-core machine) and cached in /tmp.
"""
from __future__ import annotations

import os

import casadi as ca
import numpy as np
import pytest
import trimesh
from trimesh import triangles as T

import surface as S

LENHART_DIR = os.environ.get("LENHART_DIR", "/work/shared/data/opensim-jam-lenhart2015")
BONE = os.path.join(LENHART_DIR, "lenhart2015-R-femur-subchondral-bone.stl")
TIBIA = os.path.join(LENHART_DIR, "lenhart2015-R-tibia-cartilage.stl")
THICK = 2e-3  # femoral cartilage thickness [m]
SPACING = 5e-4
K = 1e10
DELTA = 1e-5
needs_data = pytest.mark.skipif(not os.path.exists(BONE), reason="Lenhart data not present")


@pytest.fixture(scope="session")
def lenhart():
    bone = trimesh.load(BONE)
    tib = trimesh.load(TIBIA)
    art = S.articular_surface_from_bone(bone, THICK)
    split = S.split_condyles(art, tib)
    axis = S.fit_flexion_axis(split["medial"], split["lateral"])
    box = S.contact_region_box(art, tib.vertices, axis["point"], axis["direction"])
    cache = "/tmp/kneenlp_fs_lenhart_h%g.npz" % SPACING
    if os.path.exists(cache):
        fs = S.FemoralSurface.load(cache)
    else:
        fs = S.FemoralSurface.from_mesh(bone, spacing=SPACING, box=box, offset=THICK,
                                        band=2e-3, depth=1.8e-3)
        fs.save(cache)
    areas = S.vertex_areas(tib)
    return dict(bone=bone, tib=tib, art=art, split=split, axis=axis, box=box, fs=fs,
                pts=np.asarray(tib.vertices), areas=areas)


def _pose(L, flex_deg, target_depth, add_deg=0.0):
    """Flexion about the fitted axis (+ optional adduction about the femoral x axis), then
    the tibia pushed along its long axis until the exact maximal depth equals target_depth."""
    R, p = S.flexion_pose(L["axis"]["point"], L["axis"]["direction"], np.radians(flex_deg))
    if add_deg:
        Ra = S.axis_rotation([1.0, 0, 0], np.radians(add_deg))
        c = L["axis"]["point"]
        R, p = Ra @ R, Ra @ (p - c) + c
    u = R @ np.array([0.0, 1.0, 0.0])

    def depth(s):
        return S.reference_contact(L["bone"], L["pts"], L["areas"], R, p + s * u, K, DELTA,
                                   offset=THICK)["max_depth"]

    lo, hi = -5e-3, 5e-3
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if depth(mid) < target_depth else (lo, mid)
    return R, p + 0.5 * (lo + hi) * u


# ------------------------------------------------------------------------------------------
def test_gate_is_c2_and_exact_zero():
    x = np.array([-1.0, -1e-9, 0.0, DELTA / 2, DELTA, 2 * DELTA])
    g = S.smooth_gate(x, DELTA)
    assert g[0] == 0 and g[1] == 0 and g[2] == 0
    assert np.isclose(g[4], DELTA / 2) and np.isclose(g[5], 1.5 * DELTA)
    s = ca.SX.sym("s")
    gs = S.smooth_gate(s, DELTA)
    f = ca.Function("f", [s], [gs, ca.gradient(gs, s), ca.hessian(gs, s)[0]])
    for a in (0.0, DELTA):  # value, slope and curvature continuous at the joints
        lo = [float(v) for v in f(a - 1e-13)]
        hi = [float(v) for v in f(a + 1e-13)]
        assert np.allclose(lo, hi, atol=1e-6 / DELTA)


@needs_data
def test_certified_distance_is_exact(lenhart):
    bone = lenhart["bone"]
    rng = np.random.default_rng(3)
    X = lenhart["pts"][rng.choice(len(lenhart["pts"]), 25)] + rng.normal(0, 2e-3, (25, 3))
    d = S.mesh_signed_distance(bone, X)[0]
    for x, di in zip(X, d):
        c = T.closest_point(bone.triangles, np.repeat(x[None], len(bone.faces), 0))
        assert abs(np.linalg.norm(c - x, axis=1).min() - abs(di)) < 1e-12


@needs_data
def test_frames_and_thickness(lenhart):
    """Bone and tibial cartilage are both in their body frames, which coincide at the
    default pose: the tibial cartilage then lies 1.5-2.5 mm below the bone, none inside."""
    d = S.mesh_signed_distance(lenhart["bone"], lenhart["pts"])[0]
    assert 1.5e-3 < d.min() < 2.5e-3
    meta = lenhart["art"].metadata["articular"]
    assert abs(meta["achieved_offset_mean"] - THICK) < 1e-4


@needs_data
def test_split_and_axis(lenhart):
    sp, ax = lenhart["split"], lenhart["axis"]
    n = sp["plane_normal"]
    assert n[2] > 0.95  # roughly medial-lateral (+z lateral for a right knee)
    c = sp["tibia_centroids"]
    s = [(ci - sp["plane_point"]) @ n for ci in c]
    assert s[0] < 0 < s[1]  # notch between the medial and lateral compartments
    assert sp["medial"].triangles_center[:, 2].mean() < sp["lateral"].triangles_center[:, 2].mean()
    assert ax["direction"][2] > np.cos(np.radians(10))
    assert ax["rms"] < 1e-3
    for side in ("medial", "lateral"):
        assert 0.012 < ax[side]["radius"] < 0.03


@needs_data
def test_sdf_vs_exact_in_band(lenhart):
    fs, bone = lenhart["fs"], lenhart["bone"]
    rng = np.random.default_rng(0)
    X = lenhart["pts"][rng.choice(len(lenhart["pts"]), 3000)] + rng.normal(0, 1e-3, (3000, 3))
    dx = S.mesh_signed_distance(bone, X)[0] - THICK
    m = np.abs(dx) < 1.5e-3
    assert m.sum() > 300
    dn, _ = fs.eval_np(X[m])
    err = dn - dx[m]
    assert np.sqrt(np.mean(err**2)) < 10e-6 and np.abs(err).max() < 60e-6
    # the CasADi Function evaluates the same spline
    sdf = fs.signed_distance_function().map(int(m.sum()))
    dc = np.array(sdf(X[m].T)[0]).ravel()
    assert np.abs(dc - dn).max() < 1e-12


POSES = [(0.0, 0.3e-3, 0.0), (0.0, 0.8e-3, 0.0), (30.0, 0.5e-3, 0.0), (60.0, 0.5e-3, 2.0),
         (90.0, 0.3e-3, 0.0), (90.0, 1.0e-3, -2.0)]


@needs_data
@pytest.mark.parametrize("flex,depth,add", POSES)
def test_contact_vs_reference(lenhart, flex, depth, add):
    R, p = _pose(lenhart, flex, depth, add)
    ref = S.reference_contact(lenhart["bone"], lenhart["pts"], lenhart["areas"], R, p, K, DELTA,
                              offset=THICK)
    assert 0.1e-3 <= ref["max_depth"] <= 1.0e-3
    fn = lenhart["fs"].contact_wrench(lenhart["pts"], lenhart["areas"], DELTA, with_cop=True)
    F, M, cop, W = (np.array(v).ravel() for v in fn(R, p, K))
    rel = np.linalg.norm(F) / np.linalg.norm(ref["force"]) - 1
    assert abs(rel) < 0.02, (rel, F, ref["force"])
    assert np.linalg.norm(cop - ref["cop"]) < 1e-3
    ang = np.degrees(np.arccos(F @ ref["force"] / np.linalg.norm(F) / np.linalg.norm(ref["force"])))
    assert ang < 2.0
    assert np.linalg.norm(M - ref["moment"]) < 0.02 * np.linalg.norm(ref["force"]) * 0.05


def test_sphere_against_plane():
    """Sphere mesh (R = 20 mm) pressed 1 mm into a plane of sample points:
    F = pi K (R-d) (d^2 - delta d + 0.3 delta^2)  (-> pi K d^2 (R-d) for delta -> 0)."""
    Rs, d = 0.02, 1e-3
    sph = trimesh.creation.icosphere(subdivisions=6, radius=Rs)
    h = 1e-4
    g = np.arange(-8e-3, 8e-3 + h / 2, h)
    xx, zz = np.meshgrid(g, g)
    pts = np.c_[xx.ravel(), np.zeros(xx.size), zz.ravel()]  # tibial plane y = 0
    areas = np.full(len(pts), h * h)
    R = np.eye(3)
    p = np.array([0.0, -Rs + d, 0.0])  # plane at y = -R + d in the sphere frame
    exact = np.pi * K * (Rs - d) * (d**2 - DELTA * d + 0.3 * DELTA**2)
    ref = S.reference_contact(sph, pts, areas, R, p, K, DELTA)
    assert abs(-ref["force"][1] / exact - 1) < 0.01
    box = (np.array([-9e-3, -Rs, -9e-3]), np.array([9e-3, -Rs + 3e-3, 9e-3]))
    fs = S.FemoralSurface.from_mesh(sph, spacing=2.5e-4, box=box)
    F, M = (np.array(v).ravel() for v in fs.contact_wrench(pts, areas, DELTA)(R, p, K))
    assert F[1] < 0  # force on the plane pushes it away from the sphere (-y)
    assert abs(-F[1] / exact - 1) < 0.01, (-F[1], exact)
    # tangential residue from the icosphere facets (not rotationally symmetric): ~0.6 %
    assert np.linalg.norm(F[[0, 2]]) < 1e-2 * abs(F[1])


@needs_data
def test_derivatives_match_finite_differences(lenhart):
    R0, p0 = _pose(lenhart, 30.0, 0.5e-3)
    fs = lenhart["fs"]
    ws = fs.working_set(lenhart["pts"], R0, p0, margin=1e-3)
    fn = fs.contact_wrench(lenhart["pts"][ws], lenhart["areas"][ws], DELTA)
    q = ca.MX.sym("q", 6)  # rotation vector + translation
    wx, wy, wz = q[0], q[1], q[2]
    Kx = ca.vertcat(ca.horzcat(0, -wz, wy), ca.horzcat(wz, 0, -wx), ca.horzcat(-wy, wx, 0))
    th2 = wx**2 + wy**2 + wz**2 + 1e-30  # Rodrigues (exact rotation)
    th = ca.sqrt(th2)
    Rq = ca.mtimes(ca.DM(R0), ca.DM.eye(3) + ca.sin(th) / th * Kx
                   + (1 - ca.cos(th)) / th2 * ca.mtimes(Kx, Kx))
    w = ca.vertcat(*fn(Rq, ca.DM(p0) + q[3:], K))
    f = ca.Function("f", [q], [w])
    J = ca.Function("J", [q], [ca.jacobian(w, q)])
    lam = np.array([0.3, -1.0, 0.2, 5.0, 2.0, -3.0])
    H = ca.Function("H", [q], [ca.hessian(ca.dot(ca.DM(lam), w), q)[0]])
    q0 = np.array([1e-3, -2e-3, 1e-3, 1e-5, 2e-5, -1e-5])
    Ja = np.array(J(q0))
    eps = np.r_[1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]
    Jf = np.column_stack([(np.array(f(q0 + e)) - np.array(f(q0 - e))).ravel() / (2 * e[i])
                          for i, e in enumerate(np.diag(eps))])
    assert np.all(np.isfinite(Ja))
    assert np.linalg.norm(Ja - Jf) < 1e-3 * np.linalg.norm(Ja)
    g = ca.Function("g", [q], [ca.jacobian(ca.dot(ca.DM(lam), w), q)])
    Ha = np.array(H(q0))
    Hf = np.column_stack([(np.array(g(q0 + e)) - np.array(g(q0 - e))).ravel() / (2 * e[i])
                          for i, e in enumerate(np.diag(eps))])
    assert np.linalg.norm(Ha - Hf) < 1e-2 * np.linalg.norm(Ha)


@needs_data
def test_zero_force_outside_and_no_nan(lenhart):
    fs = lenhart["fs"]
    pts = np.array([[0.0, -0.02, 0.0], [0.1, 0.1, 0.1], [5.0, -3.0, 2.0]])
    fn = fs.contact_wrench(pts, np.full(3, 1e-6), DELTA)
    R = ca.MX.sym("R", 3, 3)
    p = ca.MX.sym("p", 3)
    F, M = fn(R, p, K)
    w = ca.vertcat(F, M)
    pv = ca.vertcat(ca.vec(R), p)
    JH = ca.Function("jh", [R, p], [w, ca.jacobian(w, pv), ca.hessian(ca.sum1(w), pv)[0]])
    for pp in ([0.0, -0.01, 0.0], [1.0, 1.0, 1.0], [-0.3, 0.0, 0.2]):  # far away / outside grid
        for out in JH(np.eye(3), pp):
            a = np.array(out)
            assert np.all(np.isfinite(a)) and np.all(a == 0)


@needs_data
def test_working_set(lenhart):
    fs = lenhart["fs"]
    R, p = _pose(lenhart, 0.0, 0.5e-3)
    ws = fs.working_set(lenhart["pts"], R, p, margin=1e-3)
    assert 0 < len(ws) < len(lenhart["pts"]) / 2
    full = fs.contact_wrench(lenhart["pts"], lenhart["areas"], DELTA)
    part = fs.contact_wrench(lenhart["pts"][ws], lenhart["areas"][ws], DELTA)
    for dp in ([0, 0, 0], [0, 3e-4, 0], [2e-4, 2e-4, -3e-4]):
        pp = p + np.array(dp)
        assert fs.check_excluded(lenhart["pts"], ws, R, pp) <= 0
        a = np.array(ca.vertcat(*full(R, pp, K)))
        b = np.array(ca.vertcat(*part(R, pp, K)))
        assert np.allclose(a, b, rtol=1e-12, atol=1e-9)
    # a 1.5 mm push exceeds the 1 mm margin: the check must flag it
    assert fs.check_excluded(lenhart["pts"], ws, R, p + R @ np.array([0, 1.5e-3, 0])) > 0
