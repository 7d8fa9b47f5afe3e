"""Tests for osim.py.  The `opensim` 4.6 wheel is the external oracle (frames, kinematics,
SimmSpline, Blankevoort1991Ligament force law, calibrated-file round trip); it runs in a
separate process (see `oracle`) because it cannot be imported next to kneenlp's casadi."""
from __future__ import annotations

import difflib
import itertools
import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest

from kneenlp.base.resources import resource
from kneenlp.io import osim as O
from kneenlp.io.osim import kinematics as K

LENHART = str(resource("knees", "lenhart2015", "opensim", "lenhart2015.osim"))


@pytest.fixture(scope="module")
def model() -> O.OsimModel:
    return O.read_osim(LENHART)


@pytest.fixture(scope="module")
def raw_text() -> str:
    with open(LENHART, encoding="utf-8", newline="") as fh:  # keep CRLF
        return fh.read()


# ----------------------------------------------------------------------------- OpenSim oracle process
# The opensim wheel's libosimMoco is linked against a different casadi build than the one kneenlp
# uses: once casadi is loaded (importing kneenlp does that) `import opensim` fails with an undefined
# casadi symbol.  All OpenSim queries are therefore made in ONE separate Python process that imports
# only opensim and json; it reads its queries from a JSON file and writes the raw OpenSim numbers to
# another JSON file (floats round-trip exactly through JSON).  All comparisons happen in the tests.
_ORACLE_SCRIPT = r"""
import json
import sys

with open(sys.argv[1], encoding="utf-8") as fh:
    query = json.load(fh)


def dump(obj):
    with open(sys.argv[2], "w", encoding="utf-8") as fh:
        json.dump(obj, fh)


try:
    import opensim as osm
except ImportError as e:  # reported to the test process, which skips
    dump({"unavailable": f"{type(e).__name__}: {e}"})
    sys.exit(0)
osm.Logger.setLevelString("error")


def T(xf):
    R, p = xf.R(), xf.p()
    return [[R.get(i, 0), R.get(i, 1), R.get(i, 2), p.get(i)] for i in range(3)] + [[0.0, 0.0, 0.0, 1.0]]


def v3(v):
    return [v.get(0), v.get(1), v.get(2)]


def lig(fs, name):
    return osm.Blankevoort1991Ligament.safeDownCast(fs.get(name))


out = {"version": osm.__version__}

# body-fixed XYZ orientation of a PhysicalOffsetFrame
q = query["offset"]
m = osm.Model()
b = osm.Body("b", 1, osm.Vec3(0), osm.Inertia(1))
m.addBody(b)
m.addJoint(osm.WeldJoint("w", m.getGround(), osm.Vec3(*q["translation"]), osm.Vec3(*q["orientation"]),
                         b, osm.Vec3(0), osm.Vec3(0)))
s = m.initSystem()
out["offset"] = T(b.getTransformInGround(s))

# SimmSpline values
out["spline"] = {}
for key, c in query["spline"].items():
    ref = osm.SimmSpline()
    for xi, yi in zip(c["x"], c["y"]):
        ref.addPoint(xi, yi)
    out["spline"][key] = [ref.calcValue(osm.Vector(1, t)) for t in c["t"]]

# stripped Lenhart model: body transforms, path points in ground, path lengths per pose
m = osm.Model(query["model"])
s0 = m.initSystem()
cs, bs, fs = m.getCoordinateSet(), m.getBodySet(), m.getForceSet()
out["poses"] = {}
for pose, coords in query["poses"].items():
    s = osm.State(s0)
    for i in range(cs.getSize()):
        c = cs.get(i)
        c.setValue(s, coords.get(c.getName(), c.getDefaultValue()), False)
    m.realizePosition(s)
    res = {"bodies": {bs.get(i).getName(): T(bs.get(i).getTransformInGround(s)) for i in range(bs.getSize())},
           "points": {}, "lengths": {}}
    for i in range(fs.getSize()):
        f = osm.Blankevoort1991Ligament.safeDownCast(fs.get(i))
        if f is None:
            continue
        pps = f.getGeometryPath().getPathPointSet()
        res["points"][f.getName()] = [v3(pps.get(k).getLocationInGround(s)) for k in range(pps.getSize())]
        res["lengths"][f.getName()] = f.getLength(s)
    out["poses"][pose] = res

# Blankevoort1991Ligament force law on a slider
out["force"] = {}
for key, c in query["force"].items():
    m = osm.Model()
    b = osm.Body("b", 1.0, osm.Vec3(0), osm.Inertia(1e-3))
    m.addBody(b)
    sl = osm.SliderJoint("s", m.getGround(), b)
    m.addJoint(sl)
    f = osm.Blankevoort1991Ligament("lig", m.getGround(), osm.Vec3(0), b, osm.Vec3(0), c["k"], c["L0"])
    f.set_transition_strain(c["et"])
    m.addForce(f)
    s = m.initSystem()
    coord = sl.getCoordinate()
    rows = []
    for L in c["lengths"]:
        coord.setValue(s, L)
        coord.setSpeedValue(s, 0.0)
        m.realizeVelocity(s)
        rows.append([f.getLength(s), f.getSpringForce(s), f.getTotalForce(s)])
    out["force"][key] = rows

# calibrated (and stripped) model read back by OpenSim
m = osm.Model(query["calibrated"]["model"])
m.initSystem()
fs = m.getForceSet()
out["calibrated"] = {n: {"linear_stiffness": lig(fs, n).get_linear_stiffness(),
                         "slack_length": lig(fs, n).get_slack_length(),
                         "transition_strain": lig(fs, n).get_transition_strain()}
                     for n in query["calibrated"]["ligaments"]}
dump(out)
"""

OFFSET_TRANSLATION, OFFSET_ORIENTATION = (0.1, 0.2, 0.3), (0.3, -0.5, 0.7)
SPLINE_SIZES = (2, 3, 4, 7, 14)
FORCE_TRANSITION_STRAINS = (0.06, 0.1)
FORCE_L0, FORCE_K = 0.05, 1000.0
POSES: dict[str, dict[str, float]] = {
    "default": {},
    "flexed": {"knee_flex_r": 0.8, "knee_add_r": 0.05, "knee_rot_r": -0.12, "knee_tx_r": 0.003,
               "knee_ty_r": -0.002, "knee_tz_r": 0.001, "hip_flex_r": 0.4, "hip_add_r": -0.1,
               "hip_rot_r": 0.2, "pelvis_tilt": 0.1, "pelvis_tx": 0.3, "pf_flex_r": 0.5,
               "pf_rot_r": 0.05, "pf_tilt_r": 0.02, "pf_ty_r": -0.01,
               "knee_flex_l": 1.3, "ankle_flex_r": 0.2},  # knee_l uses SimmSplines
}
CAL_VALUES = {"MCLd1": {"linear_stiffness": 1234.5, "slack_length": 0.031234567891},
              "ACLam2": {"slack_length": 0.0301},
              "PCLpm3": {"transition_strain": 0.05}}  # absent in file -> inserted
CAL_READBACK = ("MCLd1", "ACLam2", "PCLpm3", "PCLpm2")


def _spline_case(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Knots (x, y) and evaluation points t of the SimmSpline comparison with n knots."""
    rng = np.random.default_rng(n)
    x = np.sort(rng.uniform(-1, 2, n)) + np.arange(n) * 0.05
    y = rng.normal(size=n)
    return x, y, np.linspace(x[0] - 0.5, x[-1] + 0.5, 57)


def _force_lengths(et: float) -> np.ndarray:
    return FORCE_L0 * (1 + np.array([-0.2, -1e-9, 0.0, 1e-4, 0.25 * et, 0.5 * et, 0.999 * et, et,
                                     1.001 * et, 2 * et, 0.3]))


@pytest.fixture(scope="module")
def oracle(tmp_path_factory) -> dict:
    """All OpenSim reference numbers, computed in one `opensim`-only subprocess (or skip)."""
    d = tmp_path_factory.mktemp("opensim_oracle")
    stripped = d / "lenhart_stripped.osim"
    removed = O.write_opensim_loadable_copy(LENHART, stripped)
    assert sorted(removed) == sorted(["tf_contact", "pf_contact", "femur_cartilage",
                                      "tibia_cartilage", "patella_cartilage"])
    cal, cal_stripped = d / "cal.osim", d / "cal_stripped.osim"
    O.write_calibrated(LENHART, cal, CAL_VALUES)
    O.write_opensim_loadable_copy(cal, cal_stripped)
    query = {
        "offset": {"translation": OFFSET_TRANSLATION, "orientation": OFFSET_ORIENTATION},
        "spline": {str(n): dict(zip("xyt", (a.tolist() for a in _spline_case(n)), strict=True))
                   for n in SPLINE_SIZES},
        "model": str(stripped),
        "poses": POSES,
        "force": {str(et): {"L0": FORCE_L0, "k": FORCE_K, "et": et, "lengths": _force_lengths(et).tolist()}
                  for et in FORCE_TRANSITION_STRAINS},
        "calibrated": {"model": str(cal_stripped), "ligaments": CAL_READBACK},
    }
    qf, rf = d / "query.json", d / "result.json"
    qf.write_text(json.dumps(query), encoding="utf-8")
    # cwd: OpenSim writes opensim.log into the working directory
    proc = subprocess.run([sys.executable, "-c", _ORACLE_SCRIPT, str(qf), str(rf)], cwd=d,
                          capture_output=True, text=True, timeout=300, check=False)
    if proc.returncode != 0 or not rf.exists():
        pytest.fail(f"OpenSim oracle process failed (exit {proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    res = json.loads(rf.read_text(encoding="utf-8"))
    if "unavailable" in res:
        pytest.skip(f"opensim is not importable in a plain subprocess ({res['unavailable']})")
    res["calibrated_file"] = cal
    return res


def _T(rows) -> np.ndarray:
    X = np.array(rows, dtype=float)
    assert X.shape == (4, 4)
    return X


# ----------------------------------------------------------------------------- parsing
def test_counts_and_groups(model, raw_text):
    n_xml = len(re.findall(r"<Blankevoort1991Ligament\s+name=", raw_text))
    assert n_xml == 76 and len(model.ligaments) == 76
    g = O.ligament_groups(model)
    assert {k: len(v) for k, v in g["fine"].items()} == {
        "MCLd": 5, "MCLs": 6, "ACLpl": 6, "ACLam": 6, "PCLal": 5, "PCLpm": 5, "LCL": 4, "PT": 6,
        "lPFL": 8, "mPFL": 6, "MCLp": 5, "PFL": 5, "pCAP": 8, "ITB": 1}
    assert {k: len(v) for k, v in g["coarse"].items()} == {
        "MCL": 16, "ACL": 12, "PCL": 10, "LCL": 4, "PT": 6, "lPFL": 8, "mPFL": 6, "PFL": 5,
        "pCAP": 8, "ITB": 1}
    assert g["coarse"]["ACL"][:2] == ["ACLpl1", "ACLpl2"]
    assert sum(len(v) for v in g["fine"].values()) == 76


def test_group_rule_generic():
    g = O.ligament_groups(["ACLam1", "ACLpl12", "MCLs3", "MCLd1", "mPFL2", "PFL1", "pCAP10",
                           "lig_a_3", "ITB"])
    assert g["fine"] == {"ACLam": ["ACLam1"], "ACLpl": ["ACLpl12"], "MCLs": ["MCLs3"],
                         "MCLd": ["MCLd1"], "mPFL": ["mPFL2"], "PFL": ["PFL1"],
                         "pCAP": ["pCAP10"], "lig_a": ["lig_a_3"], "ITB": ["ITB"]}
    assert g["coarse"] == {"ACL": ["ACLam1", "ACLpl12"], "MCL": ["MCLs3", "MCLd1"],
                           "mPFL": ["mPFL2"], "PFL": ["PFL1"], "pCAP": ["pCAP10"],
                           "lig_a": ["lig_a_3"], "ITB": ["ITB"]}


def test_properties_and_points_match_xml(model, raw_text):
    # independent regex extraction of every ligament
    for m in re.finditer(r'<Blankevoort1991Ligament name="([^"]+)">(.*?)</Blankevoort1991Ligament>',
                         raw_text, re.S):
        name, body = m.group(1), m.group(2)
        lig = model.ligaments[name]
        assert lig.linear_stiffness == float(re.search(r"<linear_stiffness>([^<]+)<", body).group(1))
        assert lig.slack_length == float(re.search(r"<slack_length>([^<]+)<", body).group(1))
        pts = re.findall(r"<socket_parent_frame>([^<]+)</socket_parent_frame>\s*(?:<!--.*?-->\s*)?"
                         r"<location>([^<]+)</location>", body, re.S)
        assert [p.frame for p in lig.points] == [f for f, _ in pts]
        for p, (_, loc) in zip(lig.points, pts, strict=True):
            np.testing.assert_array_equal(p.location, [float(x) for x in loc.split()])
    # literal spot checks
    mcl = model.ligaments["MCLd1"]
    assert (mcl.linear_stiffness, mcl.slack_length) == (500.0, 0.03075)
    assert mcl.points[0].body == "femur_distal_r" and mcl.points[1].body == "tibia_proximal_r"
    np.testing.assert_array_equal(mcl.points[0].location, [-0.0017455, -0.00045737, -0.037269])
    np.testing.assert_array_equal(mcl.points[1].location, [-0.00021515, -0.031853, -0.031379])
    assert mcl.wraps == ["Med_Lig_r"] and any("Med_Lig_r" in s for s in mcl.skipped)
    assert model.ligaments["ACLam1"].linear_stiffness == 820.0
    assert model.ligaments["PT1"].bodies == ("patella_r", "tibia_proximal_r")
    assert model.ligaments["ITB1"].bodies == ("pelvis", "femur_r", "tibia_r")
    # transition strain / damping are not in this file -> OpenSim defaults
    assert all(lg.from_file == ("linear_stiffness", "slack_length") for lg in model.ligaments.values())
    assert all(lg.transition_strain == 0.06 and lg.damping_coefficient == 0.003
               for lg in model.ligaments.values())


def test_model_structure(model):
    assert model.length_units == "m" and model.force_units == "N"
    knee = model.joints["knee_r"]
    assert knee.type == "CustomJoint"
    assert (knee.parent_frame, knee.child_frame) == ("/bodyset/femur_distal_r", "/bodyset/tibia_proximal_r")
    assert [c.name for c in knee.coordinates] == ["knee_flex_r", "knee_add_r", "knee_rot_r",
                                                  "knee_tx_r", "knee_ty_r", "knee_tz_r"]
    assert all(c.default_value == 0.0 for c in knee.coordinates)
    assert model.joints["hip_r"].parent_frame == "/jointset/hip_r/pelvis_offset"
    cm = model.contact_meshes
    assert set(cm) == {"femur_cartilage", "tibia_cartilage", "patella_cartilage"}
    t = cm["tibia_cartilage"]
    assert (t.body, t.mesh_file, t.mesh_back_file) == ("tibia_proximal_r",
                                                      "lenhart2015-R-tibia-cartilage.stl",
                                                      "lenhart2015-R-tibia-bone.stl")
    assert (t.thickness, t.elastic_modulus, t.poissons_ratio) == (0.003, 1e7, 0.45)
    np.testing.assert_array_equal(t.X_body_mesh(model), np.eye(4))
    assert [g.mesh_file for g in model.bodies["tibia_proximal_r"].meshes] == [
        "lenhart2015-R-tibia-bone.stl", "lenhart2015-R-tibia-cartilage.stl",
        "lenhart2015-R-fibula-bone.stl"]
    assert model.wrap_objects["Med_Lig_r"].body == "tibia_proximal_r"
    assert model.welded_bodies("femur_distal_r") == {"femur_r", "femur_distal_r"}
    assert model.welded_bodies("tibia_proximal_r") == {"tibia_r", "tibia_proximal_r"}


def test_knee_line_elements(model):
    le = O.knee_line_elements(model)
    assert len(le) == 76 - 6 - 8 - 6  # all but PT, lPFL, mPFL
    # femur and tibia frames coincide at default pose: tibial point == tibia_proximal_r location
    np.testing.assert_allclose(le["MCLd1"].tibial_point, [-0.00021515, -0.031853, -0.031379])
    # ITB: femur_r via point re-expressed in femur_distal_r; pelvis origin dropped
    itb = model.ligaments["ITB1"]
    np.testing.assert_allclose(le["ITB1"].femoral_point,
                               itb.points[1].location + np.array([0.0055513564376633642,
                                                                   0.37418143637169787,
                                                                   0.0011706232813375212]))
    assert le["ITB1"].ignored_points == ["ITB1-P1"]
    assert not le["ITB1"].extra_length_constant and le["ITB1"].extra_length > 0.1
    assert le["MCLd1"].extra_length == 0.0 and le["MCLd1"].extra_length_constant
    # right knee, Z lateral: MCL femoral attachments medial (z<0), LCL lateral (z>0)
    assert all(le[f"MCLs{i}"].femoral_point[2] < 0 for i in range(1, 7))
    assert all(le[f"LCL{i}"].femoral_point[2] > 0 for i in range(1, 5))


# ----------------------------------------------------------------------------- errors
_MINI = """<?xml version="1.0" encoding="UTF-8" ?>
<OpenSimDocument Version="40000">
<Model name="mini">
 <Ground name="ground"/>
 <BodySet name="bodyset"><objects>
  <Body name="a"><mass>1</mass><mass_center>0 0 0</mass_center></Body>
 </objects></BodySet>
 <JointSet name="jointset"><objects>
  <WeldJoint name="w"><socket_parent_frame>/ground</socket_parent_frame>
   <socket_child_frame>/bodyset/a</socket_child_frame></WeldJoint>
 </objects></JointSet>
 <ForceSet name="forceset"><objects>
  <Blankevoort1991Ligament name="L1">
   <GeometryPath name="geometrypath"><PathPointSet><objects>
    <PathPoint name="p1"><socket_parent_frame>/ground</socket_parent_frame><location>0 0 0</location></PathPoint>
    POINT
    <PathPoint name="p2"><socket_parent_frame>/bodyset/a</socket_parent_frame><location>0 0.1 0</location></PathPoint>
   </objects></PathPointSet></GeometryPath>
   <linear_stiffness>LK</linear_stiffness><slack_length>0.05</slack_length>
  </Blankevoort1991Ligament>
 </objects></ForceSet>
</Model></OpenSimDocument>
"""


def _mini(tmp_path, point="", k="100"):
    p = tmp_path / "mini.osim"
    p.write_text(_MINI.replace("POINT", point).replace("LK", k))
    return str(p)


def test_moving_point_skipped(tmp_path):
    mp = ('<MovingPathPoint name="mv"><socket_parent_frame>/bodyset/a</socket_parent_frame>'
          '</MovingPathPoint>')
    m = O.read_osim(_mini(tmp_path, mp))
    lig = m.ligaments["L1"]
    assert [p.name for p in lig.points] == ["p1", "p2"]
    assert len(lig.skipped) == 1 and "<MovingPathPoint> 'mv'" in lig.skipped[0] and "skipped" in lig.skipped[0]
    assert "\n" not in lig.skipped[0]


@pytest.mark.parametrize("point,k,needle", [
    ('<FancyPathPoint name="zz"/>', "100", "<FancyPathPoint> 'zz': unknown path point type"),
    ("", "abc", "<linear_stiffness>: cannot parse 'abc'"),
    ('<PathPoint name="q"><socket_parent_frame>/bodyset/nope</socket_parent_frame>'
     '<location>0 0 0</location></PathPoint>', "100", "parent frame '/bodyset/nope' not found"),
])
def test_errors_name_file_and_element(tmp_path, point, k, needle):
    p = _mini(tmp_path, point, k)
    with pytest.raises(O.OsimError) as ei:
        O.read_osim(p)
    msg = str(ei.value)
    assert p in msg and needle in msg and "Blankevoort1991Ligament 'L1'" in msg and "\n" not in msg


def test_malformed_xml(tmp_path):
    p = tmp_path / "bad.osim"
    p.write_text("<OpenSimDocument><Model name='x'><BodySet></Model>")
    with pytest.raises(O.OsimError, match=r"bad\.osim: malformed XML"):
        O.read_osim(str(p))
    p.write_text("<Foo/>")
    with pytest.raises(O.OsimError, match="root element <Foo>"):
        O.read_osim(str(p))


@pytest.mark.parametrize("tag, value", [("dimensions", "0.02 -0.01 0.03"), ("dimensions", "0 0.01 0.03")])
def test_a_wrapping_surface_of_no_size_is_refused(tmp_path, tag, value):
    """Else the importer would write a knee file its reader refuses (a radius <= 0)."""
    text = open(LENHART, encoding="utf-8").read()
    start = text.index('<WrapEllipsoid name="Med_Lig_r">')
    i, j = text.index(f"<{tag}>", start), text.index(f"</{tag}>", start)
    p = tmp_path / "bad.osim"
    p.write_text(text[:i] + f"<{tag}>{value}" + text[j:])
    with pytest.raises(O.OsimError, match=rf"bad\.osim: WrapEllipsoid '.*Med_Lig_r' <{tag}>: .* must be > 0 m"):
        O.read_osim(str(p))


# ----------------------------------------------------------------------------- OpenSim oracle
def test_offset_orientation_is_body_fixed_xyz(oracle):
    X = _T(oracle["offset"])
    np.testing.assert_allclose(X[:3, :3], O.rot_body_xyz(OFFSET_ORIENTATION), atol=1e-14)
    np.testing.assert_allclose(X[:3, 3], OFFSET_TRANSLATION, atol=1e-14)


@pytest.mark.parametrize("n", SPLINE_SIZES)
def test_simmspline_matches_opensim(oracle, n):
    x, y, ts = _spline_case(n)
    ref = oracle["spline"][str(n)]
    assert len(ref) == len(ts)
    mine = K._SimmSpline(x, y)
    for t, r in zip(ts, ref, strict=True):
        assert mine(t) == pytest.approx(r, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("pose", list(POSES))
def test_body_transforms_and_points_match_opensim(model, oracle, pose):
    coords = POSES[pose]
    ref = oracle["poses"][pose]
    mine = model.body_transforms(coords)
    assert ref["bodies"]
    for name, X in ref["bodies"].items():
        np.testing.assert_allclose(mine[name], _T(X), atol=1e-12, err_msg=name)
    # every ligament path point in ground; straight-line lengths of non-wrapping bundles
    assert set(ref["points"]) == set(model.ligaments)
    for lig in model.ligaments.values():
        ref_points = ref["points"][lig.name]
        assert len(ref_points) == len(lig.points)
        pg = []
        for p, ref_point in zip(lig.points, ref_points, strict=True):
            g = K._apply(mine[p.body], p.location_in_body)
            np.testing.assert_allclose(g, ref_point, atol=1e-12)
            pg.append(g)
        if not lig.wraps:
            L = sum(np.linalg.norm(b - a) for a, b in itertools.pairwise(pg))
            assert L == pytest.approx(ref["lengths"][lig.name], rel=1e-12)
    # tibial points expressed in the femoral frame agree with OpenSim
    X_ft = model.transform("femur_distal_r", "tibia_proximal_r", coords)
    Xf = _T(ref["bodies"]["femur_distal_r"])
    Xt = _T(ref["bodies"]["tibia_proximal_r"])
    np.testing.assert_allclose(X_ft, np.linalg.inv(Xf) @ Xt, atol=1e-12)
    if pose == "default":
        np.testing.assert_allclose(X_ft, np.eye(4), atol=0)
        itb = O.knee_line_elements(model)["ITB1"]
        L = np.linalg.norm(itb.femoral_point - itb.tibial_point) + itb.extra_length
        assert L == pytest.approx(ref["lengths"]["ITB1"], rel=1e-12)


# ----------------------------------------------------------------------------- force law
@pytest.mark.parametrize("et", FORCE_TRANSITION_STRAINS)
def test_force_law_matches_opensim(oracle, et):
    L0, k = FORCE_L0, FORCE_K
    lengths = _force_lengths(et)
    ref = oracle["force"][str(et)]
    assert len(ref) == len(lengths)
    for Lq, (ref_length, ref_spring, ref_total) in zip(lengths, ref, strict=True):
        assert ref_length == pytest.approx(Lq, rel=1e-14)
        mine = O.blankevoort_force(Lq, L0, k, et)
        assert mine == pytest.approx(ref_spring, rel=1e-6, abs=1e-9)
        assert mine == pytest.approx(ref_total, rel=1e-6, abs=1e-9)
        # paper form: f = k e^2/(4 e_l) (0<=e<=2 e_l), k (e - e_l) beyond, e_l = et/2
        e, el = Lq / L0 - 1, et / 2
        paper = 0.0 if e <= 0 else (k * e * e / (4 * el) if e <= 2 * el else k * (e - el))
        assert mine == pytest.approx(paper, rel=1e-12, abs=1e-12)
    # vectorised and continuous at the transition (value and slope k)
    f = O.blankevoort_force(np.array([L0 * (1 + et) - 1e-9, L0 * (1 + et) + 1e-9]), L0, k, et)
    assert f[1] - f[0] == pytest.approx(k * 2e-9 / L0, rel=1e-3)


# ----------------------------------------------------------------------------- writer
def test_write_calibrated_changes_only_values(tmp_path, model, raw_text, oracle):
    out = tmp_path / "cal.osim"
    vals = CAL_VALUES
    changes = O.write_calibrated(LENHART, out, vals)
    assert ("MCLd1", "linear_stiffness", "500", "1234.5") in changes
    new_text = out.read_bytes().decode("utf-8")
    old_lines, new_lines = raw_text.splitlines(keepends=True), new_text.splitlines(keepends=True)
    diff = [d for d in difflib.unified_diff(old_lines, new_lines, n=0)
            if d[:1] in "+-" and not d.startswith(("+++", "---"))]
    assert sorted(d[0] + d[1:].strip() for d in diff) == sorted([
        "-<linear_stiffness>500</linear_stiffness>", "+<linear_stiffness>1234.5</linear_stiffness>",
        "-<slack_length>0.03075</slack_length>", "+<slack_length>0.031234567891</slack_length>",
        "-<slack_length>0.029948600000000044</slack_length>", "+<slack_length>0.0301</slack_length>",
        "+<transition_strain>0.05</transition_strain>"])
    # line structure and CRLF endings preserved; undoing the edits gives the source bytes
    assert len(new_lines) == len(old_lines) + 1
    assert new_text.count("\r\n") == raw_text.count("\r\n") + 1
    undone = new_text
    for a, b in [("<linear_stiffness>1234.5<", "<linear_stiffness>500<"),
                 ("<slack_length>0.031234567891<", "<slack_length>0.03075<"),
                 ("<slack_length>0.0301<", "<slack_length>0.029948600000000044<")]:
        assert undone.count(a) == 1
        undone = undone.replace(a, b)
    ins = re.search(r"\t*<transition_strain>0.05</transition_strain>\r\n", undone)
    undone = undone[:ins.start()] + undone[ins.end():]
    assert undone == raw_text
    m2 = O.read_osim(str(out))
    assert m2.ligaments["MCLd1"].linear_stiffness == 1234.5
    assert m2.ligaments["MCLd1"].slack_length == 0.031234567891
    assert m2.ligaments["ACLam2"].slack_length == 0.0301
    assert m2.ligaments["PCLpm3"].transition_strain == 0.05
    for n, lg in model.ligaments.items():
        if n not in vals:
            l2 = m2.ligaments[n]
            assert (l2.linear_stiffness, l2.slack_length, l2.transition_strain) == (
                lg.linear_stiffness, lg.slack_length, lg.transition_strain)
    # OpenSim reads the new values (via a stripped copy).  The oracle process loaded the stripped
    # copy of a file written by the same call, which must be byte-identical to this one.
    assert oracle["calibrated_file"].read_bytes() == out.read_bytes()
    g = oracle["calibrated"]
    assert g["MCLd1"]["linear_stiffness"] == 1234.5
    assert g["MCLd1"]["slack_length"] == 0.031234567891
    assert g["ACLam2"]["slack_length"] == 0.0301
    assert g["PCLpm3"]["transition_strain"] == 0.05
    assert g["PCLpm2"]["transition_strain"] == 0.06


def test_write_calibrated_rejects_bad_input(tmp_path):
    with pytest.raises(O.OsimError, match="'NOPE' found 0 times"):
        O.write_calibrated(LENHART, tmp_path / "x.osim", {"NOPE": {"slack_length": 0.03}})
    with pytest.raises(O.OsimError, match="not writable"):
        O.write_calibrated(LENHART, tmp_path / "x.osim", {"MCLd1": {"mass": 1.0}})
    with pytest.raises(O.OsimError, match="invalid value"):
        O.write_calibrated(LENHART, tmp_path / "x.osim", {"MCLd1": {"slack_length": -1.0}})
    with pytest.raises(O.OsimError, match="nan"):
        O.write_calibrated(LENHART, tmp_path / "x.osim", {"MCLd1": {"slack_length": math.nan}})
    with pytest.raises(O.OsimError, match="refuses to overwrite"):
        O.write_calibrated(LENHART, LENHART, {"MCLd1": {"slack_length": 0.03}})
    assert not (tmp_path / "x.osim").exists()
