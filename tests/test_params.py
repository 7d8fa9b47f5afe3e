"""Parameters: one object per parameter (value, unit, bounds, vary, prior, tie), made by the model,
given to identify, written to and read from a problem file's table; ties checked against oracles."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.model import ties
from kneenlp.model.parameters import read_entries
from kneenlp.model.priors import Prior


@pytest.fixture(scope="module")
def model():
    return KneeModel.of(kneenlp.Knee.named("synthetic"))


def data_of(model, tmp_path, parameters=None, noise="none", seed=0, protocol="set1"):
    path = tmp_path / f"{protocol}_{seed}.csv"
    kneenlp.simulate(model, protocol, parameters=parameters).measured(noise, seed).to_csv(path, index=False)
    return read_measured(path)


def test_make_params_gives_every_parameter_with_its_value_unit_bounds_and_default_vary(model):
    params = model.make_params()
    assert list(params) == model.parameter_names
    assert params.free == IdentificationProblem(model, (), list(params.free)).free
    theta = model.theta()
    for name, p in params.items():
        assert p.value == theta[model.index(name)] and (p.min, p.max) == model.parameter(name).bounds
    assert params["ACL.ref_strain"].unit == "%" and params["contact.modulus"].unit == "GN/m^3"
    assert all(p.prior is None for p in params.values())
    with_priors = model.make_params(priors="default")
    assert with_priors["ACL.k"].prior == model.parameter("ACL.k").default_prior(theta[model.index("ACL.k")])
    with pytest.raises(InputError, match="unknown parameter 'ACLx'"):
        params["ACLx"]
    with pytest.raises(InputError, match="unknown priors"):
        model.make_params(priors="flat")


def test_a_parameter_table_reads_back_to_the_same_parameters(model, tmp_path):
    params = model.make_params(priors="default").only(["ACL.k", "MCL.ref_strain"])
    params["ACL.k"].set(value=9.5, unit="kN", min=2, max=50)
    params["MCL.k"].set(expr="2 * LCL.k ** 1")
    table = params.to_table()
    assert set(table) == {"ACL.k", "MCL.ref_strain", "MCL.k"}
    text = tomli_w.dumps({"parameters": table})
    import tomllib

    entries = read_entries(tomllib.loads(text)["parameters"], "p.toml", "parameters")
    knee = model.knee.with_parameters(model.knee.parameters.with_entries(entries))
    back = KneeModel.of(knee).make_params(priors="declared")
    for name in table:
        a, b = params[name], back[name]
        assert (a.vary, a.expr) == (b.vary, b.expr), name
        assert np.allclose([a.min, a.max], [b.min, b.max], rtol=1e-12)
        assert (a.prior is None or not a.vary) == (b.prior is None)
        if b.prior is not None:
            assert a.prior.shape == b.prior.shape and np.isclose(a.prior.mean, b.prior.mean, rtol=1e-12)
    assert back.valuesdict()["MCL.k"] == pytest.approx(2 * back["LCL.k"].value)  # the knee applies its tie
    assert back["ACL.k"].value == pytest.approx(9500.0)


def test_identify_with_params_is_identify_with_the_same_choices(model, tmp_path):
    data = data_of(model, tmp_path, noise="uniform:0.5", seed=3)
    by_names = kneenlp.identify(model, data, free=["ACL.k", "PCL.k", "MCL.k"], seed=1)
    params = model.make_params().only(["ACL.k", "PCL.k", "MCL.k"])
    by_params = kneenlp.identify(model, data, params, seed=1)
    assert by_params.free == by_names.free
    assert by_params.params == by_names.params
    with pytest.raises(InputError, match="not by free"):
        kneenlp.identify(model, data, params, free=["ACL.k"])
    with pytest.raises(TypeError, match="method='nested'"):
        kneenlp.identify(model, data, "nested")


def test_bounds_and_priors_of_params_are_the_fits(model, tmp_path):
    data = data_of(model, tmp_path)
    params = model.make_params().only(["ACL.k", "PCL.k"])
    truth = params["ACL.k"].value
    params["ACL.k"].set(value=0.5 * truth, max=0.8 * truth)  # the truth beyond the bound: the fit ends on it
    fit = kneenlp.identify(model, data, params, seed=2)
    assert fit.params["ACL.k"] == pytest.approx(0.8 * truth, rel=1e-6)
    params = model.make_params().only(["ACL.k"])
    params["ACL.k"].set(prior=Prior("normal", 0.5 * truth, 1e-3 * truth))  # a prior far stronger than the data
    fit = kneenlp.identify(model, data, params, seed=2)
    assert fit.params["ACL.k"] == pytest.approx(0.5 * truth, rel=0.01)


def test_a_tie_fits_like_the_model_it_defines(model, tmp_path):
    """Data made with MCL.k = 1.5 LCL.k, fitted with that tie and LCL.k free: the truth, to the
    solver's tolerance; the tie's sensitivity equals the chain rule through both stiffnesses
    (the oracle: the sensitivities of the untied problem)."""
    lcl = 1.2 * model.theta()[model.index("LCL.k")]
    truth = {"LCL.k": lcl, "MCL.k": 1.5 * lcl}
    data = data_of(model, tmp_path, parameters=truth, protocol="set3")
    params = model.make_params().only(["LCL.k", "ACL.k"])
    params["MCL.k"].set(expr="1.5 * LCL.k")
    fit = kneenlp.identify(model, data, params, seed=4)
    assert fit.free == ["ACL.k", "LCL.k"]
    assert fit.params["LCL.k"] == pytest.approx(lcl, rel=1e-5)
    assert fit.theta[model.index("MCL.k")] == pytest.approx(1.5 * fit.params["LCL.k"], rel=1e-12)
    tied = fit.problem
    plain = IdentificationProblem(model, tied.trials, ["ACL.k", "LCL.k", "MCL.k"], tied.measured)
    s_tied = tied.sensitivities(fit.q_pred, fit.theta)
    s_plain = plain.sensitivities(fit.q_pred, fit.theta)
    assert np.allclose(s_tied[:, 1], s_plain[:, 1] + 1.5 * s_plain[:, 2], rtol=1e-9, atol=1e-12)
    assert np.allclose(s_tied[:, 0], s_plain[:, 0], rtol=1e-12, atol=0)


def test_ties_are_checked_in_one_line():
    known = ["ACL.k", "PCL.k", "MCL.k"]
    assert ties.names_in("2 * ACL.k + exp(PCL.k) - MCL.k / 3") == ["ACL.k", "PCL.k", "MCL.k"]
    assert ties.tied({"ACL.k": 2.0, "PCL.k": 0.0, "MCL.k": 1.0}, {"MCL.k": "ACL.k ** 2 + sqrt(ACL.k * 8)"}) \
        == {"ACL.k": 2.0, "PCL.k": 0.0, "MCL.k": 8.0}
    assert ties.ordered({"MCL.k": "PCL.k", "PCL.k": "2 * ACL.k"}, known) == ["PCL.k", "MCL.k"]
    with pytest.raises(InputError, match=r"cycle: MCL\.k -> PCL\.k -> MCL\.k"):
        ties.ordered({"MCL.k": "PCL.k", "PCL.k": "MCL.k"}, known)
    with pytest.raises(InputError, match=r"unknown parameter in a tie 'ACLx\.k'"):
        ties.ordered({"MCL.k": "ACLx.k"}, known)
    for bad in ("__import__('os')", "ACL.k if 1 else 2", "[ACL.k]", "2 *", "True * ACL.k"):
        with pytest.raises(InputError, match="tie"):
            ties.names_in(bad)


def test_a_tied_parameter_cannot_vary_or_take_a_prior(model):
    params = model.make_params()
    params["MCL.k"].set(expr="LCL.k")
    assert not params["MCL.k"].vary
    params["MCL.k"].vary = True
    with pytest.raises(InputError, match="cannot vary"):
        params.check()
    params["MCL.k"].set(vary=False, prior=Prior("normal", 1e4, 1e3))
    with pytest.raises(InputError, match="takes no prior"):
        params.check()
    with pytest.raises(InputError, match="outside its bounds"):
        model.make_params()["ACL.k"].set(value=-1.0).check()


def test_effects_and_elements_are_freed_by_name(model):
    params = model.make_params().only([]).freed(["ACL.k", "posterior_capsule"])
    assert params.free == ["ACL.k", *model.effect("posterior_capsule").free_names()]
    with pytest.raises(InputError, match="unknown parameter, effect or element 'capsule'"):
        params.freed(["capsule"])


def test_a_calibration_refuses_a_fixed_value_it_would_not_start_from():
    from kneenlp.estimation.choice import from_params

    model = KneeModel.of(kneenlp.Knee.named("synthetic"))
    params = model.make_params().only(["ACL.k"])
    params["ACL.k"].set(value=12.0, unit="kN")
    free, priors, start, _ = from_params(model, params)
    assert free == ["ACL.k"] and priors == {"ACL.k": None} and start == {"ACL.k": 12e3}
    params["PCL.k"].set(value=1.0, unit="kN")
    with pytest.raises(InputError, match=r"PCL\.k is fixed at another value than the knee's"):
        from_params(model, params)
    with pytest.raises(InputError, match="not by free"):
        from_params(model, params, free=["ACL.k"])


@pytest.mark.slow
def test_a_calibration_of_the_real_knee_with_a_tie():
    """S192803 calibrated with one stiffness scale for the anterior and middle superficial MCL
    (``MCLm.k_scale = MCLa.k_scale``): the fit converges, the tie holds at its end, the tied scale
    is not fitted, and its poses and parameters give the same misfit in the untied problem (the
    tie reached the NLP's parameter vector, not a copy of it)."""
    from kneenlp.base.resources import resource
    from kneenlp.estimation.calibrate import calibrate

    model = KneeModel.of(kneenlp.Knee.named("s192803"))
    data = read_measured(resource("datasets", "s192803_laxity.csv"))
    base = calibrate(model, data, starts=1, keep_outliers=True)
    params = model.make_params(priors="default").only(base.fit.free)
    for name in base.fit.free:
        params[name].set(prior=base.fit.problem.priors.get(name))
    params["MCLm.k_scale"].set(expr="MCLa.k_scale")
    tied = calibrate(model, data, params=params, starts=1, keep_outliers=True)
    assert tied.fit.success and "MCLm.k_scale" not in tied.fit.free
    theta = tied.fit.theta
    assert theta[model.index("MCLm.k_scale")] == pytest.approx(theta[model.index("MCLa.k_scale")], rel=1e-12)
    assert base.fit.problem.objective(tied.fit.q_pred, theta) == pytest.approx(tied.fit.objective, rel=1e-12)
