"""OpenSim knee models in, calibrated ligaments out: import-osim, multi-bundle grouped
ligaments, identifiability before fitting, export-osim."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.design.identifiability import identifiability
from kneenlp.estimation.identify import identify
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.io import osim as O
from kneenlp.io.export_osim import calibrated_values, export_osim
from kneenlp.io.import_osim import import_osim
from kneenlp.model.ligament import force_strain_numpy

DATA = resource("knees", "lenhart2015", "opensim")
LENHART = DATA / "lenhart2015.osim"
BONE = DATA / "lenhart2015-R-femur-subchondral-bone.stl"


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """The Lenhart model imported with coarse groups (ACL, PCL, MCL, LCL, PFL, pCAP)."""
    out = tmp_path_factory.mktemp("imported")
    report = import_osim(LENHART, out, groups="coarse", femur_mesh=BONE, femur_offset=0.002)
    return report, kneenlp.Knee.load(out / "knee.toml")


def test_imported_bundles_match_the_osim(imported):
    report, knee = imported
    lines = O.knee_line_elements(O.read_osim(LENHART))
    expected = {n for n, e in lines.items() if not e.ignored_points}  # ITB1 runs to the pelvis
    bundles = {b.name: (lig, b) for lig in knee.ligaments.values() for b in lig.bundles}
    assert set(bundles) == expected and len(bundles) == 55 == report.n_bundles
    assert set(knee.ligaments) == {"ACL", "PCL", "MCL", "LCL", "PFL", "pCAP"}
    assert any("ITB1" in s for s in report.skipped) and any("wrapping surfaces imported" in s for s in report.skipped)
    for name, (lig, b) in bundles.items():
        e = lines[name]
        assert lig.grouped and name.startswith(lig.name)
        # attachments: the frame changed (cylinder fits), lengths do not
        assert b.reference_length == pytest.approx(np.linalg.norm(e.femoral_point - e.tibial_point), rel=1e-9)
        assert b.stiffness == e.linear_stiffness
        assert b.lin_strain == pytest.approx(e.transition_strain / 2)
        assert b.ref_strain == pytest.approx(lig.bundle_length(b) / e.slack_length - 1, rel=1e-9)  # along its path


def test_bundle_law_is_opensims_blankevoort1991ligament():
    """kneenlp's law with lin_strain = transition_strain / 2 is OpenSim's force (its implementation
    in kneenlp.io.osim is checked against OpenSim 4.6 itself in tests/test_osim.py)."""
    L0, k = 0.05, 820.0
    for et in (0.06, 0.1):
        lengths = L0 * (1 + np.array([-0.2, 0.0, 1e-4, et / 4, et / 2, 0.999 * et, et, 1.001 * et, 2 * et, 0.3]))
        ours = force_strain_numpy(lengths / L0 - 1, k, et / 2)
        theirs = O.blankevoort_force(lengths, L0, k, et)
        assert np.allclose(ours, theirs, rtol=1e-12, atol=1e-12)


def test_identifiability_is_reported_in_words(imported):
    _, knee = imported
    high = identifiability(knee, "high_flexion")
    assert high.rank == 10 and not high.identifiable  # the posterior capsule is slack at 60-90 deg
    text = high.report()
    assert "pCAP.k_scale does not change any measured coordinate" in text
    assert "rank 10, 2 not identifiable" in text
    assert identifiability(knee, "set4").identifiable


def test_export_osim_changes_only_the_calibrated_values(imported, tmp_path):
    _, knee = imported
    fit = {"params": {"ACL.k_scale": 1.2, "ACL.ref_strain_offset": -0.005, "MCL.ref_strain_offset": 0.01}}
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    out = tmp_path / "calibrated.osim"
    changes = export_osim(tmp_path / "fit.json", knee, LENHART, out)
    n_acl, n_mcl = len(knee.ligaments["ACL"].bundles), len(knee.ligaments["MCL"].bundles)
    assert len(changes) == 2 * n_acl + n_mcl  # ACL: stiffness and slack length; MCL: slack length
    old, new = LENHART.read_text().splitlines(), out.read_text().splitlines()
    assert len(old) == len(new)
    changed = [(a, b) for a, b in zip(old, new, strict=True) if a != b]
    assert all(re.search(r"<(linear_stiffness|slack_length)>", a) for a, _ in changed)
    assert len(changed) == len([c for c in changes if c[2] != c[3]])
    model = O.read_osim(out)
    expected = calibrated_values(knee, fit["params"])
    for b in knee.ligaments["ACL"].bundles:
        assert model.ligaments[b.name].linear_stiffness == pytest.approx(1.2 * b.stiffness, rel=1e-12)
        assert model.ligaments[b.name].slack_length == pytest.approx(expected[b.name]["slack_length"], rel=1e-12)
    assert model.ligaments["LCL1"].slack_length == O.read_osim(LENHART).ligaments["LCL1"].slack_length


@pytest.mark.parametrize("params, out, needle", [
    ({"ACL.k_scle": 1.2}, "cal.osim", "unknown parameter 'ACL.k_scle'"),
    ({"ACL.k_scale": "1.2"}, "cal.osim", "expected a finite number"),
    ({"ACL.k_scale": 1.2}, "missing/cal.osim", "does not exist"),
])
def test_export_osim_bad_input(imported, tmp_path, params, out, needle):
    """A misspelt parameter, a value that is text, an output in a missing directory: one line, no
    file written."""
    from kneenlp.base.errors import InputError

    _, knee = imported
    (tmp_path / "fit.json").write_text(json.dumps({"params": params}))
    with pytest.raises(InputError, match=needle):
        export_osim(tmp_path / "fit.json", knee, LENHART, tmp_path / out)
    assert not (tmp_path / out).exists()


_READBACK = r"""
import json, sys
try:
    import opensim as osm
except Exception as exc:
    json.dump({"unavailable": str(exc)}, open(sys.argv[2], "w")); sys.exit(0)
names = json.load(open(sys.argv[1]))["ligaments"]
m = osm.Model(json.load(open(sys.argv[1]))["model"])
m.initSystem()
fs = m.getForceSet()
out = {}
for n in names:
    lig = osm.Blankevoort1991Ligament.safeDownCast(fs.get(n))
    out[n] = [lig.get_linear_stiffness(), lig.get_slack_length()]
json.dump(out, open(sys.argv[2], "w"))
"""


def test_calibrated_model_loads_in_opensim(imported, tmp_path):
    """The written model (without OpenSim JAM's contact classes) loads in OpenSim 4.6 and reads
    back the calibrated properties (OpenSim runs in its own process: it cannot share one with casadi)."""
    _, knee = imported
    params = {"PCL.k_scale": 0.8, "PCL.ref_strain_offset": 0.02}  # both properties of every PCL bundle
    (tmp_path / "fit.json").write_text(json.dumps({"params": params}))
    export_osim(tmp_path / "fit.json", knee, LENHART, tmp_path / "cal.osim")
    O.write_opensim_loadable_copy(tmp_path / "cal.osim", tmp_path / "cal_plain.osim")
    expected = calibrated_values(knee, params)
    query = {"model": str(tmp_path / "cal_plain.osim"), "ligaments": sorted(expected)}
    (tmp_path / "q.json").write_text(json.dumps(query))
    proc = subprocess.run([sys.executable, "-c", _READBACK, str(tmp_path / "q.json"), str(tmp_path / "r.json")],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    got = json.loads((tmp_path / "r.json").read_text())
    if "unavailable" in got:
        pytest.skip(f"opensim not importable ({got['unavailable']})")
    for n, (k, L0) in got.items():
        assert k == pytest.approx(expected[n]["linear_stiffness"], rel=1e-12)
        assert L0 == pytest.approx(expected[n]["slack_length"], rel=1e-12)


@pytest.mark.slow
def test_set4_and_high_flexion_converge_on_the_multi_bundle_knee(imported):
    _, knee = imported
    for name in ("set4", "high_flexion"):
        res = kneenlp.simulate(knee, name)
        assert not res.failed, (name, [(s.trial.id, s.reason) for s in res.failed])
        assert res.max_residual <= 1e-6


@pytest.mark.slow
def test_zero_noise_recovery_of_the_grouped_parameters(imported, tmp_path):
    _, knee = imported
    truth = {"ACL.k_scale": 1.15, "PCL.ref_strain_offset": -0.01, "MCL.k_scale": 0.9, "LCL.ref_strain_offset": 0.005}
    res = kneenlp.simulate(knee, "set4", parameters=truth)
    path = tmp_path / "exact.csv"
    res.measured("none").to_csv(path, index=False)
    fit = identify(knee, path, seed=2)  # every group's scale and offset (12), from the paper's scatter
    assert fit.success, fit.report()
    assert len(fit.free) == 12
    theta = KneeModel.of(knee).theta(truth)
    for n in fit.free:
        true = theta[KneeModel.of(knee).index(n)]
        if n.endswith("k_scale"):
            assert fit.params[n] == pytest.approx(true, rel=1e-6), n
        else:  # offsets are strains (true value may be 0): absolute
            assert fit.params[n] == pytest.approx(true, abs=1e-8), n


def test_design_pool_reaches_90_degrees_on_a_multi_bundle_knee(imported):
    from kneenlp.design.optimal import FLEXIONS, FLEXIONS_MULTI_BUNDLE, default_flexions

    _, knee = imported
    assert default_flexions(knee) == FLEXIONS_MULTI_BUNDLE and max(FLEXIONS_MULTI_BUNDLE) == 90.0
    assert default_flexions(kneenlp.Knee.named("synthetic")) == FLEXIONS


def test_command_line_round_trip(tmp_path, capsys):
    """import-osim -> identifiability -> export-osim from the command line."""
    from kneenlp.cli import main

    out = tmp_path / "knee"
    assert main(["import-osim", str(LENHART), "--out", str(out), "--groups", "coarse", "--femur-mesh", str(BONE),
                 "--femur-offset", "2"]) == 0
    assert "55 bundles in 6 groups" in capsys.readouterr().out
    assert main(["identifiability", "--knee", str(out / "knee.toml"), "--protocol", "set1", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert len(report["free"]) == 12 and report["rank"] <= 12
    (tmp_path / "fit.json").write_text(json.dumps({"params": {"LCL.k_scale": 1.1}}))
    assert main(["export-osim", str(tmp_path / "fit.json"), "--knee", str(out / "knee.toml"), "--model", str(LENHART),
                 "--out", str(tmp_path / "cal.osim")]) == 0
    assert "4 values of 4 bundles" in capsys.readouterr().out  # the LCL's 4 stiffnesses (slack lengths unchanged)
    assert main(["export-osim", str(tmp_path / "fit.json"), "--knee", str(out / "knee.toml"), "--model",
                 str(tmp_path / "missing.osim"), "--out", str(tmp_path / "x.osim")]) == 2


def test_bundle_groups_are_adequacy_candidates(imported):
    """Each bundle group is a candidate effect (its scale and offset), for fits that keep it fixed."""
    _, knee = imported
    effects = {e.name: e.parameters for e in KneeModel.of(knee).effects}
    for g in knee.ligaments:
        assert effects[f"{g}_bundles"] == (f"{g}.k_scale", f"{g}.ref_strain_offset")
        assert f"{g}_femoral_attachment" in effects and f"{g}_tibial_attachment" in effects
    synthetic = KneeModel.of(kneenlp.Knee.named("synthetic"))
    assert not any(n.endswith("_bundles") for n in (e.name for e in synthetic.effects))


@pytest.mark.slow
def test_a_fixed_bundle_group_that_differs_is_found(imported, tmp_path):
    """Data from the knee with the PFL 1.6 times stiffer, fitted with the PFL group fixed at the
    model's values: diagnose recommends PFL_bundles and estimates the scale within 3 sd."""
    from kneenlp.adequacy.basefit import base_fit
    from kneenlp.adequacy.diagnosis import diagnose
    from kneenlp.experiment.measured import read_measured

    _, knee = imported
    path = tmp_path / "pfl.csv"
    kneenlp.simulate(knee, "set4", parameters={"PFL.k_scale": 1.6}).measured("uniform:0.5", 3).to_csv(path, index=False)
    free = [f"{g}.{p}" for g in ("MCL", "ACL", "PCL", "LCL") for p in ("k_scale", "ref_strain_offset")]
    d = diagnose(base_fit(knee, read_measured(path), "uniform:0.5", seed=1, free=free), "uniform:0.5")
    assert d.outcome == "missing_effect" and d.recommended.effect == "PFL_bundles", d.verdict
    refit = d.refits["PFL_bundles"]
    assert abs(refit.params["PFL.k_scale"] - 1.6) < 3 * refit.stderr["PFL.k_scale"]
    assert "Add PFL_bundles" in d.verdict


def test_import_without_a_patellar_tendon(tmp_path, imported):
    """A model without PT bundles (a total-knee model, e.g. CAMS) imports: the tuberosity is
    estimated from the tibial mesh and the report says so, or taken from --tuberosity."""
    import xml.etree.ElementTree as ET

    tree = ET.parse(LENHART)
    for parent in tree.iter():
        for child in list(parent):
            if (child.get("name") or "").startswith("PT"):
                parent.remove(child)
    no_pt = tmp_path / "no_pt.osim"
    tree.write(no_pt)
    report = import_osim(no_pt, tmp_path / "estimated", groups="coarse", geometry=DATA, femur_mesh=BONE,
                         femur_offset=0.002)
    assert any("estimated from the tibial mesh" in s for s in report.skipped)
    knee = kneenlp.Knee.load(tmp_path / "estimated" / "knee.toml")
    _, with_pt = imported
    assert 0.0 < np.linalg.norm(knee.tuberosity - with_pt.tuberosity) < 0.025  # m: an estimate, not the tendon
    given = (0.05, -0.04, 0.001)
    report = import_osim(no_pt, tmp_path / "given", groups="coarse", geometry=DATA, femur_mesh=BONE,
                         femur_offset=0.002, tuberosity=given)
    assert any("as given" in s for s in report.skipped)
    doc = (tmp_path / "given" / "knee.toml").read_text()
    assert re.search(r"tibial_tuberosity = \[\s*0\.05,\s*-0\.04,\s*0\.001,?\s*\]", doc)


def test_tuberosity_option_needs_three_numbers(tmp_path, capsys):
    from kneenlp.cli import main

    code = main(["import-osim", str(LENHART), "--out", str(tmp_path / "k"), "--tuberosity", "1,2"])
    err = capsys.readouterr().err
    assert code == 2 and "X,Y,Z" in err and "Traceback" not in err and not (tmp_path / "k").exists()


def test_refused_import_leaves_nothing_behind(tmp_path, capsys):
    """Issue 24: a refused import-osim left meshes/ in --out."""
    from kneenlp.cli import main

    out = tmp_path / "k"
    code = main(["import-osim", str(LENHART), "--out", str(out), "--femur-mesh", str(tmp_path / "missing.stl")])
    assert code == 2 and "--femur-mesh" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_cli_import_writes_the_knee(tmp_path, capsys):
    from kneenlp.cli import main

    out = tmp_path / "k"
    assert main(["import-osim", str(LENHART), "--out", str(out), "--femur-mesh", str(BONE), "--femur-offset", "2",
                 "--groups", "coarse"]) == 0
    assert f"wrote {out / 'knee.toml'}" in capsys.readouterr().out
    assert (out / "knee.toml").is_file() and any((out / "meshes").iterdir())
