"""Simultaneous identification: recovery, optimality, model equality, diagnostics."""

from __future__ import annotations

import json

import numpy as np
import pytest

import kneenlp
from kneenlp.base.conventions import coords_to_user
from kneenlp.cli import main
from kneenlp.estimation.identify import identify
from kneenlp.experiment.measured import MeasuredData, read_measured
from kneenlp.solvers.forward import ForwardSolver


def measured(knee, protocol, noise, seed, tmp_path):
    res = kneenlp.simulate(knee, protocol)
    path = tmp_path / f"{protocol}_{seed}.csv"
    res.measured(noise, seed).to_csv(path, index=False)
    return read_measured(path)


def objective_at(model, data, theta):
    sols = ForwardSolver(model).solve(data.trials, theta)
    assert all(s.converged for s in sols)
    pred = coords_to_user(np.array([s.q for s in sols]))
    return float(np.sum((pred - data.q_user) ** 2))


def rel_errors(fit, truth):
    return {n: abs(fit.params[n] - truth[n]) / abs(truth[n]) for n in fit.free}


def test_zero_noise_set1_recovers_table1_from_paper_scatter(knee, tmp_path):
    data = measured(knee, "set1", "none", 0, tmp_path)
    fit = identify(knee, data, seed=11)
    assert fit.success, fit.report()
    assert fit.start != {n: knee.parameters[n] for n in fit.free}  # really started elsewhere
    assert max(rel_errors(fit, knee.parameters.values).values()) <= 1e-6
    assert fit.identifiable and fit.rank == 8
    assert fit.max_residual <= 1e-6


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["set2", "set3", "set4"])
def test_zero_noise_sets_2_to_4_recover_table1(knee, tmp_path, protocol):
    data = measured(knee, protocol, "none", 0, tmp_path)
    fit = identify(knee, data, seed=5)
    assert fit.success, fit.report()
    assert max(rel_errors(fit, knee.parameters.values).values()) <= 1e-6


def test_noisy_fit_is_optimal_and_consistent_with_forward_model(knee, model, tmp_path):
    data = measured(knee, "set1", "uniform:0.5", 3, tmp_path)
    fit = identify(knee, data, seed=3, noise="uniform:0.5")
    assert fit.success, fit.report()
    assert fit.max_residual <= 1e-6
    # sanity of optimality: not worse than the truth
    assert fit.objective <= objective_at(model, data, model.theta()) + 1e-9
    # the NLP's residual is the forward model's: re-simulate at the estimate
    warm = {t.id: q for t, q in zip(data.trials, fit.q_pred, strict=True)}
    again = ForwardSolver(model).solve(data.trials, fit.theta, warm)
    assert np.allclose(coords_to_user(np.array([s.q for s in again])), coords_to_user(fit.q_pred), atol=1e-6)
    # covariance from the given noise: uniform +-0.5 has variance 0.25/3
    assert np.allclose(fit.noise_variance, 0.25 / 3)
    assert all(np.isfinite(v) and v > 0 for v in fit.stderr.values())


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["set1", "set2", "set3", "set4"])
def test_twenty_noise_seeds_converge(knee, model, tmp_path, protocol):
    theta_true = model.theta()
    for seed in range(20):
        data = measured(knee, protocol, "uniform:0.5", seed, tmp_path)
        fit = identify(knee, data, seed=seed)
        assert fit.success, (seed, fit.report())
        assert fit.max_residual <= 1e-6
        assert fit.objective <= objective_at(model, data, theta_true) * (1 + 1e-9) + 1e-9, seed


def test_rank_deficient_data_says_so(knee, tmp_path):
    full = measured(knee, "set1", "none", 0, tmp_path)
    one = MeasuredData(full.trials[:1], full.q[:1], None, "one-trial")
    fit = identify(knee, one, seed=1, free=["ACL.k", "ACL.ref_strain", "PCL.k", "PCL.ref_strain",
                                            "MCL.k", "MCL.ref_strain", "LCL.k", "LCL.ref_strain"])
    assert fit.rank <= 5 and not fit.identifiable
    assert fit.unidentifiable_directions()
    assert any(not np.isfinite(v) for v in fit.stderr.values())
    assert "NOT ALL PARAMETERS IDENTIFIABLE" in fit.report()


def test_free_parameters_by_name(knee, tmp_path):
    data = measured(knee, "set1", "none", 0, tmp_path)
    fit = identify(knee, data, free=["ACL.k", "contact.modulus"], start={"ACL.k": 9000.0, "contact.modulus": 9e9})
    assert fit.success and fit.free == ["ACL.k", "contact.modulus"]
    assert fit.params["ACL.k"] == pytest.approx(10000.0, rel=1e-6)
    assert fit.params["contact.modulus"] == pytest.approx(1e10, rel=1e-6)
    with pytest.raises(kneenlp.InputError, match=r"unknown parameter 'ACLx\.k'"):
        identify(knee, data, free=["ACLx.k"])
    assert not fit.at_bounds() and "AT ITS BOUND" not in fit.report()


def test_a_parameter_on_its_bound_is_named(knee, tmp_path):
    """Measured anterior translations 15 mm off: the registration's bound is 10 mm, so the fit
    stops on it, and the report and the summary say so instead of giving a standard error."""
    data = measured(knee, "set1", "none", 0, tmp_path)
    shifted = MeasuredData(data.trials, data.q + np.array([0.0, 0.0, 0.0, 0.015, 0.0]), data.protocol, "shifted")
    fit = identify(knee, shifted, free=["ACL.k", "registration.anterior_translation"])
    assert fit.params["registration.anterior_translation"] == pytest.approx(0.010, abs=1e-9)
    assert fit.at_bounds() == ["registration.anterior_translation"]
    line = next(ln for ln in fit.report().splitlines() if ln.strip().startswith("registration.anterior"))
    assert "AT ITS BOUND" in line and "+/-" not in line
    assert fit.summary()["at_bounds"] == ["registration.anterior_translation"]


def test_cli_identify_json(knee, tmp_path, capsys):
    res = kneenlp.simulate(knee, "set1")
    path = tmp_path / "m.csv"
    res.measured("uniform:0.5", 2).to_csv(path, index=False)
    code = main(["identify", "--knee", "synthetic", str(path), "--json", "--noise", "uniform:0.5"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert {"params", "stderr", "objective", "iterations", "seconds", "max_residual", "status"} <= set(out)
    assert set(out["params"]) == {f"{lig}.{k}" for lig in knee.ligaments for k in ("k", "ref_strain")}


def test_cli_identify_bad_data(knee, tmp_path, capsys):
    res = kneenlp.simulate(knee, "set1")
    good = res.measured("uniform:0.5", 2)
    cases = {
        "missing_trial": good.iloc[:-1],
        "nan": good.assign(anterior_translation_mm=[np.nan, *good["anterior_translation_mm"][1:]]),
        "units": good.rename(columns={"varus_rotation_deg": "varus_rotation_rad"}),
        "unknown_trial": good.assign(trial=["mystery", *good["trial"][1:]]),
    }
    for name, df in cases.items():
        path = tmp_path / f"{name}.csv"
        df.to_csv(path, index=False)
        code = main(["identify", "--knee", "synthetic", str(path)])
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.startswith("kneenlp: error:") and "\n" not in err, (name, err)
        assert str(path) in err


def test_early_hand_over_from_reduced_space_reaches_the_reduced_optimum(tmp_path):
    """The rescue of a failed start stops the reduced-space fit early and lets IPOPT finish
    (:func:`reduced_then_nlp`): it must reach a minimum no worse than the reduced fit run to its
    tolerance, with fewer reduced evaluations.  Set 4 from cartilage four times softer (where
    IPOPT alone wandered for 150 iterations), from the paper's scattered start; there the former
    rescue (reduced fit to its tolerance, then IPOPT) failed: IPOPT wandered off to objective 4705."""
    from kneenlp.estimation.solve import reduced_then_nlp
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.experiment.problem import IdentificationProblem
    from kneenlp.solvers.reduced import reduced_least_squares

    knee = kneenlp.Knee.named("synthetic")
    path = tmp_path / "soft.csv"
    kneenlp.simulate(knee, "set4", parameters={"contact.modulus": 2.5e9}).measured("uniform:0.5", 3000).to_csv(
        path, index=False)
    problem = IdentificationProblem.from_data(KneeModel.of(knee), read_measured(path), None, noise="uniform:0.5")
    start = problem.scatter(np.random.default_rng(3000))
    early, finished, evaluations = reduced_then_nlp(problem, start)
    full = reduced_least_squares(problem, start)
    assert early.success
    # the fit holds every solve it took, the judged one last, and its counts are theirs
    assert early.solves[0].solver == "reduced" and early.solves[-1] is early.result and len(early.solves) >= 2
    assert early.iterations == sum(r.iterations for r in early.solves)
    assert early.seconds == pytest.approx(sum(r.seconds for r in early.solves))
    # no worse than the reduced fit run to its own tolerance (here far worse: it stalled at 138.0
    # against 48.8), and a minimum in reduced space too: the reduced fit started there stays
    assert early.objective <= full.objective * (1 + 1e-7)
    there = reduced_least_squares(problem, problem.values(early.theta), q0=early.q_pred)
    assert there.objective == pytest.approx(early.objective, rel=1e-6)
    for n in problem.free:
        assert there.values[n] == pytest.approx(early.params[n], rel=1e-3), n
    # fewer reduced evaluations when IPOPT finishes from the early stop; the path is
    # chaotic: since the tibial axes changed the NLP Hessian's rounding (1e-12 relative), IPOPT
    # from the early stop runs out of iterations here, and the rescue finishes the reduced fit first
    # and reaches the same minimum from there, at no more evaluations than the reduced fit alone
    assert evaluations < full.evaluations if finished is None else evaluations <= full.evaluations


def test_set4_start_that_wandered_converges_without_rescue(tmp_path):
    """Set 4 on the default knee, noise seed 186 (the paper's scatter): under IPOPT's own ceiling of
    the equilibrium residual (``theta_max_fact`` 1e4) the first steps broke equilibrium by 20-200 N,
    the restoration phase failed after 150 iterations and the reduced-space rescue took 12 s.  With
    the large-protocol ceiling (:data:`kneenlp.solvers.nlp.THETA_MAX_FACT`) IPOPT converges alone."""
    from kneenlp.solvers.nlp import THETA_MAX_FACT, ipopt_trial_options

    assert ipopt_trial_options(60) == {"obj_scaling_factor": 0.1, "theta_max_fact": THETA_MAX_FACT}
    assert ipopt_trial_options(13) == {"obj_scaling_factor": 1.0}  # small protocols: IPOPT's own
    knee = kneenlp.Knee.default()
    fit = identify(knee, measured(knee, "set4", "uniform:0.5", 186, tmp_path), seed=186, noise="uniform:0.5")
    assert fit.success and fit.starts == 1 and "rescued" not in fit.message, fit.message
    assert fit.iterations <= 40


@pytest.mark.parametrize("entry", ["identify", "calibrate", "diagnose", "base_fit", "design", "cross_validate",
                                   "run_study", "coverage"])
def test_an_entry_point_refuses_a_keyword_it_does_not_take_by_name(entry):
    """Each documented entry point checks its keyword options in one place, before any work."""
    from kneenlp.adequacy.basefit import base_fit
    from kneenlp.adequacy.diagnosis import diagnose
    from kneenlp.design.optimal import design
    from kneenlp.estimation.calibrate import calibrate
    from kneenlp.studies.coverage import coverage
    from kneenlp.studies.study import run_study
    from kneenlp.validation.crossval import cross_validate

    calls = {"identify": lambda: identify(None, "absent.csv", seeds=1),
             "calibrate": lambda: calibrate(None, None, seeds=1), "diagnose": lambda: diagnose(None, seeds=1),
             "base_fit": lambda: base_fit(None, None, "uniform:0.5", seeds=1),
             "design": lambda: design(None, seeds=1), "cross_validate": lambda: cross_validate(None, None, seeds=1),
             "run_study": lambda: run_study(None, "absent", seeds=1),
             "coverage": lambda: coverage(None, "set1", seeds=1)}
    with pytest.raises(TypeError, match=rf"^{entry}\(\) got unexpected keyword argument\(s\): seeds$"):
        calls[entry]()
