"""Problem files (``problems/<name>/problem.toml``, ``--problem DIR``): the shipped ones load and are
what they say (the Sets' data regenerate from their seeds), a problem runs as the same options do,
the parameter table's free flags and bounds act, and bad problem files are refused in one line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.cli import main
from kneenlp.experiment.problem_file import ProblemFile

PROBLEMS = Path(__file__).resolve().parents[1] / "problems"


def test_every_shipped_problem_loads():
    names = sorted(p.name for p in PROBLEMS.iterdir() if (p / "problem.toml").is_file())
    assert names == ["s192803", "set1", "set2", "set3", "set4"]
    for name in names:
        problem = ProblemFile.load(PROBLEMS / name)
        assert problem.name == name and problem.data.is_file() and problem.entries is not None
        kneenlp.KneeModel.of(problem.knee_with_parameters())  # the table's names, units and priors checked


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_sets_are_the_default_knee_measured_from_their_seed(n):
    shipped = pd.read_csv(PROBLEMS / f"set{n}" / "measured.csv")
    again = kneenlp.simulate(kneenlp.Knee.default(), f"set{n}").measured("uniform:0.5", n)
    # bit for bit on one machine; across processors the last bit of the transcendental functions
    # (libm's and NumPy's SIMD variants differ by processor) moves the equilibria by up to 5e-9
    # relative, 4e-9 mm or deg (the files' machine against an AMD EPYC): far below the 0.5 mm noise
    pd.testing.assert_frame_equal(shipped, again.reset_index(drop=True), check_exact=False, rtol=1e-7, atol=1e-7)


def test_s192803_problem_holds_the_shipped_dataset():
    assert (PROBLEMS / "s192803" / "laxity.csv").read_bytes() == resource("datasets", "s192803_laxity.csv").read_bytes()


def test_a_problem_fits_as_its_options_do(tmp_path, capsys):
    assert main(["identify", "--problem", str(PROBLEMS / "set1"), "--json"]) == 0
    by_problem = json.loads(capsys.readouterr().out)
    assert main(["identify", str(PROBLEMS / "set1" / "measured.csv"), "--knee", "default", "--noise", "uniform:0.5",
                 "--json"]) == 0
    by_options = json.loads(capsys.readouterr().out)
    assert by_problem["params"] == by_options["params"] and by_problem["success"]
    assert main(["predict", "--problem", str(PROBLEMS / "set1"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["converged"] == 7


def _copy(tmp_path: Path, name: str = "set1") -> Path:
    folder = tmp_path / name
    shutil.copytree(PROBLEMS / name, folder)
    return folder


def test_free_flags_and_bounds_of_the_table_act(tmp_path, capsys):
    """``free = false`` keeps a parameter at its value; ``bounds`` replace the kind's in the fit."""
    folder = _copy(tmp_path)
    text = (folder / "problem.toml").read_text()
    text = text.replace('"ACL.k" = {value = 10000.0, unit = "N", free = true}',
                        '"ACL.k" = {value = 10000.0, unit = "N", free = false}')
    old = '"PCL.ref_strain" = {value = -6.0, unit = "%", free = true}'
    assert old in text
    text = text.replace(old, '"PCL.ref_strain" = {value = -6.0, unit = "%", free = true, bounds = [-6.2, -5.5]}')
    (folder / "problem.toml").write_text(text)
    assert main(["identify", "--problem", str(folder), "--json"]) == 0
    fit = json.loads(capsys.readouterr().out)
    assert "ACL.k" not in fit["params"] and len(fit["params"]) == 7
    assert -0.062 - 1e-9 <= fit["params"]["PCL.ref_strain"] <= -0.055 + 1e-9  # free, it went to -6.3 %


@pytest.mark.parametrize("edit, needle", [
    (lambda t: 'colour = "red"\n' + t, "unknown key 'colour'"),
    (lambda t: t.replace('data = "measured.csv"', 'data = "nowhere.csv"'), "data"),
    (lambda t: t.replace('noise = "uniform:0.5"', 'noise = "uniform:0"'), "noise"),
    (lambda t: t.replace('strategy = "scatter"', 'strategy = "guess"'), "unknown strategy 'guess'"),
    (lambda t: t.replace('knee = "default"', 'knee = "nosuchknee"'), "knee"),
    (lambda t: t.replace('"ACL.k" = {value = 10000.0, unit = "N", free = true}',
                         '"ACL.k" = {value = 10000.0, unit = "N", free = "yes"}'), "parameters.ACL.k.free"),
    (lambda t: t.replace('"ACL.k" = {value = 10000.0, unit = "N", free = true}',
                         '"ACL.k" = {value = 10000.0, unit = "N", bounds = [2, 1]}'), "parameters.ACL.k.bounds"),
    (lambda t: t.replace('"ACL.k" = {value = 10000.0, unit = "N", free = true}',
                         '"ACL.k" = {value = 10000.0, unit = "N", bounds = [0, 5000]}'), "outside its bounds"),
    (lambda t: t.replace('"ACL.k" =', '"ACLx.k" ='), "unknown parameter 'ACLx.k'"),
    (lambda t: t.replace('"ACL.k" = {value = 10000.0,', '"ACL.k" = {value = -1.0,'), "outside the range"),
    (lambda t: t.replace('"PCL.ref_strain" = {value = -6.0,', '"PCL.ref_strain" = {value = 400.0,'),
     "PCL.ref_strain: value 400 % outside"),
    (lambda t: t.replace('"PCL.ref_strain" = {value = -6.0,', '"PCL.ref_strain" = {value = 400.0,'),
     "parameters.PCL.ref_strain: value 400 % outside"),  # the problem's own table is named, not values.
    (lambda t: t.replace('"ACL.k" = {value = 10000.0, unit = "N", free = true}',
                         '"ACL.k" = {value = 1e4, unit = "N", free = true, bounds = [-5000, 2e5]}'),
     "parameters.ACL.k.bounds: lower bound -5000 N lets ACL.k be negative"),
    (lambda t: t.replace('"ACL.k" = {value = 10000.0, unit = "N", free = true}',
                         '"ACL.k" = {value = 1e4, unit = "N", free = false, prior = {distribution = "normal", '
                         'mean = 1e4, sd = 100}}'), "parameters.ACL.k: has a prior but free = false"),
    (lambda t: t.replace('"ACL.k" = {value = 10000.0, unit = "N", free = true}',
                         'ACL.k = {value = 10000.0, unit = "N", free = true}'),
     'parameters.ACL: a parameter name with a dot must be quoted: "ACL.k"'),
    (lambda t: "multistart = 0\n" + t, "multistart: expected a whole number of starts from 1 to 1000, got 0"),
    (lambda t: "multistart = 2.5\n" + t, "multistart"),
    (lambda t: "multistart = true\n" + t, "multistart"),
    # names the command does not use are checked too, against the file's own field
    (lambda t: 'also_free = ["ACLx_femoral_attachment"]\n' + t,
     "problem.toml: also_free: unknown parameter, effect or element 'ACLx_femoral_attachment'"),
    (lambda t: 'hold_outs = ["nope"]\n' + t, "problem.toml: hold_outs: unknown hold-out 'nope'; known: "),
])
def test_bad_problem_file_is_refused(tmp_path, capsys, edit, needle):
    folder = _copy(tmp_path)
    (folder / "problem.toml").write_text(edit((folder / "problem.toml").read_text()))
    assert main(["identify", "--problem", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and "problem.toml" in err


def test_data_and_problem_together_or_neither_are_refused(capsys):
    assert main(["identify", str(PROBLEMS / "set1" / "measured.csv"), "--problem", str(PROBLEMS / "set1")]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["identify"]) == 2
    assert "--problem" in capsys.readouterr().err


def test_a_problem_names_its_calibration_options():
    """``calibrate_options``: what the file says, as keywords ``calibrate`` takes; left-out fields
    are not given (the calibration's defaults stand)."""
    import dataclasses

    from kneenlp.estimation.calibration_options import CalibrationOptions

    s192803 = ProblemFile.load(PROBLEMS / "s192803")
    options = s192803.calibrate_options()
    assert options == {"also_free": list(s192803.also_free), "starts": 16, "priors": "default", "prior_weight": 1.0}
    assert set(options) <= {f.name for f in dataclasses.fields(CalibrationOptions)}
    assert ProblemFile.load(PROBLEMS / "set1").calibrate_options() == {"priors": "none"}


@pytest.mark.slow
def test_s192803_problem_is_the_calibration_with_what_the_held_out_error_accepts(capsys):
    """The shipped problem's parameter table is the calibration's default written out, its
    also_free the effects the held-out error accepts, its starts those of the global search: the
    same fit as those options give."""
    problem = ProblemFile.load(PROBLEMS / "s192803")
    assert problem.also_free and problem.strategy == "calibration" and problem.starts == 16
    assert main(["identify", "--problem", str(PROBLEMS / "s192803"), "--json"]) == 0
    by_problem = json.loads(capsys.readouterr().out)
    assert main(["identify", str(resource("datasets", "s192803_laxity.csv")), "--knee", "s192803", "--also-free",
                 ",".join(problem.also_free), "--starts", "16", "--json"]) == 0
    by_options = json.loads(capsys.readouterr().out)
    assert list(by_problem["params"]) == list(by_options["params"])
    for name, value in by_options["params"].items():
        assert np.isclose(by_problem["params"][name], value, rtol=1e-9, atol=1e-12), name


def test_held_out_judge_is_for_real_experiments(capsys):
    assert main(["diagnose", "--problem", str(PROBLEMS / "set1"), "--held-out", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--held-out" in err
    assert main(["identify", "--problem", str(PROBLEMS / "set1"), "--held-out"]) == 2
    assert "--held-out" in capsys.readouterr().err


@pytest.mark.parametrize("entry, needle", [
    ('{value = 30.0, unit = "1", free = true,', "ACLam.k_scale: value 30 outside the range of a stiffness scale "
                                                "of a bundle group [0, 20]\n"),
    ('{value = 1.0, unit = "1", free = true, bounds = [-2, 5],', "ACLam.k_scale.bounds: lower bound -2 lets "
                                                                 "ACLam.k_scale be negative"),
])
def test_a_dimensionless_parameter_out_of_range_is_named_without_a_bare_unit(tmp_path, capsys, entry, needle):
    """A bundle group's stiffness scale: its range and a bound that lets it go negative (16 of 25
    trials failed with k_scale = -1, the cause never named) are refused, and the unit "1" is not printed."""
    folder = tmp_path / "s192803"
    shutil.copytree(PROBLEMS / "s192803", folder)
    text = (folder / "problem.toml").read_text()
    old = '"ACLam.k_scale" = {value = 1.0, unit = "1", free = true,'
    assert old in text
    (folder / "problem.toml").write_text(text.replace(old, f'"ACLam.k_scale" = {entry}'))
    assert main(["identify", "--problem", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and " 1 " not in err and "problem.toml: parameters." in err
