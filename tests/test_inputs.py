"""Bad input gives a one-line error naming the file and field (exit 2 on the CLI), never a traceback."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import kneenlp
from kneenlp.base.conventions import load_vector
from kneenlp.base.errors import InputError
from kneenlp.base.resources import resource
from kneenlp.cli import main
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.protocol import Protocol
from kneenlp.model.knee import Knee
from kneenlp.model.knee_file import knee_file
from kneenlp.model.parameters import ParameterSet


@pytest.fixture()
def knee_copy(tmp_path):
    src = knee_file("synthetic").parent
    dst = tmp_path / "knee"
    shutil.copytree(src, dst)
    shutil.copy(src.parent.parent / "parameters" / "table1.toml", tmp_path / "table1.toml")
    text = (dst / "knee.toml").read_text().replace("../../parameters/table1.toml", "../table1.toml")
    (dst / "knee.toml").write_text(text)
    return dst / "knee.toml"


def run_cli(capsys, *argv):
    code = main(list(argv))
    err = capsys.readouterr().err.strip()
    return code, err


def test_unknown_protocol(capsys):
    code, err = run_cli(capsys, "simulate", "--protocol", "set9", "--no-plots")
    assert code == 2 and err.count("\n") == 0
    assert "unknown protocol 'set9'; known: " in err
    assert all(name in err for name in ("set1", "set2", "set3", "set4", "set4_high_flexion"))


def test_malformed_knee_toml(capsys, knee_copy):
    knee_copy.write_text(knee_copy.read_text() + "\n[ligaments.ACL\n")
    code, err = run_cli(capsys, "simulate", "--knee", str(knee_copy), "--no-plots")
    assert code == 2 and "malformed TOML" in err and str(knee_copy) in err and "\n" not in err


def test_missing_and_broken_mesh(knee_copy):
    (knee_copy.parent / "meshes" / "tibia_medial.stl").unlink()
    with pytest.raises(InputError, match=r"contact\.medial\.tibia: mesh file not found"):
        Knee.load(knee_copy)
    (knee_copy.parent / "meshes" / "tibia_medial.stl").write_bytes(b"solid junk\nthis is not an stl\n")
    with pytest.raises(InputError, match=r"contact\.medial\.tibia"):
        Knee.load(knee_copy)


def test_bad_attachment_field(knee_copy):
    knee_copy.write_text(knee_copy.read_text().replace("femur = [-3.0, 1.0, 7.0]", 'femur = [-3.0, "x", 7.0]'))
    with pytest.raises(InputError, match=r"ligaments\.ACL\.femur: expected a number"):
        Knee.load(knee_copy)


def test_unknown_ligament_and_units_in_parameter_set(tmp_path, knee_copy):
    bad = tmp_path / "p.toml"
    text = (knee_copy.parent.parent / "table1.toml").read_text()
    bad.write_text(text.replace("[ligaments.ACL]", "[ligaments.ACLx]"))
    with pytest.raises(InputError, match="unknown ligament 'ACLx'; known: ACL, PCL, MCL, LCL"):
        Knee.load(knee_copy, parameters=bad)
    bad.write_text(text.replace('ref_strain = "%"', 'ref_strain = "fraction"'))
    with pytest.raises(InputError, match=r"units\.ref_strain: unit 'fraction' not accepted"):
        ParameterSet.load(bad)
    # a misnamed property is named as unknown, not as the property it should have been
    bad.write_text(text.replace("k = 10000.0", "stiffness = 10000.0", 1))
    with pytest.raises(InputError, match=r"ligaments\.ACL\.stiffness: unknown key 'stiffness'; known: k, ref_strain"):
        ParameterSet.load(bad)


def test_protocol_errors(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text('[[cases]]\ndirection = "sideways"\nmagnitude = [1.0]\nflexion = [0.0]\n')
    with pytest.raises(InputError, match="unknown load direction 'sideways'"):
        Protocol.load(p)
    p.write_text('[[cases]]\ndirection = "anterior"\nmagnitude = [-5.0]\nflexion = [0.0]\n')
    with pytest.raises(InputError, match="magnitudes must be > 0"):
        Protocol.load(p)


def _measured_csv(tmp_path) -> Path:
    from kneenlp import simulate

    res = simulate(kneenlp.Knee.named("synthetic"), "set1")
    path = tmp_path / "m.csv"
    res.measured("uniform:0.5", seed=1).to_csv(path, index=False)
    return path


def test_measured_csv_errors(tmp_path):
    path = _measured_csv(tmp_path)
    data = read_measured(path)
    assert len(data) == 7 and data.protocol == "set1"
    text = path.read_text()
    lines = text.splitlines()
    cols = lines[0].split(",")
    j = cols.index("anterior_translation_mm")
    row = lines[2].split(",")
    row[j] = "nan"
    path.write_text("\n".join([lines[0], lines[1], ",".join(row), *lines[3:]]))
    nan = r"anterior_translation_mm: row 3 \(trial .*\): value nan \(or empty\) is not a finite number"
    with pytest.raises(InputError, match=nan):
        read_measured(path)
    path.write_text(text.replace("anterior_translation_mm", "anterior_translation_m"))
    with pytest.raises(InputError, match="wrong unit; expected anterior_translation_mm"):
        read_measured(path)
    path.write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="missing column"):
        read_measured(path)
    with pytest.raises(InputError, match="file not found"):
        read_measured(tmp_path / "nope.csv")


@pytest.mark.parametrize("column", ["internal_rotation_deg", "varus_rotation_deg"])
def test_one_rotation_in_radians_is_named(tmp_path, column):
    """S192803 with one rotation column in radians, the other in degrees (the check of both in
    radians does not see it): the column is named; the shipped data pass."""
    import pandas as pd

    src = resource("datasets", "s192803_laxity.csv")
    read_measured(src)
    df = pd.read_csv(src)
    df[column] = np.radians(df[column])
    df.to_csv(tmp_path / "laxity.csv", index=False)
    with pytest.raises(InputError, match=rf"laxity.csv: {column}: never beyond .* radians in a _deg column"):
        read_measured(tmp_path / "laxity.csv")


def test_data_checked_against_protocol(tmp_path):
    path = _measured_csv(tmp_path)
    data = read_measured(path)
    small = Protocol.from_dict({"name": "small", "cases": [{"direction": "none", "flexion": [30.0]}]})
    with pytest.raises(InputError, match="trial 'anterior_134N_flex30' is not in protocol 'small'"):
        data.check_protocol(small)
    data.trials.pop()
    with pytest.raises(InputError, match="missing trials of protocol 'set1': valgus_10Nm_flex0"):
        data.check_protocol(Protocol.load("set1"))


def test_cli_process_exit_code_and_no_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "kneenlp.cli", "simulate", "--knee", str(tmp_path / "none.toml")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.strip().count("\n") == 0
    assert "file not found" in proc.stderr


def test_knee_in_scanner_coordinates_loads_to_the_same_model(tmp_path):
    """The default knee moved by a rigid transform into 'scanner' coordinates, with coordinates =
    'scan': the ISB frame is rebuilt from the landmarks and the model is the same."""
    import numpy as np
    import trimesh

    from kneenlp.experiment.kneemodel import KneeModel

    rot = trimesh.transformations.rotation_matrix(0.4, [0.3, 1.0, 0.2])[:3, :3]
    shift = np.array([120.0, -35.0, 410.0])

    def move(p):
        return (rot @ np.asarray(p, float).T).T + shift

    src = knee_file("synthetic").parent
    text = (src / "knee.toml").read_text()
    import re

    def repl(m):
        vals = move([float(v) for v in m.group(1).split(",")])
        return "[" + ", ".join(f"{v:.12f}" for v in vals) + "]"

    text = re.sub(r"\[(-?[\d.]+, -?[\d.]+, -?[\d.]+)\]", repl, text)
    # the default knee's tibial landmarks are given in the tibial frame = femoral frame at reference
    text = text.replace('units = "mm"', 'units = "mm"\ncoordinates = "scan"')
    text = text.replace("../../parameters/table1.toml", str(src.parent.parent / "parameters" / "table1.toml"))
    (tmp_path / "meshes").mkdir()
    for f in (src / "meshes").glob("*.stl"):
        mesh = trimesh.load(f)
        mesh.vertices = move(mesh.vertices)
        mesh.export(tmp_path / "meshes" / f.name)
    (tmp_path / "knee.toml").write_text(text)
    scan = Knee.load(tmp_path / "knee.toml")
    ref = Knee.named("synthetic")
    m1, m2 = KneeModel.of(ref), KneeModel.of(scan)
    q = np.array([0.01, 0.05, 0.0005, -0.001, 0.0003])
    load = load_vector({"anterior_force": 50.0, "varus_moment": 2.0, "internal_moment": 0.5})
    r1 = np.asarray(m1.evaluate(q, m1.theta(), load, 0.3)).ravel()
    r2 = np.asarray(m2.evaluate(q, m2.theta(), load, 0.3)).ravel()
    assert np.allclose(r1, r2, rtol=1e-5, atol=1e-5), (r1, r2)
    assert np.allclose(scan.compartments["medial"].centre, ref.compartments["medial"].centre,
                       atol=1e-8)


@pytest.fixture()
def default_copy(tmp_path):
    """The default (Lenhart, metre) knee file beside its resources, to edit one field."""
    src = knee_file("default")
    dst = src.parent / f"_test_{tmp_path.name}.toml"  # beside the original: its relative mesh paths hold
    yield src, dst
    dst.unlink(missing_ok=True)


@pytest.mark.parametrize("old, new, field, needle", [
    ("gate = 1e-5", "gate = 0.01", "contact.gate", "10 mm in this file's unit ('m')"),
    ("femur_offset = 0.002", "femur_offset = 2.0", "contact.femur_offset", "2000 mm"),
    ("grid_spacing = 5e-4", "grid_spacing = 0.5", "contact.grid_spacing", "500 mm"),
    ("grid_spacing = 5e-4", "grid_spacing = 1e-6", "contact.grid_spacing", "0.001 mm"),
    ("grid_spacing = 5e-4", "grid_spacing = 5e-5", "contact.grid_spacing", "GB"),
])
def test_contact_lengths_in_the_wrong_unit_or_too_fine(default_copy, old, new, field, needle):
    """A contact length written in another unit, or a distance-field grid too fine for memory, is
    a one-line error naming the field, before any work (unchecked: a 1 um grid tried to allocate
    1 PiB; femur_offset = 2.0 in a metre knee failed trials later with 'residual 867')."""
    src, dst = default_copy
    text = src.read_text()
    assert old in text
    dst.write_text(text.replace(old, new))
    with pytest.raises(InputError, match=re.escape(needle)) as err:
        Knee.load(dst)
    assert err.value.field == field and "\n" not in str(err.value)


FEMUR_LINE = 'femur = "../lenhart2015/opensim/lenhart2015-R-femur-subchondral-bone.stl"'
TIBIA_LINE = 'tibia = "../lenhart2015/opensim/lenhart2015-R-tibia-cartilage.stl"'


@pytest.mark.parametrize("swap, needle", [
    ({FEMUR_LINE: FEMUR_LINE.replace("femur-subchondral-bone", "tibia-cartilage"),
      TIBIA_LINE: TIBIA_LINE.replace("tibia-cartilage", "femur-subchondral-bone")}, "meshes swapped?"),
    ({TIBIA_LINE: TIBIA_LINE.replace("tibia-cartilage", "femur-subchondral-bone")}, "the same file given twice?"),
])
def test_swapped_or_repeated_meshes(default_copy, swap, needle):
    """Femoral and tibial meshes swapped, or the femur given twice (unchecked: exit 3, or silently
    wrong): one line naming contact.tibia and the slip."""
    src, dst = default_copy
    text = src.read_text()
    for old, new in swap.items():
        assert old in text
        text = text.replace(old, new)
    dst.write_text(text)
    with pytest.raises(InputError, match=re.escape(needle)) as err:
        Knee.load(dst)
    assert err.value.field == "contact.tibia"


@pytest.mark.parametrize("shift", ["anterior", "distal"])
def test_tibia_out_of_reach(default_copy, tmp_path, shift):
    """A tibia placed 80 mm anterior or 40 mm distal of the femur (unchecked: exit 3, "no femoral
    surface within reach"): one line naming contact.tibia and what to check."""
    import trimesh

    src, dst = default_copy
    mesh = trimesh.load(src.parent.parent / "lenhart2015" / "opensim" / "lenhart2015-R-tibia-cartilage.stl")
    mesh.apply_translation([0.08, 0, 0] if shift == "anterior" else [0, -0.04, 0])
    moved = tmp_path / "tibia.stl"
    mesh.export(moved)
    dst.write_text(src.read_text().replace(TIBIA_LINE, f'tibia = "{moved.as_posix()}"'))
    with pytest.raises(InputError, match="within reach") as err:
        Knee.load(dst)
    assert err.value.field == "contact.tibia"


def test_one_tibial_mesh_in_the_other_unit(knee_copy):
    """One plateau's mesh in metres in a millimetre knee (unchecked: 17 mm/deg off, exit 0, since
    the knee's size check spans both plateaus): caught on that mesh, before any work."""
    import trimesh

    path = knee_copy.parent / "meshes" / "tibia_medial.stl"
    mesh = trimesh.load(path)
    mesh.apply_scale(1e-3)
    mesh.export(path)
    with pytest.raises(InputError, match=r"spans 0\.0\d+ mm with units = 'mm'.*in m\?") as err:
        Knee.load(knee_copy)
    assert err.value.field == "contact.medial.tibia"


@pytest.mark.parametrize("knee", ["synthetic", "default"])
def test_declared_side_contradicted_by_the_geometry(knee_copy, default_copy, knee):
    """A right knee declared left (unchecked: 16.6 mm/deg off, exit 0): read as a left knee, its
    collateral ligaments change sides; one line naming `side` and the fix."""
    path = knee_copy if knee == "synthetic" else default_copy[1]
    text = (knee_copy if knee == "synthetic" else default_copy[0]).read_text()
    assert 'side = "right"' in text
    path.write_text(text.replace('side = "right"', 'side = "left"'))
    with pytest.raises(InputError, match=re.escape("is it a right knee? (set side = 'right')")) as err:
        Knee.load(path)
    assert err.value.field == "side" and "collateral" in str(err.value)


def test_named_plateaus_on_the_wrong_sides(knee_copy):
    """[contact.medial] and [contact.lateral] naming each other's meshes contradict the side the
    ligaments give: the error says which evidence disagrees."""
    text = knee_copy.read_text()
    medial, lateral = "meshes/tibia_medial.stl", "meshes/tibia_lateral.stl"
    swapped = text.replace(medial, "@").replace(lateral, medial).replace("@", lateral)
    knee_copy.write_text(swapped)
    with pytest.raises(InputError, match=re.escape("lateral plateau ([contact.lateral]) lies medial")) as err:
        Knee.load(knee_copy)
    assert err.value.field == "side"


def test_flexion_beyond_the_represented_surface(tmp_path, capsys):
    """A trial at 115 deg on a mesh knee whose femoral surface is represented to 100 deg (unchecked:
    diagnose failed after 300 s with a numba dispatcher error): one line naming the trial, exit 2,
    from simulate and from a fit's data alike."""
    protocol = tmp_path / "p115.toml"
    protocol.write_text('name = "p115"\n[[cases]]\ndirection = "anterior"\nmagnitude = [134.0]\n'
                        'flexion = [30.0, 115.0]\n')
    code, err = run_cli(capsys, "simulate", "--protocol", str(protocol), "--out", str(tmp_path / "out"))
    assert code == 2 and "anterior_134N_flex115" in err and "between -5 and 100 deg" in err
    assert not (tmp_path / "out").exists()
    synthetic = kneenlp.simulate(Knee.named("synthetic"), Protocol.load(protocol))  # spheres: any flexion
    data = synthetic.measured("uniform:0.5", 0)
    csv = tmp_path / "d.csv"
    data.to_csv(csv, index=False)
    from kneenlp.estimation.identify import identify

    with pytest.raises(InputError, match="115 deg flexion") as err:
        identify(Knee.default(), read_measured(csv))
    assert err.value.field == "flexion"


@pytest.mark.parametrize("depth_mm, inside", [(8.0, True), (1.0, False)])
def test_attachment_inside_bone(default_copy, depth_mm, inside):
    """A femoral attachment moved into the femur, ``depth_mm`` above its most distal articular point
    (unchecked: accepted silently): deeper than the tolerance it is one line naming the field and the
    mesh; 1 mm inside (as real attachments on a segmented surface may lie) it is accepted."""
    import numpy as np
    import trimesh

    src, dst = default_copy
    femur = trimesh.load(src.parent.parent / "lenhart2015" / "opensim" / "lenhart2015-R-femur-subchondral-bone.stl")
    distal = femur.vertices[np.argmin(femur.vertices[:, 1])]  # scan Y points to the hip
    point = distal + np.array([0.0, depth_mm * 1e-3, 0.0])
    text = src.read_text()
    old = "femur = [-0.001151, -0.000054, 0.005299]"
    assert old in text
    dst.write_text(text.replace(old, f"femur = [{point[0]:.6f}, {point[1]:.6f}, {point[2]:.6f}]"))
    if not inside:
        Knee.load(dst)
        return
    with pytest.raises(InputError, match=r"femoral attachment lies 8\.\d mm inside the femoral mesh") as err:
        Knee.load(dst)
    assert err.value.field == "ligaments.ACL.femur" and "\n" not in str(err.value)


HIP_LINE = "hip_center = [0.005551, 0.374181, 0.001171]"


@pytest.mark.parametrize("new, field, needle", [
    ("hip_center = [0.005551, 0.05, 0.001171]", "landmarks.hip_center", "the hip center at the knee?"),
    ("hip_center = [0.005551, 0.0, 0.374]", "landmarks.hip_center", "from the flexion axis"),
    ("", "landmarks.hip_center", "a knee in scan coordinates needs the hip centre"),
    (HIP_LINE + "\nmedial_epicondyle = [0.0, 3.0, -40.0]", "landmarks.medial_epicondyle", "a point in mm with units"),
])
def test_landmark_slips(default_copy, new, field, needle):
    """The hip centre at the knee or beside it, a scan-coordinate knee without it, a landmark in
    the other unit (unchecked: silently accepted): one line naming the landmark."""
    src, dst = default_copy
    text = src.read_text()
    assert HIP_LINE in text
    dst.write_text(text.replace(HIP_LINE, new))
    with pytest.raises(InputError, match=re.escape(needle)) as err:
        Knee.load(dst)
    assert err.value.field == field and "\n" not in str(err.value)


@pytest.mark.parametrize("old, new, field", [
    ("tibial_tuberosity = [32.0, -45.0, 3.0]", "tibial_tuberosity = [0.032, -0.045, 0.003]",
     "landmarks.tibial_tuberosity"),
    ("femur = [-3.0, 1.0, 7.0]", "femur = [-0.003, 0.001, 0.007]", "ligaments.ACL.femur"),
])
def test_point_in_metres_in_a_millimetre_knee(knee_copy, old, new, field):
    """One point written in metres in a millimetre knee lands at the frame's origin: named."""
    text = knee_copy.read_text()
    assert old in text
    knee_copy.write_text(text.replace(old, new))
    with pytest.raises(InputError, match=re.escape("a point in m with units = 'mm'?")) as err:
        Knee.load(knee_copy)
    assert err.value.field == field


def test_negative_femur_offset_in_import_osim(tmp_path, capsys):
    """import-osim --femur-offset -2 (unchecked: accepted): exit 2 naming the option, nothing written."""
    from kneenlp.base.resources import resource

    data = resource("knees", "lenhart2015", "opensim")
    out = tmp_path / "imp"
    code, err = run_cli(capsys, "import-osim", str(data / "lenhart2015.osim"), "--out", str(out), "--femur-mesh",
                        str(data / "lenhart2015-R-femur-subchondral-bone.stl"), "--femur-offset", "-2")
    assert code == 2 and "--femur-offset: -2 mm" in err and "inside the bone" in err
    assert not out.exists() or not any(out.iterdir())


LENHART_DIR = knee_file("default").parent.parent / "lenhart2015" / "opensim"


def _femur():
    import trimesh

    return trimesh.load(LENHART_DIR / "lenhart2015-R-femur-subchondral-bone.stl")


def _tibia():
    import trimesh

    return trimesh.load(LENHART_DIR / "lenhart2015-R-tibia-cartilage.stl")


def _inverted(mesh):
    mesh.invert()
    return mesh


def _moved(mesh, shift):
    mesh.apply_translation(shift)
    return mesh


def _decimated(mesh, faces):
    return mesh.simplify_quadric_decimation(face_count=faces)


def _degenerate(mesh):
    import numpy as np
    import trimesh

    faces = np.column_stack([mesh.faces[:, 0], mesh.faces[:, 0], mesh.faces[:, 1]])
    return trimesh.Trimesh(mesh.vertices, faces, process=False)


def _one_triangle(_mesh):
    import trimesh

    return trimesh.Trimesh([[0, -0.02, -0.03], [0.03, -0.02, 0.03], [-0.03, -0.02, 0.03]], [[0, 1, 2]])


@pytest.mark.parametrize("bone, change, field, needle", [
    ("femur", _inverted, "contact.femur", "the femoral mesh is inside-out"),
    ("tibia", lambda m: _moved(m, [0, 0.008, 0]), "contact.tibia", "lies 8.21 mm inside the femoral articular surface"),
    ("tibia", _one_triangle, "contact.tibia", "1 faces, 3 vertices"),
    ("femur", lambda m: _decimated(m, 10), "contact.femur", "too coarse to represent the condyles"),
    ("femur", _degenerate, "contact.femur", "19229 of 19229 faces are degenerate"),
])
def test_meshes_that_failed_without_naming_the_cause(default_copy, tmp_path, bone, change, field, needle):
    """Inverted femoral normals, a tibia 8 mm inside the femur at the reference pose, a one-triangle
    tibia, a 10-face femur, all-degenerate femoral faces (unchecked: exit 1 with "residual 867/inf",
    an unhelpful cylinder-fit error or exit 3): one line naming the mesh's field and the slip."""
    src, dst = default_copy
    mesh = change(_femur() if bone == "femur" else _tibia())
    path = tmp_path / f"{bone}.stl"
    mesh.export(path)
    line = FEMUR_LINE if bone == "femur" else TIBIA_LINE
    dst.write_text(src.read_text().replace(line, f'{bone} = "{path.as_posix()}"'))
    with pytest.raises(InputError, match=re.escape(needle)) as err:
        Knee.load(dst)
    assert err.value.field == field and "\n" not in str(err.value)


def test_truncated_binary_stl(knee_copy, capsys):
    """A binary STL cut short (unchecked: blamed on "No module named 'charset_normalizer'"): exit 2,
    the file named truncated with the sizes."""
    path = knee_copy.parent / "meshes" / "tibia_medial.stl"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    code, err = run_cli(capsys, "simulate", "--knee", str(knee_copy), "--protocol", "set1", "--no-plots")
    assert code == 2 and "contact.medial.tibia: mesh tibia_medial.stl is truncated" in err
    assert f"the file has {len(data) // 2} bytes" in err and "\n" not in err


def test_huge_study_refused_early(tmp_path, capsys):
    """study --samples 1000000 (unchecked: no early message): refused at once with its estimated time
    and disk, naming --samples and --yes; nothing written.  The estimate scales with the study."""
    import argparse

    from kneenlp.cli.inputs import study_size as _study_size

    out = tmp_path / "st"
    code, err = run_cli(capsys, "study", "--knee", "synthetic", "--samples", "1000000", "--workers", "2",
                        "--out", str(out))
    assert code == 2 and "--samples: 4 sets x 1,000,000 samples = 4,000,000 fits" in err and "--yes" in err
    assert "sample files (16.4 GB)" in err and "\n" not in err and not out.exists()
    args = argparse.Namespace(sets=["set1"], samples=100, workers=1, scheduler=None, dask=False, knee="synthetic",
                              yes=False)
    small = _study_size(args)
    assert "100 fits: about 5 min on 1 worker" in small
    args.knee = "default"
    assert "about 1.67 h on 1 worker (~60 s a fit on a mesh knee)" in _study_size(args)
    args.samples, args.yes = 20_000, True
    assert "20,000 fits" in _study_size(args)


def test_fine_mesh_decimated_to_the_contact_resolution(tmp_path, monkeypatch):
    """The decimation path on a moderately large mesh: the implant's femoral component subdivided
    once (46,816 faces) with the limit lowered to 20,000 is read by the lean binary reader (the same
    triangles as trimesh's), decimated below the limit within 20 um of the surface, and the knee
    report says so; above the read limit the file is refused unread, naming it."""
    import numpy as np
    import trimesh

    import kneenlp.geometry.decimate as dec
    import kneenlp.model.knee_file as knee_module
    from kneenlp.geometry.distance import MeshDistance

    src = knee_file("implant").parent
    shutil.copytree(src, tmp_path / "implant")
    text = (src / "knee.toml").read_text().replace("../../parameters/table1.toml",
                                                   str(src.parent.parent / "parameters" / "table1.toml"))
    (tmp_path / "implant" / "knee.toml").write_text(text)
    original = trimesh.load(src / "meshes" / "femur_component.stl")
    fine = original.subdivide()
    path = tmp_path / "implant" / "meshes" / "femur_component.stl"
    fine.export(path)
    vertices, faces = dec.read_binary_stl(path, len(fine.faces))
    assert len(faces) == 46816 and np.allclose(np.sort(vertices[faces].reshape(-1, 9), axis=0),
                                               np.sort(np.asarray(fine.triangles, np.float32).reshape(-1, 9),
                                                       axis=0))
    monkeypatch.setattr(dec, "MAX_MESH_FACES", 20_000)
    monkeypatch.setattr(knee_module, "MAX_MESH_FACES", 20_000)
    knee = Knee.load(tmp_path / "implant" / "knee.toml")
    femur = knee.femur.mesh
    assert len(femur.faces) <= 20_000
    assert "contact.femur (meshes/femur_component.stl): 46,816 faces decimated to" in "\n".join(knee.notes)
    gap = np.abs(MeshDistance(original)(femur.vertices * 1e3)[0])  # the knee is in m, the file in mm
    assert gap.max() < 0.02, gap.max()
    monkeypatch.setattr(knee_module, "MAX_READ_FACES", 40_000)
    with pytest.raises(InputError, match="announces 46,816 triangles, more than the 40,000") as err:
        Knee.load(tmp_path / "implant" / "knee.toml")
    assert err.value.field == "contact.femur"


def test_landmarks_of_the_users_own_and_the_hip_in_metres(knee_copy):
    """A landmark of the user's own name is kept wherever it lies on the limb (not held to the knee's
    150 mm); the hip centre written in m in a mm knee is named as that unit slip."""
    text = knee_copy.read_text()
    anchor = "hip_center = [0.0, 420.0, 0.0]"
    assert anchor in text
    knee_copy.write_text(text.replace(anchor, anchor + "\nfemoral_head_marker = [10.0, 400.0, -30.0]"))
    assert "femoral_head_marker" in Knee.load(knee_copy).landmarks
    knee_copy.write_text(text.replace(anchor, "hip_center = [0.0, 0.42, 0.0]"))
    with pytest.raises(InputError, match=re.escape("a point in m with units = 'mm'?")) as err:
        Knee.load(knee_copy)
    assert err.value.field == "landmarks.hip_center"


def test_api_values_pass_the_range_check_of_file_values():
    """A value given through the API (simulate, predict, a fit's start) passes the same range check
    as a parameter file's: a negative stiffness or a NaN is an InputError naming the parameter."""
    import math

    import kneenlp
    from kneenlp.base.errors import InputError

    knee = kneenlp.Knee.named("synthetic")
    for value in (-5.0, math.nan, 2e5):
        with pytest.raises(InputError, match=r"ACL\.k = .* outside the range of a stiffness"):
            kneenlp.simulate(knee, "set1", parameters={"ACL.k": value})


def test_forces_in_kilonewtons_are_named(tmp_path):
    """Forces are checked in N as moments are in N m: a drawer of 0.134 'N' that moved the tibia
    millimetres from its unloaded pose is a force in kN (exit 2 naming the column); in N it reads."""
    from kneenlp.experiment.measured import read_measured

    df = kneenlp.simulate(kneenlp.Knee.named("synthetic"), "set3").measured()
    df.to_csv(tmp_path / "n.csv", index=False)
    read_measured(tmp_path / "n.csv")
    df["anterior_force_N"] = df["anterior_force_N"] / 1000
    df.to_csv(tmp_path / "kn.csv", index=False)
    with pytest.raises(kneenlp.InputError, match="kN in the _N columns") as err:
        read_measured(tmp_path / "kn.csv")
    assert err.value.field == "anterior_force_N"
    # the real experiment's loads are never exactly zero and its flexions scatter: the pull of each
    # load along its displacement still names the unit, forces alone or every load in kN
    import pandas as pd

    from kneenlp.base.resources import resource

    real = pd.read_csv(resource("datasets", "s192803_laxity.csv"))
    for columns, field in ((["anterior_force_N", "lateral_force_N", "proximal_force_N"], "anterior_force_N"),
                           ([c for c in real.columns if c.endswith(("_N", "_Nm"))], None)):
        slipped = real.copy()
        slipped[columns] = slipped[columns] / 1000
        slipped.to_csv(tmp_path / "real_kn.csv", index=False)
        with pytest.raises(kneenlp.InputError, match=r"along itself.*kN in the _N columns") as err:
            read_measured(tmp_path / "real_kn.csv")
        assert field is None or err.value.field == field


def test_an_error_about_a_staged_file_names_where_it_was_to_go(tmp_path):
    """A command writes its outputs into a staging folder first and reads some of them back (an
    exported Abaqus file's expressions): an error there names the file as it would have been in
    ``--out``, never the staging folder that is deleted with the failure; nothing is written."""
    from kneenlp.base.atomic import staged_directory
    from kneenlp.base.errors import InputError

    out = tmp_path / "out"
    with pytest.raises(InputError) as err:
        with staged_directory(out) as stage:
            (stage.path / "LIG.inp").write_text("*Parameter\nK = 1 +\n")
            raise InputError(f"cannot evaluate 'K = 1 +' in {stage.path / 'LIG.inp'}",
                             source=str(stage.path / "LIG.inp"), field="K")
    staged = list(out.iterdir()) if out.exists() else []
    assert err.value.source == str(out / "LIG.inp") and err.value.field == "K"
    assert str(out / "LIG.inp") in err.value.message and ".kneenlp-tmp" not in str(err.value)
    assert staged == []


@pytest.mark.parametrize("table, value, shown", [("[popliteus]\ncandidate", '"yes"', "'yes'"),
                                                 ("[meniscal_rim]\ncandidate", "1", "1")])
def test_a_flag_is_true_or_false(knee_copy, table, value, shown):
    """pydantic would read "yes" or 1 as true: a flag of a file is a TOML boolean or an error."""
    knee_copy.write_text(f"{knee_copy.read_text()}\n{table} = {value}\n")
    field = table.strip("[").replace("]\n", ".")
    with pytest.raises(InputError, match=rf"{re.escape(field)}: expected true or false, got {re.escape(shown)}"):
        Knee.load(knee_copy)


def test_an_experiment_files_flag_is_true_or_false(tmp_path):
    from kneenlp.experiment.kind import Experiment
    path = tmp_path / "robot.toml"
    path.write_text('name = "robot"\nlaboratory = "false"\n')
    with pytest.raises(InputError, match=r"robot\.toml: laboratory: expected true or false, got 'false'"):
        Experiment.load(path)
