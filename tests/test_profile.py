"""Profile-likelihood intervals (``kneenlp.estimation.profile``, ``identify --profile``): checked
against an independent refit (the simultaneous NLP with the parameter held), against a prior's
closed-form interval where the data say little, and at a bound."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.cli import main
from kneenlp.estimation.profile import profile
from kneenlp.experiment.measured import read_measured

NOISE = "uniform:0.5"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("profile") / "set1.csv"
    kneenlp.simulate(kneenlp.Knee.named("synthetic"), "set1").measured(NOISE, 3).to_csv(path, index=False)
    return read_measured(path)


def test_interval_ends_where_an_independent_refit_rises_by_the_threshold(data):
    """At each end of the 95 % interval of ACL.ref_strain, the least-squares objective refitted by
    IPOPT (the other parameter free, this one held) lies chi2_1(0.95) = 3.84 noise variances above
    the fit's: the profile (reduced-space refits, interpolated) is the likelihood-ratio interval."""
    knee = kneenlp.Knee.named("synthetic")
    fit = kneenlp.identify(knee, data, noise=NOISE, free=["ACL.k", "ACL.ref_strain"])
    (iv,) = profile(fit, ["ACL.ref_strain"])
    s2 = kneenlp.NoiseModel.parse(NOISE).std ** 2
    assert iv.lower < fit.params["ACL.ref_strain"] < iv.upper and not (iv.lower_at_bound or iv.upper_at_bound)
    for end in (iv.lower, iv.upper):
        held = kneenlp.identify(knee, data, noise=NOISE, free=["ACL.k"], fixed={"ACL.ref_strain": end},
                                start={"ACL.k": fit.params["ACL.k"]}, strategy="scatter")
        assert held.success
        assert (held.objective - fit.objective) / s2 == pytest.approx(stats.chi2.ppf(0.95, 1), abs=0.3)
    # nearly linear in a reference strain: close to the Laplace (Wald) interval
    sd = fit.stderr["ACL.ref_strain"]
    assert iv.upper - iv.lower == pytest.approx(2 * 1.96 * sd, rel=0.15)


def test_a_parameter_the_data_barely_see_has_its_priors_interval_and_stops_at_its_bound(data):
    """The synthetic knee has no ALL (k = 0): its stiffness barely moves the poses of Set 1, so its
    MAP profile is its prior's (normal about 0, 1.96 sd above) and, below, the bound k >= 0 ends
    the interval (flagged)."""
    fit = kneenlp.identify(kneenlp.Knee.named("synthetic"), data, noise=NOISE, priors="default",
                           free=["ACL.k", "ACL.ref_strain", "ALL.k"])
    (iv,) = profile(fit, ["ALL.k"])
    prior = fit.problem.priors["ALL.k"]
    assert iv.lower == 0.0 and iv.lower_at_bound and not iv.upper_at_bound
    assert iv.upper == pytest.approx(prior.interval(0.95)[1], rel=0.05)
    assert iv.record()["lower_at_bound"] and "(bound)" in iv.line()
    assert all(np.isfinite(d) and d >= -1e-6 for _, d in iv.points)


def test_profile_refuses_unknown_and_fixed_names(data, tmp_path, capsys):
    fit = kneenlp.identify(kneenlp.Knee.named("synthetic"), data, noise=NOISE, free=["ACL.k"])
    with pytest.raises(InputError, match="was not fitted"):
        profile(fit, ["PCL.k"])
    with pytest.raises(InputError, match=r"unknown parameter 'ACLx\.k'"):
        profile(fit, ["ACLx.k"])
    csv = str(tmp_path / "m.csv")
    kneenlp.simulate(kneenlp.Knee.named("synthetic"), "set1").measured(NOISE, 3).to_csv(csv, index=False)
    for names, needle in (("ACLx.k", "unknown parameter 'ACLx.k'"), ("PCL.k", "'PCL.k' was not fitted")):
        assert main(["identify", csv, "--knee", "synthetic", "--free", "ACL.k", "--profile", names]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--profile" in err and needle in err
    assert main(["identify", csv, "--knee", "synthetic", "--free", "ACL.k,ACL.ref_strain", "--profile",
                 "ACL.ref_strain", "--json"]) == 0
    (record,) = json.loads(capsys.readouterr().out)["profile"]
    assert record["name"] == "ACL.ref_strain" and record["unit"] == "%"
    assert record["lower"] < record["estimate"] < record["upper"]
