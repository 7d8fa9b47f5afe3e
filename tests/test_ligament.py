import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.model.ligament import force_strain, force_strain_numpy, slack_length

K, EPS_L = 10000.0, 0.03


def paper_eq1(eps, k, eps_l):
    """Eq. (1) of the paper, written independently, case by case."""
    if eps <= 0:
        return 0.0
    if eps <= 2 * eps_l:
        return k * eps**2 / (4 * eps_l)
    return k * (eps - eps_l)


@settings(deadline=None, derandomize=True)  # a timing deadline fails a loaded CI machine, not the law
@given(st.floats(-0.2, 0.3), st.floats(100.0, 30000.0), st.floats(0.01, 0.06))
def test_casadi_law_matches_eq1_everywhere_outside_kink_band(eps, k, eps_l):
    if min(abs(eps), abs(eps - 2 * eps_l)) < 1e-4:
        return
    f = float(ca.Function("f", [], [force_strain(ca.DM(eps), k, eps_l)])()["o0"])
    assert abs(f - paper_eq1(eps, k, eps_l)) < 0.1
    assert abs(f - paper_eq1(eps, k, eps_l)) <= 1e-9 * max(1.0, abs(f))  # not smoothed at all


def test_law_is_c1_at_both_kinks():
    e = ca.SX.sym("e")
    f = force_strain(e, K, EPS_L)
    df = ca.Function("df", [e], [ca.jacobian(f, e)])
    for kink in (0.0, 2 * EPS_L):
        left, right = float(df(kink - 1e-9)), float(df(kink + 1e-9))
        assert abs(left - right) < 1e-3
    assert float(df(2 * EPS_L + 1e-6)) == pytest.approx(K)


def test_numpy_and_casadi_agree():
    eps = np.linspace(-0.05, 0.2, 501)
    e = ca.SX.sym("e")
    f = ca.Function("f", [e], [force_strain(e, K, EPS_L)])
    assert np.allclose(np.array(f(eps.reshape(1, -1))).ravel(), force_strain_numpy(eps, K, EPS_L))


def test_acl_pretension_of_table1_is_700N():
    # Table 1: ACL k = 10 kN, reference strain 10 %: at the reference pose f = k (0.10 - 0.03) = 700 N
    assert paper_eq1(0.10, 10000.0, 0.03) == pytest.approx(700.0)
    l0 = slack_length(0.033, 0.10)
    assert (0.033 - l0) / l0 == pytest.approx(0.10)


def test_opensims_law_is_the_papers_in_other_terms():
    """Blankevoort1991Ligament with transition strain e_t and the paper's Eq. (1) with eps_l = e_t / 2
    are one function: equal on NumPy arrays and in CasADi, through both kinks."""
    from kneenlp.model.laws import CASADI, NUMPY, BlankevoortLaw, ToeLinearLaw

    eps = np.linspace(-0.05, 0.2, 2001)
    for k, eps_l in ((5000.0, 0.03), (123.0, 0.011)):
        a = ToeLinearLaw().tension(eps, k, eps_l, NUMPY)
        b = BlankevoortLaw().tension(eps, k, eps_l, NUMPY)
        assert np.allclose(a, b, rtol=1e-13, atol=1e-10)
        e = ca.SX.sym("e")
        f = ca.Function("f", [e], [BlankevoortLaw().tension(e, k, eps_l, CASADI)])
        assert np.allclose(np.asarray(f(eps.reshape(1, -1))).ravel(), a, rtol=1e-13, atol=1e-10)


@pytest.mark.parametrize("law, needle", [("toe_linaer", "unknown law 'toe_linaer'; built in: toe_linear, blankevoort"),
                                         ("no_such_module:Law", "cannot import law"),
                                         ("kneenlp.model.laws:Ops", "cannot make law"),
                                         ("kneenlp.model.laws:CASADI", "cannot make law"),
                                         ("kneenlp.model.laws:Protocol", "not a ligament law")])
def test_unknown_law_in_a_knee_file_is_named(tmp_path, law, needle):
    """A knee file's law that does not exist or is not a law: one line naming the field."""
    import shutil

    from kneenlp.base.errors import InputError
    from kneenlp.base.resources import resource
    from kneenlp.model.knee import Knee
    from kneenlp.model.knee_file import knee_file

    shutil.copytree(knee_file("synthetic").parent, tmp_path / "k")
    toml = tmp_path / "k" / "knee.toml"
    toml.write_text(toml.read_text().replace("../../parameters/table1.toml", str(resource("parameters", "table1.toml")))
                    .replace("[ligaments.MCL]", f'[ligaments.MCL]\nlaw = "{law}"'))
    with pytest.raises(InputError, match=r"ligaments\.MCL\.law") as err:
        KneeModel.of(Knee.load(toml))
    assert needle in str(err.value)
