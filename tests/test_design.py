"""Optimal laxity protocols."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

import kneenlp
from kneenlp.cli import main
from kneenlp.design.optimal import candidate_pool, criterion_value, design, predicted_rse, write_protocol
from kneenlp.experiment.protocol import Protocol


@pytest.fixture(scope="module")
def small_design():
    pool = candidate_pool(flexions=(0.0, 30.0), levels=(1.0, 0.5))
    return design(kneenlp.Knee.named("synthetic"), max_cases=10, criterion="A", pool=pool, robust=1)


def test_design_is_a_valid_protocol_and_beats_the_papers_set_with_as_many_cases(small_design, model, tmp_path):
    r = small_design
    assert len(r.protocol) == 10
    path = write_protocol(r, tmp_path / "d.toml")
    proto = Protocol.load(path)
    assert proto.trials == r.protocol.trials  # loads back unchanged (tomli-w writer)
    assert (proto.name, proto.title, proto.description) == (r.protocol.name, r.protocol.title, r.protocol.description)
    assert kneenlp.simulate(kneenlp.Knee.named("synthetic"), proto).converged == 10  # simulate accepts it
    # A-criterion of the design is better than Set 2's (13 cases) at the same noise
    set2 = predicted_rse(model, Protocol.load("set2"), r.free, "uniform:0.5")
    ours = r.predicted_rse
    assert sum(v**2 for v in ours.values()) < sum(v**2 for v in set2.values())


def test_criteria_are_consistent():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(20, 4))
    info = a.T @ a
    cov = np.linalg.inv(info)
    assert criterion_value(info, "A") == pytest.approx(np.trace(cov))
    assert criterion_value(info, "W") == pytest.approx(np.sqrt(cov.diagonal().max()))
    assert criterion_value(info, "D") == pytest.approx(-np.linalg.slogdet(info)[1] / 4)
    assert criterion_value(np.zeros((4, 4)), "A") == np.inf


def test_cli_design_json(tmp_path, capsys):
    code = main(["design", "--knee", "synthetic", "--max-cases", "6", "--flexions", "0,30", "--robust", "1", "--out",
                 str(tmp_path / "p.toml"), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["cases"] == 6 and len(out["trials"]) == 6
    assert Protocol.load(tmp_path / "p.toml").name == "designed_A6"


@pytest.mark.slow
def test_designed_protocol_monte_carlo(tmp_path):
    """22 designed cases vs Set 4's 60, 100 Monte Carlo samples each, which also checks
    the noise study's requirement: Set 4's Monte Carlo standard deviations agree with the linearised
    prediction within 25 % (a sample standard deviation of 100 draws is within about 7 % of the
    true one; the worst ratio measured is 1.18; 200 samples took 10 of CI's 20 slow minutes)."""
    from kneenlp.studies.study import StudySpec, run_study

    r = design(kneenlp.Knee.named("synthetic"), max_cases=22, criterion="A", robust=3)
    path = write_protocol(r, tmp_path / "designed.toml")
    # fits start at the truth: the spread is the noise's effect on the estimate, not the search's
    spec = StudySpec(knee="synthetic", sets=(str(path), "set4"), samples=100, seed=5, start="truth")
    study = run_study(spec, tmp_path / "mc", progress=False)
    table = pd.read_csv(study.out / "table3.csv")
    d = table[table["set"] == str(path)].set_index(["ligament", "parameter"])
    s4 = table[table["set"] == "set4"].set_index(["ligament", "parameter"])
    print(pd.DataFrame({"designed_range": d["range"], "set4_range": s4["range"], "designed_mc_std": d["mc_std"],
                        "designed_pred_std": d["predicted_std"]}).to_string())
    assert np.all(np.abs(d["mc_std"] / d["predicted_std"] - 1) <= 0.25)
    assert np.all(np.abs(s4["mc_std"] / s4["predicted_std"] - 1) <= 0.25)
    assert (d["n"] == 100).all() and (s4["n"] == 100).all()
    # the designed 22 cases are at least as tight as Set 4's 60 for most parameters (docs/design.md:
    # six of eight when it kept them, five since the design leaves out cases that converged only
    # warm-started from the pool's previous trial)
    assert (d["range"] <= s4["range"]).sum() >= 5


@pytest.mark.parametrize("name", ["set1", "set2", "set3", "set4"])
def test_protocols_round_trip_through_the_toml_writer(name, tmp_path):
    """Every shipped protocol written with tomli-w loads back with the same trials."""
    proto = Protocol.load(name)
    path = tmp_path / f"{name}.toml"
    path.write_text(proto.to_toml(["round trip"]))
    back = Protocol.load(path)
    assert back.trials == proto.trials and back.name == proto.name and back.title == proto.title


@pytest.mark.parametrize("name", ["default", "synthetic"])
def test_designed_protocol_simulates_with_every_trial_converged(name):
    """Every candidate is checked for equilibrium (knee's values and robustness draws) on its own
    path from the unloaded pose; the designed protocol then simulates with all trials converged
    (unchecked, the default knee's design proposed varus_10Nm_flex60, which failed in simulate)."""
    knee = kneenlp.Knee.named(name)
    r = design(knee, max_cases=22, criterion="A", robust=2)
    result = kneenlp.simulate(knee, r.protocol)
    assert all(s.converged for s in result.solutions), [s.trial.id for s in result.solutions if not s.converged]
    assert len(r.protocol) == 22 and not set(r.infeasible) & {t.id for t in r.protocol.trials}


def test_one_case_design_says_what_it_cannot_identify(capsys, tmp_path):
    """One load case cannot determine 8 parameters: no "0.00 %" for an unidentified one."""
    r = design(kneenlp.Knee.named("synthetic"), max_cases=1, criterion="A", robust=1,
               pool=candidate_pool((30.0,), (1.0,)))
    assert len(r.protocol) == 1
    assert sum(not np.isfinite(v) for v in r.predicted_rse.values()) >= len(r.free) - 5
    assert "not identified" in r.to_toml() and " 0.00 %" not in r.to_toml()
