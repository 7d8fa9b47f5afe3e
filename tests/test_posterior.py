"""A calibration's posterior in ``calibrated.toml`` and ``predict``'s predictive band: written and
read back exactly, the band checked against finite-difference sensitivities (an independent route
through each trial's equilibrium), bad posterior tables refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

import kneenlp
from kneenlp.base.conventions import BAND_Z
from kneenlp.cli import main
from kneenlp.estimation.calibrated import Calibration, posterior
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.prediction.predict import predict

NOISE = "uniform:0.5"
FREE = ["ACL.k", "ACL.ref_strain", "MCL.k", "MCL.ref_strain"]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """(data path, calibrated.toml path, fit) of Set 1 on the synthetic knee."""
    tmp = tmp_path_factory.mktemp("posterior")
    csv = tmp / "set1.csv"
    kneenlp.simulate(kneenlp.Knee.named("synthetic"), "set1").measured(NOISE, 5).to_csv(csv, index=False)
    fit = kneenlp.identify(kneenlp.Knee.named("synthetic"), read_measured(csv), free=FREE)
    toml = tmp / "calibrated.toml"
    toml.write_text(Calibration(fit).to_toml())
    return csv, toml, fit


def test_posterior_round_trips_through_the_parameter_file(calibrated):
    _, toml, fit = calibrated
    read = kneenlp.ParameterSet.load(toml).posterior
    written = posterior(fit)
    assert read.names == tuple(FREE) == written.names
    np.testing.assert_allclose(read.covariance, written.covariance, rtol=1e-12)
    np.testing.assert_allclose(read.noise_sd, written.noise_sd, rtol=1e-12)
    assert np.all(np.isfinite(read.covariance)) and np.all(np.linalg.eigvalsh(read.covariance) > 0)


def test_band_is_the_posterior_through_finite_difference_sensitivities(calibrated):
    """sd^2 - noise^2 = diag(S C S') with S by central differences of ``predict`` itself."""
    csv, toml, _ = calibrated
    knee = kneenlp.Knee.named("synthetic").with_parameters(toml)
    data = read_measured(csv)
    pred = predict(knee, data)
    post = knee.parameters.posterior
    assert pred.sd_user is not None and pred.converged.all()
    model = KneeModel.of(knee)
    base = dict(zip(model.parameter_names, model.theta(), strict=True))
    columns = []
    for n, sd in zip(post.names, np.sqrt(np.diag(post.covariance)), strict=True):
        h = 1e-3 * sd
        up = predict(knee, data, base | {n: base[n] + h}).observed_user
        down = predict(knee, data, base | {n: base[n] - h}).observed_user
        columns.append(((up - down) / (2 * h)).ravel())
    S = np.array(columns).T
    expected = np.einsum("ij,jk,ik->i", S, post.covariance, S).reshape(-1, 5)
    np.testing.assert_allclose(pred.sd_user**2 - post.noise_sd**2, expected, rtol=2e-3, atol=1e-8)
    inside = pred.inside_band()
    assert sum(inside.values()) == int(np.sum(np.abs(pred.errors_user) <= BAND_Z * pred.sd_user))
    assert "predictive band" in pred.report() and "sd_anterior_translation_mm" in pred.table()


@pytest.mark.parametrize("edit, needle", [
    (lambda t: t.replace('method = "laplace"', 'method = "mcmc"'), "posterior.method"),
    (lambda t: t.replace('method = "laplace"', 'method = "laplace"\nextra = 1'), "posterior.extra"),
    (lambda t: t.replace('"ACL.k",\n', '"ACLx.k",\n', 1), "posterior.parameters"),
    (lambda t: t.replace("noise_sd = [", "noise_sd = [-1.0, "), "posterior.noise_sd"),
    (lambda t: t[:t.index("covariance = [")] + "covariance = [[1.0]]\n" + t[t.index("noise_sd"):],
     "posterior.covariance"),
])
def test_bad_posterior_is_refused(calibrated, tmp_path, capsys, edit, needle):
    csv, toml, _ = calibrated
    bad = tmp_path / "bad.toml"
    bad.write_text(edit(toml.read_text()))
    assert main(["predict", str(csv), "--knee", "synthetic", "--parameters", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err


def test_asymmetric_or_indefinite_covariance_is_refused(calibrated, tmp_path, capsys):
    import tomllib

    import tomli_w

    csv, toml, _ = calibrated
    doc = tomllib.loads(toml.read_text())
    for change, needle in ((lambda c: c.__setitem__((0, 1), c[0, 1] + abs(c[0, 0])), "not symmetric"),
                           (lambda c: c.__setitem__((0, 0), -abs(c[0, 0])), "not positive semi-definite")):
        cov = np.array(doc["posterior"]["covariance"])
        change(cov)
        bad = tmp_path / "bad.toml"
        bad.write_text(tomli_w.dumps(doc | {"posterior": doc["posterior"] | {"covariance": cov.tolist()}}))
        assert main(["predict", str(csv), "--knee", "synthetic", "--parameters", str(bad)]) == 2
        assert needle in capsys.readouterr().err


def test_identify_writes_the_posterior_for_arviz(calibrated, tmp_path, capsys):
    """``identify --out`` writes posterior.nc: ArviZ reads it, its draws have the fit's values as
    means and the Laplace standard errors as sds (seeded: the same file twice)."""
    az = pytest.importorskip("arviz")
    csv, _, _ = calibrated
    out = tmp_path / "fit"
    assert main(["identify", str(csv), "--knee", "synthetic", "--free", ",".join(FREE), "--out", str(out)]) == 0
    assert not capsys.readouterr().err  # no stray warnings
    fit = kneenlp.identify(kneenlp.Knee.named("synthetic"), read_measured(csv), free=FREE)
    idata = az.from_netcdf(out / "posterior.nc")
    post = posterior(fit)
    summary = az.summary(idata, kind="stats")
    for n, sd in zip(post.names, np.sqrt(np.diag(post.covariance)), strict=True):
        f = fit.info(n).to_user
        assert summary.loc[n, "mean"] == pytest.approx(fit.params[n] * f, abs=4 * sd * f / np.sqrt(4000))
        assert summary.loc[n, "sd"] == pytest.approx(sd * f, rel=0.05)
    assert idata.observed_data["measured"].shape == (len(fit.data), 5)
    again = tmp_path / "again"
    assert main(["identify", str(csv), "--knee", "synthetic", "--free", ",".join(FREE), "--out", str(again)]) == 0
    same = az.from_netcdf(again / "posterior.nc")
    assert all(np.array_equal(idata.posterior[n].values, same.posterior[n].values) for n in post.names)
