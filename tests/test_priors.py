"""Priors in the one NLP: the prior type, the MAP estimate, its Laplace covariance and bad priors."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from scipy import stats

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.cli import main
from kneenlp.estimation.identify import identify
from kneenlp.estimation.solve import reduced_fit
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.model.parameters import ParameterSet
from kneenlp.model.priors import Prior


def measured(knee, protocol, noise, seed, tmp_path):
    path = tmp_path / f"{protocol}_{seed}.csv"
    kneenlp.simulate(knee, protocol).measured(noise, seed).to_csv(path, index=False)
    return read_measured(path)


def test_prior_z_and_interval_are_the_closed_forms():
    normal, lognormal = Prior("normal", 0.02, 0.03), Prior("lognormal", 5000.0, 0.3)
    assert normal.z(0.08) == pytest.approx(2.0)
    assert lognormal.z(5000.0 * math.exp(0.6)) == pytest.approx(2.0)
    lo, hi = normal.interval()
    assert (lo, hi) == pytest.approx((0.02 - 3 * 0.03, 0.02 + 3 * 0.03), rel=1e-3)
    lo, hi = lognormal.interval(0.95)
    assert stats.lognorm(0.3, scale=5000.0).cdf(hi) - stats.lognorm(0.3, scale=5000.0).cdf(lo) == pytest.approx(0.95)
    with pytest.raises(ValueError):
        Prior("normal", 0.0, 0.0)
    with pytest.raises(ValueError):
        Prior("lognormal", -1.0, 0.3)


def test_map_estimate_of_the_nlp_is_the_reduced_methods(knee, model, tmp_path):
    """The priors enter the NLP's objective and the reduced-space residuals as the same rows: both
    solvers reach one MAP optimum (an independent route to the same number)."""
    data = measured(knee, "set1", "uniform:0.5", 2, tmp_path)
    fit = identify(knee, data, seed=2, noise="uniform:0.5", priors="default")
    assert fit.success, fit.report()
    assert fit.prior_objective > 0
    problem = fit.problem
    other = reduced_fit(problem, fit.start, tol=1e-12, max_evaluations=200)
    assert other.success
    assert fit.map_objective <= other.map_objective * (1 + 1e-6)
    assert other.map_objective == pytest.approx(fit.map_objective, rel=1e-6)
    # the MAP moves towards the priors' centres: its own objective is above the data-only fit's
    data_only = identify(knee, data, seed=2, noise="uniform:0.5")
    assert data_only.objective <= fit.objective + 1e-9


def test_priors_decide_where_data_do_not(knee, tmp_path):
    """A tight prior holds its parameter at the prior's mean; a very wide one leaves the data-only fit."""
    data = measured(knee, "set1", "uniform:0.5", 4, tmp_path)
    data_only = identify(knee, data, seed=4, noise="uniform:0.5")
    tight = identify(knee, data, seed=4, noise="uniform:0.5",
                     priors={"ACL.k": Prior("lognormal", 7000.0, 1e-4)})
    assert tight.params["ACL.k"] == pytest.approx(7000.0, rel=2e-3)
    wide = identify(knee, data, seed=4, noise="uniform:0.5",
                    priors={n: Prior("normal", knee.parameters[n], 1e3 * abs(knee.parameters[n]))
                            for n in data_only.free})
    for n in data_only.free:
        assert abs(wide.params[n] - data_only.params[n]) <= 0.01 * data_only.stderr[n]


def test_laplace_covariance_is_the_posterior_of_the_linearised_problem(knee, tmp_path):
    data = measured(knee, "set1", "uniform:0.5", 5, tmp_path)
    fit = identify(knee, data, seed=5, noise="uniform:0.5", priors="default")
    sigma2 = 0.5**2 / 3
    assert fit.problem.prior_weight == pytest.approx(sigma2)
    # by hand: sigma^2 (S'S + sigma^2 D' P D)^-1 with P the priors' precisions (SI) and D the transform
    S = fit.sensitivity
    prec = []
    for n in fit.free:
        prior = fit.problem.priors[n]
        d = 1 / fit.params[n] if prior.log else 1.0
        prec.append(d**2 / prior.sd**2)
    expected = sigma2 * np.linalg.inv(S.T @ S + sigma2 * np.diag(prec))
    assert np.allclose(fit.covariance, expected, rtol=1e-6)
    # every direction has a prior: nothing undetermined
    assert np.all(np.isfinite(np.diag(fit.covariance)))


def test_bad_priors_are_refused_with_the_parameters_name(model, tmp_path):
    trials_csv = tmp_path / "d.csv"
    kneenlp.simulate(model.knee, "set1").measured("none", 0).to_csv(trials_csv, index=False)
    data = read_measured(trials_csv)
    cases = {
        "ACL.ref_strain": Prior("lognormal", 0.05, 0.3),  # can be negative
        "ACL.k": Prior("normal", 2e5, 100.0),  # mean outside the bounds
    }
    for name, prior in cases.items():
        with pytest.raises(InputError, match=name.replace(".", r"\.")):
            IdentificationProblem.from_data(model, data, priors={name: prior})
    with pytest.raises(InputError, match="ACLx"):
        IdentificationProblem.from_data(model, data, priors={"ACLx.k": Prior("normal", 1.0, 1.0)})
    with pytest.raises(InputError, match="not free"):
        IdentificationProblem.from_data(model, data, priors={"ACL.lin_strain": Prior("normal", 0.03, 0.01)})
    with pytest.raises(TypeError, match=r"from_data\(\) got unexpected keyword argument\(s\): prior"):
        IdentificationProblem.from_data(model, data, prior={"ACL.k": Prior("normal", 1.0, 1.0)})


@pytest.mark.parametrize("entry, field", [
    ('"ACL.k" = {unit = "N", prior = {distribution = "normal", mean = 5000, sd = 0}}', "sd"),
    ('"ACL.k" = {unit = "N", prior = {distribution = "normal", mean = 5000, sd = -3}}', "sd"),
    ('"ACL.ref_strain" = {unit = "%", prior = {distribution = "lognormal", median = 5, sd_log = 0.3}}',
     "ACL.ref_strain"),
    ('"ACL.k" = {unit = "N", prior = {distribution = "normal", mean = 500000, sd = 100}}', "ACL.k"),
    ('"ACLx.k" = {unit = "N", prior = {distribution = "normal", mean = 5000, sd = 100}}', "ACLx"),
    ('"ACL.k" = {unit = "N", prior = {distribution = "cauchy", mean = 5000, sd = 100}}', "ACL.k"),
])
def test_bad_prior_in_a_parameter_file_is_one_line_exit_2(tmp_path, capsys, entry, field):
    base = (kneenlp.base.resources.resource("parameters", "table1.toml")).read_text()
    path = tmp_path / "p.toml"
    path.write_text(base + "\n[values]\n" + entry + "\n")
    code = main(["simulate", "--protocol", "set1", "--parameters", str(path), "--no-plots"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and field in err and "Traceback" not in err


def test_a_prior_declared_in_the_parameter_file_replaces_the_default(tmp_path):
    base = (kneenlp.base.resources.resource("parameters", "table1.toml")).read_text()
    path = tmp_path / "p.toml"
    path.write_text(base + '\n[values]\n"ACL.k" = {unit = "kN", prior = {distribution = "normal", '
                           'mean = 6, sd = 0.5}}\n')
    params = ParameterSet.load(path)
    assert params.priors["ACL.k"] == Prior("normal", 6000.0, 500.0, source=str(path))
    table1 = ParameterSet.load(kneenlp.base.resources.resource("parameters", "table1.toml"))
    assert params.values["ACL.k"] == table1.values["ACL.k"]  # the value stays the file's own


def test_laplace_intervals_cover_truths_drawn_from_the_prior():
    """The fast version of benchmarks/bench_coverage.py: 20 experiments of Set 1 on the synthetic
    knee, each truth drawn from the priors the MAP uses; the 95 % Laplace intervals cover it in
    85-99.5 % of the 160 (parameter, experiment) cases (a fixed seed: the same cases every run)."""
    from kneenlp.studies.coverage import coverage

    result = coverage(kneenlp.Knee.named("synthetic"), "set1", 20, seed=1)
    assert not result.failed and result.covered.shape == (20, 8)
    assert 0.85 <= result.overall() <= 0.995


@pytest.mark.slow
def test_a_calibration_from_several_starts_keeps_the_lowest_and_lists_them():
    """``multistart`` on a real experiment's calibration: the first start is the single-start fit,
    the kept one the lowest converged MAP objective, and the note lists every start's end."""
    import re

    from kneenlp.base.resources import resource
    from kneenlp.experiment.kneemodel import KneeModel

    model = KneeModel.of(kneenlp.Knee.named("s192803"))
    data = read_measured(resource("datasets", "s192803_laxity.csv"))
    one = identify(model, data, starts=1)  # the local chain; its further starts: multistart
    several = identify(model, data, multistart=2)
    m = re.search(r"2 starts .*: MAP objectives (.*); start (\d) kept", several.message)
    assert m, several.message
    ends = [float(v.split()[0]) for v in m.group(1).split(", ")]
    assert math.isclose(ends[0], one.map_objective, rel_tol=1e-5)  # noted to 6 digits
    converged = [e for e, text in zip(ends, m.group(1).split(", "), strict=True) if "not converged" not in text]
    assert several.success and math.isclose(several.map_objective, min(converged), rel_tol=1e-5)
    assert several.map_objective <= one.map_objective * (1 + 1e-9)
    shared = identify(model, data, multistart=2, workers=2)  # the starts in two processes: the same ends
    assert shared.message == several.message and shared.map_objective == several.map_objective


@pytest.mark.slow
def test_a_calibration_at_a_bound_is_read_back_by_predict(tmp_path):
    """A calibration whose meniscus stiffness may end at its bound 0 (IPOPT relaxes bounds by 1e-8,
    so it ended at -1e-7 N/mm and predict refused the written file; on some processors the
    calibration ends at the bound, on others just inside it): the written values lie within their
    bounds, and predict reads the calibration identify wrote."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "problems" / "s192803"
    effects = ("tibial_origin,femoral_origin,tibial_axes,PCLal_femoral_attachment,ACLam_femoral_attachment,"
               "PCLal_bundles,PFL_tibial_attachment,meniscus")
    assert main(["identify", "--problem", str(root), "--also-free", effects, "--out", str(tmp_path / "cal")]) == 0
    text = (tmp_path / "cal" / "calibrated.toml").read_text()
    written = re.search(r'\[values\."meniscus\.k"\]\nvalue = (\S+)\n', text)
    assert written and float(written.group(1)) >= 0.0
    # read, not refused (exit 2); exit 1 when a trial has no equilibrium there (the outlier the
    # calibration set aside may have none)
    assert main(["predict", str(root / "laxity.csv"), "--knee", "s192803", "--parameters",
                 str(tmp_path / "cal" / "calibrated.toml"), "--out", str(tmp_path / "pred")]) in (0, 1)
    assert (tmp_path / "pred" / "predicted.csv").is_file()
