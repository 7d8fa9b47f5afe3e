"""Fuzz suite, knee section: a researcher's own knee files load correctly or say why.

Hand-made cases (one per knee-file slip) run the command line in this process on copies
of shipped mesh knees: the implant knee (millimetres, femoral frame), the default knee (metres,
scan coordinates, the Lenhart meshes beside it) and s192803 (its bones); the mutations also take the synthetic
knee (explicit spheres).  Each must exit 2 with one stderr line
naming the knee file (or the option) and the field, the JSON error object on stdout with ``--json``,
and nothing written to ``--out``.  Hypothesis then mutates the shipped knee files as a user would
slip: a field deleted, a number scaled by 1e-3 or 1e3 (a unit slip), two strings swapped, a mesh
swapped for another or scaled; each mutated knee is loaded (``Knee.load``) and must load or raise a
one-line input error naming the file, never another exception, within a time and memory limit
(:data:`SECONDS_PER_CASE`, :data:`BYTES_PER_CASE`).  Examples: :data:`EXAMPLES` a test, the same
every run (``KNEENLP_FUZZ_EXAMPLES=1000`` for a deeper random search).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
import tomllib
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kneenlp.base.errors import InputError
from kneenlp.cli import main
from kneenlp.model.knee import Knee
from kneenlp.model.knee_file import knee_file

SHIPPED = knee_file("default").parent.parent
LENHART = SHIPPED / "lenhart2015" / "opensim"
PARAMETERS = SHIPPED.parent / "parameters" / "table1.toml"
#: Time and memory (traced allocations, NumPy's included) one mutated knee may take to load.
SECONDS_PER_CASE = 30.0
BYTES_PER_CASE = 2e9
DEEP = os.environ.get("KNEENLP_FUZZ_EXAMPLES")
EXAMPLES = int(DEEP or 30)
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=not DEEP,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """``implant/`` (knee.toml, meshes/) and ``default/`` (knee.toml beside femur.stl and tibia.stl)
    with ``table1.toml``: copies whose relative paths hold."""
    d = tmp_path_factory.mktemp("kneefuzz")
    shutil.copy(PARAMETERS, d / "table1.toml")
    shutil.copytree(SHIPPED / "implant", d / "implant")
    shutil.copytree(SHIPPED / "synthetic", d / "synthetic")
    text = (d / "synthetic" / "knee.toml").read_text()
    (d / "synthetic" / "knee.toml").write_text(text.replace("../../parameters/table1.toml", "../table1.toml"))
    (d / "default").mkdir()
    shutil.copy(LENHART / "lenhart2015-R-femur-subchondral-bone.stl", d / "default" / "femur.stl")
    shutil.copy(LENHART / "lenhart2015-R-tibia-cartilage.stl", d / "default" / "tibia.stl")
    text = (SHIPPED / "default" / "knee.toml").read_text()
    text = text.replace("../lenhart2015/opensim/lenhart2015-R-femur-subchondral-bone.stl", "femur.stl")
    text = text.replace("../lenhart2015/opensim/lenhart2015-R-tibia-cartilage.stl", "tibia.stl")
    (d / "default" / "knee.toml").write_text(text.replace("../../parameters/table1.toml", "../table1.toml"))
    text = (d / "implant" / "knee.toml").read_text()
    (d / "implant" / "knee.toml").write_text(text.replace("../../parameters/table1.toml", "../table1.toml"))
    shutil.copytree(SHIPPED / "s192803", d / "s192803")  # with its [bones]
    return d


# ------------------------------------------------------------------ setups of the hand-made cases
def edit(knee: str, old: str, new: str) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        path = d / knee / "knee.toml"
        text = path.read_text()
        assert old in text, (knee, old)
        path.write_text(text.replace(old, new, 1))
    return setup


def mesh(rel: str, change: Callable[[trimesh.Trimesh], trimesh.Trimesh]) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        change(trimesh.load(d / rel, force="mesh")).export(d / rel)
    return setup


def moved(shift) -> Callable[[trimesh.Trimesh], trimesh.Trimesh]:
    def change(m: trimesh.Trimesh) -> trimesh.Trimesh:
        m.apply_translation(shift)
        return m
    return change


def scaled(factor: float) -> Callable[[trimesh.Trimesh], trimesh.Trimesh]:
    def change(m: trimesh.Trimesh) -> trimesh.Trimesh:
        m.apply_scale(factor)
        return m
    return change


def inverted(m: trimesh.Trimesh) -> trimesh.Trimesh:
    m.invert()
    return m


def one_triangle(m: trimesh.Trimesh) -> trimesh.Trimesh:
    """One triangle spanning the mesh's top (a plateau-sized placeholder)."""
    (x0, _, z0), (x1, y1, z1) = m.bounds
    return trimesh.Trimesh([[x0, y1, z0], [x1, y1, z0], [(x0 + x1) / 2, y1, z1]], [[0, 1, 2]])


def coarse(m: trimesh.Trimesh) -> trimesh.Trimesh:
    return m.simplify_quadric_decimation(face_count=10)


def degenerate(m: trimesh.Trimesh) -> trimesh.Trimesh:
    faces = np.column_stack([m.faces[:, 0], m.faces[:, 0], m.faces[:, 1]])
    return trimesh.Trimesh(m.vertices, faces, process=False)


def truncated(rel: str) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        data = (d / rel).read_bytes()
        (d / rel).write_bytes(data[: len(data) // 2])
    return setup


def swap_files(a: str, b: str) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        tmp = d / "swap.tmp"
        (d / a).rename(tmp)
        (d / b).rename(d / a)
        tmp.rename(d / b)
    return setup


@dataclass
class Case:
    id: str
    setup: Callable[[Path], None] | None
    field: str
    needle: str
    knee: str = "implant"
    argv: str | None = None  # a whole command line instead of simulating the knee


DEF_HIP = "hip_center = [0.005551, 0.374181, 0.001171]"
DEF_ACL = "femur = [-0.001151, -0.000054, 0.005299]"
IMP_ACL = "femur = [-3.0, 1.0, 7.0]"
CASES = [
    # landmarks (unchecked: silently accepted)
    Case("hip-at-the-knee", edit("default", DEF_HIP, "hip_center = [0.005551, 0.03, 0.001171]"),
         "landmarks.hip_center", "at the knee?", "default"),
    Case("hip-lateral", edit("default", DEF_HIP, "hip_center = [0.005551, 0.0, 0.374]"),
         "landmarks.hip_center", "from the flexion axis", "default"),
    Case("scan-knee-without-hip", edit("default", DEF_HIP, ""), "landmarks.hip_center",
         "needs the hip centre", "default"),
    Case("landmark-in-mm-in-a-metre-knee", edit("default", "tibial_tuberosity = [0.034875, -0.048184, 0.013353]",
                                                "tibial_tuberosity = [34.875, -48.184, 13.353]"),
         "landmarks.tibial_tuberosity", "in mm with units = 'm'", "default"),
    Case("landmark-in-m-in-a-mm-knee", edit("implant", "tibial_tuberosity = [32.0, -45.0, 3.0]",
                                            "tibial_tuberosity = [0.032, -0.045, 0.003]"),
         "landmarks.tibial_tuberosity", "a point in m"),
    Case("attachment-in-m-in-a-mm-knee", edit("implant", IMP_ACL, "femur = [-0.003, 0.001, 0.007]"),
         "ligaments.ACL.femur", "a point in m"),
    Case("attachment-inside-the-femur", edit("default", DEF_ACL, "femur = [0.0140, -0.0129, 0.0264]"),
         "ligaments.ACL.femur", "inside the femoral mesh", "default"),
    Case("attachment-inside-a-condyle", edit("s192803", "femur = [\n    -6.98181,\n    -2.259463,\n    -8.263589,\n]",
                                             "femur = [6.34, 0.90, 20.47]"),  # the medial condyle's centre
         "ligaments.ACLam.bundles[0].femur", "inside the femoral bone", "s192803"),
    Case("side-declared-wrong", edit("implant", 'side = "right"', 'side = "left"'), "side", "is it a right knee?"),
    # contact lengths in another unit
    Case("gate-in-mm-in-a-metre-knee", edit("default", "gate = 1e-5", "gate = 0.01"), "contact.gate",
         "10 mm in this file's unit", "default"),
    Case("femur-offset-in-mm-in-a-metre-knee", edit("default", "femur_offset = 0.002", "femur_offset = 2.0"),
         "contact.femur_offset", "2000 mm", "default"),
    Case("grid-of-one-micrometre", edit("default", "grid_spacing = 5e-4", "grid_spacing = 1e-6"),
         "contact.grid_spacing", "0.001 mm", "default"),
    # meshes
    Case("femur-inside-out", mesh("implant/meshes/femur_component.stl", inverted), "contact.femur", "inside-out"),
    Case("tibia-8mm-inside-the-femur", mesh("default/tibia.stl", moved([0, 0.008, 0])), "contact.tibia",
         "mm inside the femoral articular surface", "default"),
    Case("tibia-out-of-reach", mesh("default/tibia.stl", moved([0.08, 0, 0])), "contact.tibia", "within reach",
         "default"),
    Case("one-triangle-tibia", mesh("implant/meshes/inlay.stl", one_triangle), "contact.tibia", "too few"),
    Case("ten-face-femur", mesh("implant/meshes/femur_component.stl", coarse), "contact.femur", "too coarse"),
    Case("degenerate-femur", mesh("implant/meshes/femur_component.stl", degenerate), "contact.femur", "degenerate"),
    Case("truncated-binary-stl", truncated("implant/meshes/femur_component.stl"), "contact.femur", "is truncated"),
    Case("femur-in-mm-in-a-metre-knee", mesh("default/femur.stl", scaled(1000)), "contact.femur", "is it in mm?",
         "default"),
    Case("meshes-swapped", swap_files("default/femur.stl", "default/tibia.stl"), "contact.tibia", "swapped?",
         "default"),
    Case("femur-given-twice", edit("default", 'tibia = "tibia.stl"', 'tibia = "femur.stl"'), "contact.tibia",
         "given twice?", "default"),
    # commands around knees
    Case("import-osim-negative-femur-offset", None, "--femur-offset", "inside the bone",
         argv=f"import-osim {LENHART / 'lenhart2015.osim'} --out {{d}}/o --femur-mesh "
              f"{LENHART / 'lenhart2015-R-femur-subchondral-bone.stl'} --femur-offset -2"),
    Case("study-of-a-million-samples", None, "--samples", "needs --yes",
         argv="study --knee {d}/implant --samples 1000000 --out {d}/o --json"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_knee_case(case: Case, base: Path, tmp_path: Path, capsys):
    """Exit 2, one stderr line naming the file and field, the JSON error object, no output."""
    d = tmp_path / "case"
    shutil.copytree(base, d)
    if case.setup:
        case.setup(d)
    argv = (case.argv or f"simulate --knee {{d}}/{case.knee}/knee.toml --protocol set1 --out {{d}}/o --no-plots "
            "--json").format(d=d).split()
    if "--json" not in argv and argv[0] != "import-osim":
        argv.append("--json")
    t0 = time.perf_counter()
    code = main(argv)
    out, err = capsys.readouterr()
    assert time.perf_counter() - t0 < SECONDS_PER_CASE
    err = err.strip()
    assert code == 2, (code, err)
    assert err.count("\n") == 0 and err.startswith("kneenlp: error: "), err
    assert f"{case.field}:" in err and case.needle in err, err
    if case.argv is None:
        assert str(d / case.knee / "knee.toml") in err, err
    if "--json" in argv:
        obj = json.loads(out)
        assert obj["field"] == case.field and obj["error"] in err
    assert not (d / "o").exists() or not any((d / "o").iterdir())


def test_knee_case_count():
    """Every knee-file slip has a case (the count only grows)."""
    assert len({c.id for c in CASES}) == len(CASES) >= 24


# ------------------------------------------------------------------ Hypothesis: mutations of shipped knees
def leaves(doc: object, path: tuple = ()) -> list[tuple]:
    """Paths of every scalar in a TOML document (list indices included)."""
    if isinstance(doc, dict):
        return [p for k, v in doc.items() for p in leaves(v, (*path, k))]
    if isinstance(doc, list):
        return [p for i, v in enumerate(doc) for p in leaves(v, (*path, i))]
    return [path]


def get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"


def dumps(doc: dict, prefix: str = "") -> str:
    """A TOML document: scalars and arrays inline, tables as [sections], arrays of tables inline."""
    lines = [f"{json.dumps(k)} = {toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            name = f"{prefix}.{json.dumps(k)}" if prefix else json.dumps(k)
            lines += [f"[{name}]", dumps(v, name)]
    return "\n".join(lines)


MESHES = {"implant": ["meshes/femur_component.stl", "meshes/inlay.stl"], "default": ["femur.stl", "tibia.stl"],
          "synthetic": ["meshes/tibia_medial.stl", "meshes/tibia_lateral.stl"]}


def mutate(doc: dict, d: Path, knee: str, data) -> str:
    """One slip in ``doc`` (or in a mesh file of the knee directory ``d``); returns what was done."""
    kind = data.draw(st.sampled_from(["delete", "scale", "swap-strings", "swap-meshes", "scale-mesh"]))
    paths = leaves(doc)
    if kind == "delete":
        path = data.draw(st.sampled_from(paths))
        parent = get(doc, path[:-1])
        del parent[path[-1]]
        if isinstance(parent, list) and not parent:  # an empty array: delete the field that held it
            del get(doc, path[:-2])[path[-2]]
    elif kind == "scale":
        numeric = [p for p in paths if isinstance(get(doc, p), (int, float)) and not isinstance(get(doc, p), bool)]
        path = data.draw(st.sampled_from(numeric))
        factor = data.draw(st.sampled_from([1e-3, 1e3]))
        get(doc, path[:-1])[path[-1]] = get(doc, path) * factor
        if data.draw(st.booleans()) and isinstance(path[-1], int):  # the whole point, as a unit slip is
            point = get(doc, path[:-1])
            point[:] = [v * factor if i != path[-1] else v for i, v in enumerate(point)]
    elif kind == "swap-strings":
        strings = [p for p in paths if isinstance(get(doc, p), str)]
        a, b = data.draw(st.sampled_from(strings)), data.draw(st.sampled_from(strings))
        va, vb = get(doc, a), get(doc, b)
        get(doc, a[:-1])[a[-1]], get(doc, b[:-1])[b[-1]] = vb, va
        return f"{kind} {a} {b}"
    elif kind == "swap-meshes":
        owner, other = data.draw(st.sampled_from([(k, m) for k, ms in MESHES.items() for m in ms]))
        own = data.draw(st.sampled_from(MESHES[knee]))
        source = d.parent / owner / other
        if source != d / own:
            shutil.copy(source, d / own)
        return f"{kind} {own} <- {other}"
    else:
        own = data.draw(st.sampled_from(MESHES[knee]))
        factor = data.draw(st.sampled_from([1e-3, 1e3]))
        m = trimesh.load(d / own, force="mesh")
        m.apply_scale(factor)
        m.export(d / own)
        return f"{kind} {own} x{factor}"
    return f"{kind} {path}"


@FUZZ
@given(data=st.data())
def test_mutated_shipped_knees_load_or_say_why(base: Path, tmp_path_factory, data):
    """A shipped knee with one slip loads, or raises a one-line input error naming its file; never
    another exception, within the time and memory limits of a case."""
    knee = data.draw(st.sampled_from(["implant", "default", "synthetic"]))
    d = tmp_path_factory.mktemp("mutant")
    shutil.copytree(base, d, dirs_exist_ok=True)
    path = d / knee / "knee.toml"
    doc = tomllib.loads(path.read_text())
    what = mutate(doc, d / knee, knee, data)
    path.write_text(dumps(doc) + "\n")
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        loaded = Knee.load(path)
    except InputError as exc:
        text = str(exc)
        assert "\n" not in text and (str(path) in text or re.search(r"\.(toml|stl)", text)), (what, text)
        loaded = None
    finally:
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        shutil.rmtree(d, ignore_errors=True)
    assert seconds < SECONDS_PER_CASE and peak < BYTES_PER_CASE, (what, seconds, peak)
    if loaded is not None:  # what loads is a knee: finite, plausible lengths
        assert all(1e-3 <= b.reference_length <= 0.3 for lig in loaded.ligaments.values() for b in lig.bundles)
        assert all(np.isfinite(c.points).all() for c in loaded.compartments.values())


def cracked(m: trimesh.Trimesh) -> trimesh.Trimesh:
    """The same surface with T-junctions (a vertex added on an edge, on one side only) in every 20th
    face and a zero-area face along every 30th face's edge: topologically open, geometrically not."""
    v, f = np.asarray(m.vertices, float), np.asarray(m.faces)
    new_v, new_f = [v], [f]
    n = len(v)
    for i in range(0, len(f), 20):
        a, b, c = f[i]
        new_v.append([0.5 * (v[a] + v[b])])
        new_f.append([[a, n, c], [n, b, c]])
        n += 1
    split = set(range(0, len(f), 20))
    base = np.array([face for i, face in enumerate(f) if i not in split])
    slivers = []
    for i in range(5, len(f), 30):
        a, b, _ = f[i]
        new_v.append([0.5 * (v[a] + v[b])])
        slivers.append([a, b, n])
        n += 1
    faces = np.vstack([base, *new_f[1:], np.array(slivers).reshape(-1, 3)])
    return trimesh.Trimesh(np.vstack(new_v), faces, process=False)


@pytest.mark.slow
def test_a_femur_with_cracks_and_zero_area_faces_solves_as_the_intact_one(base: Path, tmp_path: Path):
    """T-junction cracks and zero-area faces do not open a surface: the knee solves every trial as
    the intact one does (same surface, so the same poses to the solver's tolerance)."""
    import kneenlp

    d = tmp_path / "case"
    shutil.copytree(base, d)
    mesh("implant/meshes/femur_component.stl", cracked)(d)
    assert len(trimesh.grouping.group_rows(trimesh.load(d / "implant/meshes/femur_component.stl").edges_sorted,
                                           require_count=1)) > 100  # open, topologically
    intact = kneenlp.simulate(kneenlp.Knee.load(base / "implant" / "knee.toml"), "set1")
    odd = kneenlp.simulate(kneenlp.Knee.load(d / "implant" / "knee.toml"), "set1")
    assert all(s.converged for s in odd.solutions)
    assert np.allclose(odd.q, intact.q, atol=1e-6)
