"""Fuzz suite: bad input never gives a traceback or a silent wrong answer.

A table of hand-made cases (every case of the issue and more) runs the command line in this
process (``kneenlp.cli.main``), each in its own copy of the synthetic knee and a measured-data
file.  Every case ends in one of two ways:

* exit 2: exactly one stderr line ``kneenlp: error: ...`` that names the file and/or field of the
  case; with ``--json`` also a JSON object ``{"error", "file", "field"}`` on stdout; nothing
  written or changed in the case directory; for cases checked "before the work", the work
  (simulation, fit, design, study, export) is never started;
* exit 0 with the correct output (checked per case).

Never exit 3 (an internal error) and never a traceback; no temporary or half-written file is left.
Hypothesis then throws random bytes, random TOML values, random CSV cells and random option values
at the loaders.  The count of cases is in :func:`test_case_count` (and docs/inputs.md).
"""

from __future__ import annotations

import builtins
import hashlib
import io
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.base.resources import resource
from kneenlp.cli import main
from kneenlp.cli.parser import build_parser
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.protocol import Protocol
from kneenlp.model.knee import Knee
from kneenlp.model.knee_file import knee_file
from kneenlp.model.parameters import ParameterSet

#: Commands that take --json.
JSON_COMMANDS = {"simulate", "diagnose", "identify", "compare-methods", "study", "export", "design", "identifiability"}
#: The work of each command: with ``before_work`` a case must fail before any of these is called.
WORK = [("kneenlp.simulation", "simulate"), ("kneenlp.estimation.identify", "identify"),
        ("kneenlp.design.optimal", "design"), ("kneenlp.studies.study", "run_study"),
        ("kneenlp.io.export", "export_problem")]
TMP_NAME = re.compile(r"(^\.kneenlp-tmp-)|(\.tmp$)")


# ------------------------------------------------------------------ the base directory of every case
@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """Synthetic knee copy (knee/knee.toml, its meshes, table1.toml), measured data of set1 (m.csv),
    an existing file (afile) and an existing directory (adir)."""
    d = tmp_path_factory.mktemp("fuzzbase")
    src = knee_file("synthetic").parent
    shutil.copytree(src, d / "knee")
    shutil.copy(src.parent.parent / "parameters" / "table1.toml", d / "table1.toml")
    text = (d / "knee" / "knee.toml").read_text().replace("../../parameters/table1.toml", "../table1.toml")
    (d / "knee" / "knee.toml").write_text(text)
    result = kneenlp.simulate(kneenlp.Knee.named("synthetic"), "set1")
    result.measured("uniform:0.5", seed=1).to_csv(d / "m.csv", index=False)
    result.table().to_csv(d / "truth.csv", index=False)
    (d / "afile").write_text("an existing file\n")
    (d / "adir").mkdir()
    return d


def snapshot(d: Path) -> dict[str, str]:
    """Every file and directory below ``d`` with a hash of its content."""
    out = {}
    for p in sorted(d.rglob("*")):
        rel = str(p.relative_to(d))
        out[rel] = "dir" if p.is_dir() else hashlib.sha1(p.read_bytes()).hexdigest() if os.access(p, os.R_OK) \
            else "unreadable"
    return out


# ------------------------------------------------------------------ setups
def edit(rel: str, old: str, new: str) -> Callable[[Path], None]:
    """Replace ``old`` (which must occur) by ``new`` in the file ``rel`` of the case directory."""
    def setup(d: Path) -> None:
        text = (d / rel).read_text()
        assert old in text, (rel, old)
        (d / rel).write_text(text.replace(old, new, 1))
    return setup


def write(rel: str, content: str | bytes) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        (d / rel).parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            (d / rel).write_bytes(content)
        else:
            (d / rel).write_text(content)
    return setup


def frame(change: Callable[[pd.DataFrame], pd.DataFrame], rel: str = "m.csv") -> Callable[[Path], None]:
    """Rewrite the measured data through ``change(DataFrame) -> DataFrame``."""
    def setup(d: Path) -> None:
        change(pd.read_csv(d / "m.csv", dtype={"trial": str})).to_csv(d / rel, index=False)
    return setup


def scale_columns(suffix: str, factor: float) -> Callable[[Path], None]:
    def change(df: pd.DataFrame) -> pd.DataFrame:
        for c in df.columns:
            if c.endswith(suffix):
                df[c] = df[c] * factor
        return df
    return frame(change)


def set_cell(col: str, row: int, value: object) -> Callable[[Path], None]:
    def change(df: pd.DataFrame) -> pd.DataFrame:
        df[col] = df[col].astype(object)
        df.loc[row, col] = value
        return df
    return frame(change)


def many_rows(n: int) -> Callable[[Path], None]:
    def change(df: pd.DataFrame) -> pd.DataFrame:
        big = pd.concat([df.drop(columns="protocol")] * (n // len(df) + 1), ignore_index=True).iloc[:n].copy()
        big["trial"] = [f"t{i}" for i in range(n)]
        return big
    return frame(change)


def scale_knee(factor: float, units: str) -> Callable[[Path], None]:
    """The knee's points, sphere radii and meshes multiplied by ``factor``, declared in ``units``,
    the contact gate left to its default."""
    import trimesh

    def setup(d: Path) -> None:
        path = d / "knee" / "knee.toml"
        text = path.read_text().replace('units = "mm"', f'units = "{units}"')
        text = re.sub(r"\n\s*gate = [^\n]*", "\n", text)

        def triple(m: re.Match) -> str:
            return "[" + ", ".join(repr(float(v) * factor) for v in m.group(1).split(",")) + "]"

        text = re.sub(r"\[(-?[\d.]+, -?[\d.]+, -?[\d.]+)\]", triple, text)
        text = re.sub(r"sphere_radius = ([\d.]+)", lambda m: f"sphere_radius = {float(m.group(1)) * factor!r}", text)
        path.write_text(text)
        for mesh_file in (d / "knee" / "meshes").glob("*.stl"):
            mesh = trimesh.load(mesh_file, force="mesh")
            mesh.vertices = mesh.vertices * factor
            mesh.export(mesh_file)
    return setup


def nan_vertex(d: Path) -> None:
    import trimesh

    path = d / "knee" / "meshes" / "tibia_medial.stl"
    mesh = trimesh.load(path, force="mesh")
    mesh.vertices[5] = [np.nan, 0.0, 0.0]
    mesh.export(path)


def both(*setups: Callable[[Path], None]) -> Callable[[Path], None]:
    def setup(d: Path) -> None:
        for s in setups:
            s(d)
    return setup


PROTOCOL_CASE = '[[cases]]\ndirection = "anterior"\nmagnitude = [10.0]\nflexion = [0.0, 30.0]\n'


def protocol(extra: str = "", case: str = PROTOCOL_CASE) -> Callable[[Path], None]:
    return write("p.toml", f'name = "p"\n{case}{extra}')


# ------------------------------------------------------------------ checks of correct output
def check_simulate(d: Path, out: dict, trials: int = 7) -> None:
    assert out["trials"] == out["converged"] == trials and out["max_residual"] <= 1e-6
    table = pd.read_csv(d / "o" / "kinematics.csv")
    assert len(table) == trials


def check_same_kinematics(d: Path, out: dict) -> None:
    """The knee in metres simulates like the knee in millimetres (contact gate 0.01 mm, not 10 mm)."""
    check_simulate(d, out)
    assert Knee.load(d / "knee" / "knee.toml").gate == pytest.approx(1e-5)
    mine, truth = pd.read_csv(d / "o" / "kinematics.csv"), pd.read_csv(d / "truth.csv")
    cols = [c for c in truth.columns if c.endswith(("_mm", "_deg"))]
    assert np.allclose(mine[cols].to_numpy(), truth[cols].to_numpy(), atol=1e-4)


def check_fit(d: Path, out: dict) -> None:
    """Every estimate within 4 standard errors of the truth (Table 1)."""
    assert out["success"]
    truth = ParameterSet.load(d / "table1.toml")
    for name, value in out["params"].items():
        assert abs(value - truth[name]) <= 4 * out["stderr"][name] + 1e-9, name


def check_files(*names: str) -> Callable[[Path, dict], None]:
    def check(d: Path, out: dict) -> None:
        for name in names:
            assert (d / name).is_file() and (d / name).stat().st_size > 0, name
    return check


# ------------------------------------------------------------------ the table
@dataclass(frozen=True)
class Case:
    """One input: ``argv`` with ``{d}`` for the case directory; ``names``: what the error line must
    name (file and/or field), or ``check(d, json_output)`` for a case that must succeed."""

    id: str
    argv: str
    setup: Callable[[Path], None] | None = None
    names: tuple[str, ...] = ()
    check: Callable[[Path, dict], None] | None = None
    before_work: bool = True  # an error case: the work must not have started
    deny: tuple[str, ...] = ()  # files made unreadable / directories read-only
    notes: bool = False  # a successful case may print notes (kneenlp: ...) on stderr

    @property
    def ok(self) -> bool:
        return self.check is not None


K = "--knee {d}/knee/knee.toml"
SIM = f"simulate {K} --protocol set1 --no-plots --out {{d}}/o"
ID = f"identify {{d}}/m.csv {K}"

CASES = [
    # --- options, checked before any work (issue: tracebacks and bad values accepted)
    Case("seed-negative-simulate", f"{SIM} --seed -1", names=("--seed",)),
    Case("seed-negative-identify", f"{ID} --seed -1", names=("--seed",)),
    Case("seed-negative-study", "study --knee synthetic --sets 1 --samples 1 --seed -1 --out {d}/s",
         names=("--seed",)),
    Case("seed-not-integer", f"{ID} --seed 1.5", names=("--seed",)),
    Case("multistart-negative", f"{ID} --multistart -3", names=("--multistart",)),
    Case("multistart-text", f"{ID} --multistart abc", names=("--multistart",)),
    Case("refit-negative", "diagnose {d}/m.csv " + K + " --refit -1", names=("--refit",)),
    Case("robust-zero", f"design {K} --robust 0 --out {{d}}/x.toml", names=("--robust",)),
    Case("free-empty-names", f"{ID} --free ,,", names=("--free",)),
    Case("free-unknown-parameter", f"{ID} --free ACL.kk", names=("--free", "ACL.kk")),
    Case("free-twice", f"{ID} --free ACL.k,ACL.k", names=("--free",)),
    Case("max-evals-zero", "compare-methods {d}/m.csv " + K + " --max-evals 0", names=("--max-evals",)),
    Case("max-seconds-negative", "compare-methods {d}/m.csv " + K + " --max-seconds -5",
         names=("--max-seconds",)),
    Case("max-seconds-nan", "compare-methods {d}/m.csv " + K + " --max-seconds nan", names=("--max-seconds",)),
    Case("flexions-text", f"design {K} --flexions a,b --out {{d}}/x.toml", names=("--flexions",)),
    Case("flexions-out-of-range", f"design {K} --flexions 0,500 --out {{d}}/x.toml", names=("--flexions",)),
    Case("solver-bogus", f"{ID} --solver bogus", names=("--solver", "bogus")),
    Case("samples-zero", "study --knee synthetic --sets 1 --samples 0 --out {d}/s", names=("--samples",)),
    Case("workers-zero", "study --knee synthetic --sets 1 --workers 0 --out {d}/s", names=("--workers",)),
    Case("sets-unknown", "study --knee synthetic --sets 9 --samples 1 --out {d}/s", names=("--sets", "set9")),
    Case("noise-bogus", f"{SIM} --noise bogus:1", names=("--noise",)),
    Case("noise-negative", f"{SIM} --noise gaussian:-1", names=("--noise",)),
    Case("noise-zero-diagnose", "diagnose {d}/m.csv " + K + " --noise gaussian:0", names=("--noise",)),
    Case("noise-zero-design", f"design {K} --noise uniform:0 --out {{d}}/x.toml", names=("--noise",)),
    Case("protocol-unknown", f"simulate {K} --protocol set9 --out {{d}}/o", names=("--protocol", "set9")),
    Case("format-bogus", "export {d}/m.csv --format bogus --out {d}/e", names=("--format",)),
    Case("method-bogus", f"{ID} --method bogus", names=("--method",)),
    Case("command-unknown", "bogus", names=("bogus",)),
    Case("knee-missing", "simulate --knee {d}/none.toml --out {d}/o", names=("none.toml", "--knee")),
    Case("with-effect-unknown", f"{ID} --with-effect nothing", names=("--with-effect", "nothing")),
    Case("with-effect-simulate-unknown", f"{SIM} --with-effect bogus:k=1", names=("--with-effect", "bogus")),
    Case("with-effect-simulate-nan", f"{SIM} --with-effect posterior_capsule:k=nan", names=("--with-effect",)),
    Case("identifiability-free-empty", f"identifiability {K} --free ,", names=("--free",)),
    Case("identifiability-protocol-unknown", f"identifiability {K} --protocol set9", names=("--protocol", "set9")),
    Case("import-osim-femur-offset-nan", "import-osim {d}/none.osim --out {d}/i --femur-offset nan",
         names=("--femur-offset",)),
    # --- --out, checked before the work (issue: tracebacks, identify after the whole fit)
    Case("out-file-simulate", f"simulate {K} --protocol set1 --out {{d}}/afile", names=("afile", "--out")),
    Case("out-file-identify", f"{ID} --out {{d}}/afile", names=("afile", "--out")),
    Case("out-file-diagnose", "diagnose {d}/m.csv " + K + " --out {d}/afile", names=("afile", "--out")),
    Case("out-file-study", "study --knee synthetic --sets 1 --samples 1 --out {d}/afile", names=("afile", "--out")),
    Case("out-file-export", "export {d}/m.csv --format nl " + K + " --out {d}/afile", names=("afile", "--out")),
    Case("out-file-view", f"view {K} --protocol set1 --out {{d}}/afile", names=("afile", "--out")),
    Case("out-dir-design", f"design {K} --out {{d}}/adir", names=("adir", "--out")),
    Case("out-file-import-osim", "import-osim {d}/none.osim --out {d}/afile", names=("afile", "--out")),
    Case("out-dir-export-osim", "export-osim {d}/fit.json --knee {d}/knee/knee.toml --model {d}/none.osim "
         "--out {d}/adir", names=("adir", "--out")),
    Case("out-below-file", f"simulate {K} --protocol set1 --out {{d}}/afile/sub", names=("afile", "--out")),
    Case("out-read-only-dir", f"simulate {K} --protocol set1 --out {{d}}/adir/o", names=("adir", "--out"),
         deny=("adir",)),
    Case("out-read-only-design", f"design {K} --out {{d}}/adir/p.toml", names=("adir", "--out"), deny=("adir",)),
    # --- measured-data CSV
    Case("data-missing", f"identify {{d}}/none.csv {K}", names=("none.csv", "file not found")),
    Case("data-unreadable", f"{ID}", names=("m.csv", "cannot read"), deny=("m.csv",)),
    Case("data-directory", f"identify {{d}}/adir {K}", names=("adir",)),
    Case("data-binary", f"{ID}", setup=write("m.csv", b"\x00\xff\xfe garbage\n\x01,\x02\n"), names=("m.csv",)),
    Case("data-empty", f"{ID}", setup=write("m.csv", ""), names=("m.csv",)),
    Case("data-header-only", f"{ID}", setup=frame(lambda df: df.iloc[:0]), names=("m.csv", "no data rows")),
    Case("data-nan-cell", f"{ID}", setup=set_cell("anterior_translation_mm", 2, "nan"),
         names=("m.csv", "anterior_translation_mm", "row 4")),
    Case("data-text-cell", f"{ID}", setup=set_cell("varus_moment_Nm", 0, "ten"), names=("m.csv", "varus_moment_Nm")),
    Case("data-duplicate-trial", f"{ID}", setup=set_cell("trial", 1, "none_flex30"), names=("m.csv", "trial")),
    Case("data-empty-trial", f"{ID}", setup=set_cell("trial", 1, None), names=("m.csv", "trial")),
    Case("data-wrong-unit-column", f"{ID}",
         setup=frame(lambda df: df.rename(columns={"anterior_translation_mm": "anterior_translation_m"})),
         names=("m.csv", "anterior_translation_m")),
    Case("data-missing-column", f"{ID}", setup=frame(lambda df: df.drop(columns="flexion_deg")),
         names=("m.csv", "flexion_deg")),
    Case("data-translations-in-metres", f"{ID}", setup=scale_columns("_mm", 1e-3), names=("m.csv", "_mm", "metres")),
    Case("data-translations-in-micrometres", f"{ID}", setup=scale_columns("_mm", 1e3),
         names=("m.csv", "_mm", "micrometres")),
    Case("data-rotations-in-radians", f"{ID}", setup=scale_columns("_deg", np.pi / 180),
         names=("m.csv", "rotation", "radians")),
    Case("data-flexion-out-of-range", f"{ID}", setup=set_cell("flexion_deg", 0, 500), names=("m.csv", "flexion_deg")),
    Case("data-load-huge", f"{ID}", setup=set_cell("anterior_force_N", 1, 1e6), names=("m.csv", "anterior_force_N")),
    Case("data-protocol-set9", f"{ID}", setup=set_cell("protocol", slice(None), "set9"),
         names=("m.csv", "protocol", "set9")),
    Case("data-two-protocols", f"{ID}", setup=set_cell("protocol", 0, "set2"), names=("m.csv", "protocol")),
    Case("data-load-axes-unknown", f"{ID}", setup=set_cell("load_axes", 0, "sideways"), names=("m.csv", "load_axes")),
    Case("data-10000-rows-no-protocol", f"{ID}", setup=many_rows(10_000), names=("m.csv", "10000 rows")),
    Case("data-not-the-protocol", f"{ID} --protocol set2", names=("m.csv", "set2"), before_work=False),
    # --- knee TOML
    Case("knee-ligament-number", SIM, setup=edit("knee/knee.toml", "[ligaments.ACL]\nfemur = [-3.0, 1.0, 7.0]\n"
                                                 "tibia = [14.0, -22.0, 0.0]\n", "[ligaments]\nACL = 5\n"),
         names=("knee.toml", "ligaments.ACL")),
    Case("knee-candidate-number", SIM, setup=edit("knee/knee.toml", "[candidates.ALL]", "[candidates]\nX = 5\n"
                                                  "[candidates.ALL]"), names=("knee.toml", "candidates.X")),
    Case("knee-unknown-ligament", SIM, setup=edit("knee/knee.toml", "[ligaments.ACL]", "[ligaments.ACLx]"),
         names=("knee.toml", "table1.toml", "ACLx")),
    Case("knee-parameter-file-missing", SIM, setup=edit("knee/knee.toml", "../table1.toml", "../none.toml"),
         names=("knee.toml", "parameters", "none.toml")),
    Case("parameters-ligament-the-knee-lacks", f"{SIM} --parameters {{d}}/p.toml",
         setup=lambda d: (d / "p.toml").write_text((d / "table1.toml").read_text() + "\n[ligaments.ALL]\nk = 100.0\n"
                                                   "ref_strain = 0.0\nlin_strain = 3.0\n"),
         names=("p.toml", "ligaments.ALL", "knee.toml")),
    Case("knee-mesh-nan-vertex", SIM, setup=nan_vertex, names=("knee.toml", "tibia_medial.stl", "non-finite")),
    Case("knee-mesh-missing", SIM, setup=lambda d: (d / "knee" / "meshes" / "tibia_lateral.stl").unlink(),
         names=("knee.toml", "contact.lateral.tibia")),
    Case("knee-mesh-garbage", SIM, setup=write("knee/meshes/tibia_lateral.stl", b"solid x\nnot an stl\n"),
         names=("knee.toml", "contact.lateral.tibia")),
    Case("knee-1000x-too-big", SIM, setup=edit("knee/knee.toml", 'units = "mm"', 'units = "m"'),
         names=("knee.toml", "units", "1000x")),
    Case("knee-1000x-too-small", SIM, setup=scale_knee(1e-3, "mm"), names=("knee.toml", "units", "1/1000")),
    Case("knee-attachments-metres-apart", SIM,
         setup=edit("knee/knee.toml", "femur = [-3.0, 1.0, 7.0]", "femur = [-3000.0, 1.0, 7.0]"),
         names=("knee.toml", "ligaments.ACL", "apart")),
    Case("knee-attachment-two-numbers", SIM, setup=edit("knee/knee.toml", "femur = [-3.0, 1.0, 7.0]", "femur = [1, 2]"),
         names=("knee.toml", "ligaments.ACL.femur")),
    Case("knee-malformed-toml", SIM, setup=edit("knee/knee.toml", "[ligaments.ACL]", "[ligaments.ACL"),
         names=("knee.toml", "malformed TOML")),
    Case("knee-side", SIM, setup=edit("knee/knee.toml", 'side = "right"', 'side = "up"'), names=("knee.toml", "side")),
    Case("knee-units", SIM, setup=edit("knee/knee.toml", 'units = "mm"', 'units = "inch"'),
         names=("knee.toml", "units")),
    Case("knee-unreadable", SIM, names=("knee.toml", "cannot read"), deny=("knee/knee.toml",)),
    Case("knee-mesh-unreadable", SIM, names=("knee.toml", "tibia_medial.stl"), deny=("knee/meshes/tibia_medial.stl",)),
    Case("knee-gate-negative", SIM, setup=edit("knee/knee.toml", "gate = 0.01", "gate = -1"),
         names=("knee.toml", "contact.gate")),
    # --- parameter-set TOML (--parameters)
    Case("parameters-k-negative", f"{SIM} --parameters {{d}}/table1.toml",
         setup=edit("table1.toml", "k = 10000.0", "k = -10000.0"), names=("table1.toml", "ligaments.ACL.k")),
    Case("parameters-k-text", f"{SIM} --parameters {{d}}/table1.toml",
         setup=edit("table1.toml", "k = 10000.0", 'k = "stiff"'), names=("table1.toml", "ligaments.ACL.k")),
    Case("parameters-k-in-kN", f"{SIM} --parameters {{d}}/table1.toml",
         setup=edit("table1.toml", "k = 10000.0", "k = 10.0"), names=("table1.toml", "ligaments.ACL.k", "kN")),
    Case("parameters-unit-unknown", f"{SIM} --parameters {{d}}/table1.toml",
         setup=edit("table1.toml", 'k = "N"', 'k = "lbf"'), names=("table1.toml", "units.k")),
    Case("parameters-modulus-missing", f"{SIM} --parameters {{d}}/table1.toml",
         setup=lambda d: (d / "table1.toml").write_text(re.sub(r"\[contact\][^\[]*", "",
                                                               (d / "table1.toml").read_text())),
         names=("table1.toml", "contact.modulus")),
    Case("parameters-bytes", f"{SIM} --parameters {{d}}/table1.toml", setup=write("table1.toml", b"\xff\x00k=1"),
         names=("table1.toml",)),
    # --- protocol TOML
    Case("protocol-cases-numbers", f"{SIM} --protocol {{d}}/p.toml", setup=write("p.toml", "cases = [1, 2]\n"),
         names=("p.toml", "cases[0]")),
    Case("protocol-exclude-no-flexion", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol("exclude = [{magnitude = 10.0}]\n"),
         names=("p.toml", "cases[0].exclude[0].flexion")),
    Case("protocol-exclude-magnitude-text", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol('exclude = [{magnitude = "abc", flexion = 0.0}]\n'),
         names=("p.toml", "cases[0].exclude[0].magnitude")),
    Case("protocol-exclude-all", f"{SIM} --protocol {{d}}/p.toml", setup=protocol('exclude = "all"\n'),
         names=("p.toml", "cases[0].exclude")),
    Case("protocol-exclude-nothing", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol("exclude = [{magnitude = 10.0, flexion = 60.0}]\n"), names=("p.toml", "cases[0].exclude[0]")),
    Case("protocol-direction-unknown", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol(case='[[cases]]\ndirection = "sideways"\nmagnitude = 1.0\nflexion = 0.0\n'),
         names=("p.toml", "cases[0].direction", "sideways")),
    Case("protocol-magnitude-negative", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol(case='[[cases]]\ndirection = "anterior"\nmagnitude = -5.0\nflexion = 0.0\n'),
         names=("p.toml", "cases[0].magnitude")),
    Case("protocol-magnitude-huge", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol(case='[[cases]]\ndirection = "anterior"\nmagnitude = 1e9\nflexion = 0.0\n'),
         names=("p.toml", "cases[0].magnitude", "unit slip")),
    Case("protocol-flexion-out-of-range", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol(case='[[cases]]\ndirection = "none"\nflexion = 200.0\n'), names=("p.toml", "cases[0].flexion")),
    Case("protocol-unknown-key", f"{SIM} --protocol {{d}}/p.toml", setup=protocol("magnitudes = [1.0]\n"),
         names=("p.toml", "cases[0].magnitudes")),
    Case("protocol-unreadable", f"{SIM} --protocol {{d}}/p.toml", setup=protocol(), names=("p.toml", "cannot read"),
         deny=("p.toml",)),
    Case("protocol-no-cases", f"{SIM} --protocol {{d}}/p.toml", setup=write("p.toml", 'name = "p"\n'),
         names=("p.toml", "cases")),
    Case("protocol-load-component-unknown", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol(case="[[cases]]\nflexion = 0.0\nloads = {shear = 1.0}\n"), names=("p.toml", "cases[0].loads")),
    # --- correct input: exit 0 with the right output
    Case("ok-simulate", f"{SIM}", check=check_simulate),
    Case("ok-knee-in-metres-default-gate", f"{SIM}", setup=scale_knee(1e-3, "m"), check=check_same_kinematics),
    Case("ok-protocol-exclude", f"{SIM} --protocol {{d}}/p.toml",
         setup=protocol("exclude = [{magnitude = 10.0, flexion = 0.0}]\n"),
         check=lambda d, out: check_simulate(d, out, trials=1)),
    Case("ok-identify", f"{ID} --out {{d}}/fit", check=lambda d, out: (check_fit(d, out),
                                                                       check_files("fit/fit.json")(d, out))),
    Case("ok-identify-protocol-given", f"{ID} --protocol set1", check=check_fit),
    Case("ok-data-designed-protocol-beside", f"{ID}",
         setup=both(set_cell("protocol", slice(None), "mine"),
                    lambda d: (d / "mine.toml").write_text(
                        resource("protocols", "set1.toml").read_text().replace('"set1"', '"mine"'))),
         check=check_fit),
    Case("ok-data-other-protocol-name", f"{ID}", setup=set_cell("protocol", slice(None), "my design"),
         check=check_fit, notes=True),
    Case("ok-out-new-nested-dir", f"simulate {K} --protocol set1 --no-plots --out {{d}}/a/b/c",
         check=lambda d, out: check_files("a/b/c/kinematics.csv")(d, out)),
    Case("ok-stale-staging-removed", f"{SIM}",
         setup=write("o/.kneenlp-tmp-4194305/kinematics.csv", "half,writ"), check=check_simulate),
    Case("ok-export", "export {d}/m.csv --format casadi " + K + " --out {d}/e", check=lambda d, out: (
        check_files(*(str(Path(f).relative_to(d)) for f in out["files"]))(d, out))),
]


def _deny(d: Path, rels: tuple[str, ...], monkeypatch) -> None:
    """Make ``rels`` unreadable (files) or read-only (directories).  As root permissions do not
    apply, so the same failure is injected where the code opens or creates them."""
    paths = [d / r for r in rels]
    for p in paths:
        p.chmod(0o555 if p.is_dir() else 0o000)
    if os.geteuid() != 0:
        return
    files = {str(p) for p in paths if p.is_file()}
    dirs = [p for p in paths if p.is_dir()]

    def denied(name: str) -> PermissionError:
        return PermissionError(13, "Permission denied", name)

    real_open, real_mkdtemp = builtins.open, tempfile.mkdtemp

    def fake_open(file, *args, **kwargs):
        if str(file) in files:
            raise denied(str(file))
        return real_open(file, *args, **kwargs)

    def fake_mkdtemp(*args, **kwargs):
        where = Path(kwargs.get("dir") or (args[2] if len(args) > 2 else "."))
        if any(where == p or p in where.parents for p in dirs):
            raise denied(str(where))
        return real_mkdtemp(*args, **kwargs)

    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(io, "open", fake_open)  # Path.open
    monkeypatch.setattr(tempfile, "mkdtemp", fake_mkdtemp)


def run_case(case: Case, d: Path, capsys, monkeypatch) -> tuple[int, str, str]:
    argv = [a.format(d=d) for a in case.argv.split()]
    if argv[0] in JSON_COMMANDS:
        argv.append("--json")
    if not case.ok and case.before_work:
        import importlib

        for module, name in WORK:
            def started(*args, _name=name, **kwargs):
                raise AssertionError(f"{case.id}: {_name} started although the input is bad")
            monkeypatch.setattr(importlib.import_module(module), name, started)
    _deny(d, case.deny, monkeypatch)
    code = main(argv)
    captured = capsys.readouterr()
    monkeypatch.undo()
    for rel in case.deny:
        (d / rel).chmod(0o755 if (d / rel).is_dir() else 0o644)
    return code, captured.out, captured.err


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_case(case: Case, base: Path, tmp_path: Path, capsys, monkeypatch):
    d = tmp_path / "case"
    shutil.copytree(base, d)
    if case.setup:
        case.setup(d)
    before = snapshot(d)
    code, out, err = run_case(case, d, capsys, monkeypatch)
    assert "Traceback" not in err + out and "internal error" not in err, err
    lines = err.strip().splitlines()
    leftovers = [p for p in d.rglob("*") if TMP_NAME.search(p.name)]
    assert not leftovers, f"temporary files left: {leftovers}"
    if case.ok:
        assert code == 0, err
        assert case.notes or not lines, err
        result = json.loads(out) if out.lstrip().startswith("{") else {}
        case.check(d, result)
        return
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith("kneenlp: error: "), err
    for name in case.names:
        assert name in lines[0], (name, lines[0])
    if case.argv.split()[0] in JSON_COMMANDS:
        obj = json.loads(out)
        assert set(obj) == {"error", "file", "field"} and obj["error"] == lines[0].removeprefix("kneenlp: error: ")
        assert obj["file"] or obj["field"], obj
    assert snapshot(d) == before, "a failed command wrote or changed files"


def test_case_count():
    """The table's counts are quoted in docs/inputs.md."""
    ok = sum(c.ok for c in CASES)
    assert len({c.id for c in CASES}) == len(CASES)
    assert len(CASES) >= 114 and ok >= 10, (len(CASES), len(CASES) - ok, ok)


# ------------------------------------------------------------------ Hypothesis: loaders never crash
#: Examples per Hypothesis test: 40, the same ones every run; KNEENLP_FUZZ_EXAMPLES=1000 for a
#: deeper, random search.
DEEP = os.environ.get("KNEENLP_FUZZ_EXAMPLES")
FUZZ = settings(max_examples=int(DEEP or 40), deadline=None, derandomize=not DEEP,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def one_line_naming(exc: InputError, path: Path) -> None:
    text = str(exc)
    assert "\n" not in text and str(path) in text, text


def load_or_input_error(load: Callable[[Path], object], path: Path):
    try:
        return load(path)
    except InputError as exc:
        one_line_naming(exc, path)
        return None


@FUZZ
@given(data=st.binary(max_size=300))
def test_random_bytes_into_every_loader(base: Path, tmp_path: Path, data: bytes):
    """Random bytes as a measured-data CSV, a parameter set, a protocol and a knee file."""
    for name, load in (("m.csv", read_measured), ("p.toml", ParameterSet.load), ("q.toml", Protocol.load),
                       ("k.toml", Knee.load)):
        path = tmp_path / name
        path.write_bytes(data)
        load_or_input_error(load, path)


def toml_value(v: object) -> str:
    """``v`` as a TOML value (inline)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v > 0 else "-inf") if abs(v) == float("inf") else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"


scalars = st.one_of(st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True),
                    st.text(max_size=8), st.sampled_from(["anterior", "none", "ACL", "mm", "m", "N", "%", "", "set1"]))


def containers(inner: st.SearchStrategy) -> st.SearchStrategy:
    """Arrays and tables of ``inner``."""
    return st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3))


values = st.recursive(scalars, containers, max_leaves=6)


def toml_lines(doc: dict, prefix: str = "") -> list[str]:
    """A TOML document of nested tables (keys quoted)."""
    plain = [f"{json.dumps(k)} = {toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    tables = []
    for k, v in doc.items():
        if isinstance(v, dict):
            name = f"{prefix}.{json.dumps(k)}" if prefix else json.dumps(k)
            tables += [f"[{name}]", *toml_lines(v, name)]
    return plain + tables


def leaves(doc: dict, path: tuple = ()) -> list[tuple]:
    out = []
    for k, v in doc.items():
        out += leaves(v, (*path, k)) if isinstance(v, dict) and v else [(*path, k)]
    return out


def replaced(doc: dict, path: tuple, value: object) -> dict:
    doc = json.loads(json.dumps(doc))
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return doc


@FUZZ
@given(data=st.data())
def test_random_values_in_the_knee_and_parameter_files(base: Path, tmp_path: Path, data):
    """One field of the synthetic knee file or of its parameter set replaced by a random TOML value:
    the knee loads (and every length and parameter is finite) or the error names the file."""
    import tomllib

    which = data.draw(st.sampled_from(["knee/knee.toml", "table1.toml"]))
    d = tmp_path / "k"
    if not d.exists():
        shutil.copytree(base, d)
    original = (base / which).read_text()
    doc = tomllib.loads(original)
    path = data.draw(st.sampled_from(leaves(doc)))
    value = data.draw(values)
    (d / which).write_text("\n".join(toml_lines(replaced(doc, path, value))) + "\n")
    try:
        knee = Knee.load(d / "knee" / "knee.toml")
    except InputError as exc:
        assert "\n" not in str(exc) and Path(which).name in str(exc), (path, value, str(exc))
    else:
        assert all(np.isfinite(knee.parameters[n]) for n in knee.parameters.names())
        assert all(1e-3 <= b.reference_length <= 0.3 for lig in knee.ligaments.values() for b in lig.bundles)
    finally:
        (d / which).write_text(original)


@FUZZ
@given(field=st.sampled_from(["direction", "magnitude", "flexion", "exclude", "loads", "name", "extra"]),
       value=values, top=st.sampled_from(["name", "load_axes", "cases", "title"]), top_value=values,
       where=st.booleans())
def test_random_values_in_a_protocol(field: str, value: object, top: str, top_value: object, where: bool):
    """A protocol document with one random value: a valid protocol (every flexion and load in
    range) or an error naming the source and a field."""
    case = {"direction": "anterior", "magnitude": [10.0, 50.0], "flexion": [0.0, 30.0]}
    doc = {"name": "fuzz", "cases": [case | {field: value}]} if where else {"name": "fuzz", "cases": [case],
                                                                           top: top_value}
    try:
        proto = Protocol.from_dict(doc, source="fuzz.toml")
    except InputError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("fuzz.toml: "), str(exc)
        assert exc.field, str(exc)
    else:
        assert proto.trials
        for t in proto.trials:
            assert -10 <= t.flexion_deg <= 120 and all(np.isfinite(v) and abs(v) <= 1000 for v in t.loads.values())


@FUZZ
@given(cells=st.lists(st.tuples(st.integers(0, 6), st.integers(0, 11),
                                st.one_of(st.text(max_size=6), st.floats().map(repr), st.integers().map(str))),
                      min_size=1, max_size=3))
def test_random_csv_cells(base: Path, tmp_path: Path, cells):
    """Measured data with random cells: read with every value finite and plausible, or an error
    naming the file (and the column, for a bad cell)."""
    df = pd.read_csv(base / "m.csv", dtype=str)
    for row, col, value in cells:
        df.iloc[row, col] = value
    path = tmp_path / "cells.csv"
    df.to_csv(path, index=False)
    data = load_or_input_error(read_measured, path)
    if data is not None:
        assert len(data) == 7 and np.isfinite(data.q).all()
        assert all(-10 <= t.flexion_deg <= 120 for t in data.trials)


INT_OPTIONS = {("identify", "--seed"): (0, 2**63 - 1), ("identify", "--multistart"): (1, 1000),
               ("diagnose", "--refit"): (0, 1000), ("design", "--robust"): (1, 100),
               ("compare-methods", "--max-evals"): (1, 10_000_000), ("study", "--samples"): (1, 1_000_000)}


@FUZZ
@given(option=st.sampled_from(sorted(INT_OPTIONS)),
       text=st.one_of(st.integers(-10**20, 10**20).map(str), st.text(max_size=6), st.floats().map(repr)))
def test_random_option_values(option: tuple[str, str], text: str):
    """Any value of an integer option: parsed within its documented range, or an error naming it."""
    command, name = option
    data = ["data.csv"] if command in ("identify", "diagnose", "compare-methods") else []
    argv = [command, *data, f"{name}={text}"]
    try:
        args = build_parser().parse_args(argv)
    except InputError as exc:
        assert exc.field == name and "\n" not in str(exc), str(exc)
    else:
        lo, hi = INT_OPTIONS[option]
        assert lo <= getattr(args, name.lstrip("-").replace("-", "_")) <= hi


# ------------------------------------------------------------------ a study killed and restarted
def test_study_killed_at_random_points_and_restarted(tmp_path):
    """A study stopped by Ctrl-C (SIGINT), SIGTERM and SIGKILL at random (seeded) points, then a
    sample file truncated and a stale temporary file left: the restarted study reports and redoes
    the truncated sample and ends with exactly one row per (set, sample), none lost or duplicated;
    finished samples are kept as they were."""
    import random
    import signal
    import subprocess
    import sys
    import time

    rng = random.Random(int(os.environ.get("KNEENLP_FUZZ_SEED", "16")))
    out = tmp_path / "study"
    # 8 samples per set: on an idle machine a sample takes well under a second, and the three
    # kills must still leave work for the restart
    n = 8
    cmd = [sys.executable, "-m", "kneenlp.cli", "study", "--knee", "synthetic", "--sets", "1,2", "--samples", str(n),
           "--workers", "1", "--seed", "5", "--quiet", "--out", str(out)]
    tasks = {(s, i) for s in ("set1", "set2") for i in range(n)}

    def done() -> list[Path]:
        return sorted((out / "samples").glob("*.json"))

    for sig, status in ((signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGKILL, -signal.SIGKILL)):
        target = len(done()) + rng.randint(1, 2)
        proc = subprocess.Popen(cmd, start_new_session=True, stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 120
        while time.time() < deadline and len(done()) < target and proc.poll() is None:
            time.sleep(0.05)
        time.sleep(rng.uniform(0.0, 0.5))  # somewhere inside the next sample
        os.killpg(proc.pid, sig)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == status, (sig, proc.returncode, err)
        if sig != signal.SIGKILL:
            assert len(err.strip().splitlines()) == 1 and "finished work is kept" in err, err
            assert not [p for p in out.rglob("*") if TMP_NAME.search(p.name)]
        assert len(done()) >= target
    kept = {p.name: p.read_text() for p in done()}
    assert len(kept) < len(tasks), "every sample finished before the last kill: nothing left to resume"
    victim = done()[0]
    victim.write_text(kept[victim.name][: len(kept[victim.name]) // 2])
    (out / "samples" / f".set2_{n - 1:06d}.json.{os.getpid()}.tmp").write_text('{"set": "se')  # of a killed write
    final = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert final.returncode == 0, final.stderr
    assert str(victim) in final.stderr and "truncated" in final.stderr, final.stderr
    df = pd.read_csv(out / "estimates.csv")
    assert len(df) == len(tasks) and set(zip(df["set"], df["sample"], strict=True)) == tasks
    volatile = ("seconds", "wall_seconds")
    redone, original = json.loads(victim.read_text()), json.loads(kept[victim.name])
    assert {k: v for k, v in redone.items() if k not in volatile} == \
        {k: v for k, v in original.items() if k not in volatile}
    for name, text in kept.items():
        if name != victim.name:
            assert (out / "samples" / name).read_text() == text, name  # finished samples not recomputed
    assert not [p for p in out.rglob("*") if TMP_NAME.search(p.name)]


@pytest.mark.slow
@pytest.mark.parametrize("command", ["identify", "cross-validate"])
def test_signal_at_random_moments_of_a_real_calibration(command, tmp_path):
    """SIGINT and SIGTERM at random (seeded) moments of a calibration of the S192803 problem (inside
    IPOPT, the reduced fit, the working-set callback, the forked hold-outs): always exit 130/143,
    one line on stderr, no traceback, no temporary file left."""
    import random
    import signal
    import subprocess
    import sys

    rng = random.Random(int(os.environ.get("KNEENLP_FUZZ_SEED", "16")))
    problem = Path(__file__).resolve().parents[1] / "problems" / "s192803"
    for k, sig in enumerate((signal.SIGINT, signal.SIGTERM) * 2):
        out = tmp_path / f"out{k}"
        proc = subprocess.Popen([sys.executable, "-m", "kneenlp.cli", command, "--problem", str(problem), "--out",
                                 str(out)], start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True)
        try:
            proc.wait(timeout=rng.uniform(2.0, 14.0))
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, sig)
        _, err = proc.communicate(timeout=120)
        if proc.returncode == 0:  # finished before the signal (a fast machine): nothing to check
            continue
        assert proc.returncode == 128 + sig, (sig, proc.returncode, err)
        assert len(err.strip().splitlines()) == 1 and "finished work is kept" in err, err
        assert "Traceback" not in err
        assert not [p for p in tmp_path.rglob("*") if TMP_NAME.search(p.name)]


@pytest.mark.parametrize(("raised", "status", "words"), [(KeyboardInterrupt(), 130, "interrupted"),
                                                         (RuntimeError("boom\nsecond line"), 3, "internal error")])
def test_interrupt_and_bug_are_one_line_with_json(raised, status, words, tmp_path, capsys, monkeypatch):
    """Ctrl-C (130) and an unexpected exception (3, a bug): one line on stderr, the JSON error
    object on stdout with --json, nothing written."""
    import kneenlp.simulation

    def work(*args, **kwargs):
        raise raised
    monkeypatch.setattr(kneenlp.simulation, "simulate", work)
    code = main(["simulate", "--knee", "synthetic", "--protocol", "set1", "--out", str(tmp_path / "o"), "--json"])
    captured = capsys.readouterr()
    assert code == status and len(captured.err.strip().splitlines()) == 1 and words in captured.err
    obj = json.loads(captured.out)
    assert words in obj["error"] and obj["file"] is None and obj["field"] is None
    assert not (tmp_path / "o").exists()
