"""The worked example of docs/architecture.md, run as written, and the consistency of objectives
across methods and effects (one observation function for every solver)."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

import kneenlp
from kneenlp.estimation.identify import identify
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.io.export import export_problem

DOC = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """The element module and the usage block of the worked example, the element importable."""
    tmp = tmp_path_factory.mktemp("example")
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    (tmp / "compression_element.py").write_text(blocks[0])
    (tmp / "cubic_toe_law.py").write_text(blocks[2])
    sys.path.insert(0, str(tmp))
    yield tmp, blocks[1], blocks[3]
    sys.path.remove(str(tmp))


def test_worked_example(example, monkeypatch):
    tmp, usage, _ = example
    monkeypatch.chdir(tmp)
    scope: dict = {}
    exec(compile(usage, str(DOC), "exec"), scope)
    fit = scope["fit"]
    assert fit.success
    assert abs(fit.params["compression.force"] - 300.0) <= 3 * fit.stderr["compression.force"]
    assert "compression.force" in scope["nlp"].var_names


def test_user_element_on_the_command_line(example, monkeypatch, capsys):
    import json

    from kneenlp.cli import main

    tmp, _, _ = example
    monkeypatch.chdir(tmp)
    assert main(["simulate", "--knee", "synthetic",
                 "--protocol", "set1", "--element", "compression_element:make", "--with-effect",
                 "compression:force=200", "--noise", "uniform:0.5", "--out", "sim", "--no-plots", "--json"]) == 0
    capsys.readouterr()
    assert main(["identify", "--knee", "synthetic",
                 "sim/measured.csv", "--element", "compression_element:make", "--with-effect",
                 "compression", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert abs(out["params"]["compression.force"] - 200.0) < 5 * out["stderr"]["compression.force"]
    assert main(["export", "--knee", "synthetic", "sim/measured.csv", "--format", "casadi", "--out", "exp", "--element",
                 "compression_element:make", "--with-effect", "compression", "--json"]) == 0
    capsys.readouterr()
    sidecar = json.loads((tmp / "exp" / "problem.json").read_text())
    assert "compression.force" in [v["name"] for v in sidecar["variables"]]
    assert main(["study", "--knee", "synthetic",
                 "--sets", "1", "--samples", "2", "--element", "compression_element:make",
                 "--with-effect", "compression", "--start", "truth", "--workers", "1", "--out", "st", "--quiet",
                 "--json"]) == 0
    import pandas as pd

    est = pd.read_csv(tmp / "st" / "estimates.csv")
    assert len(est) == 2 and est["success"].all() and "compression.force" in est.columns
    assert main(["identify", "--knee", "synthetic", "sim/measured.csv", "--element", "nowhere:make"]) == 2


EFFECTS = ["registration", "flexion_offset", "meniscus", "posterior_capsule", "lin_strain", "contact_modulus"]


@pytest.mark.parametrize("method", ["simultaneous", "nested"])
@pytest.mark.parametrize("effect", EFFECTS)
def test_objective_is_the_weighted_residual_sum(effect, method, tmp_path):
    """For every built-in effect and both methods, the reported objective equals the weighted sum of
    squared residuals of the returned fit (the nested objective once left out the registration bias)."""
    knee = kneenlp.Knee.named("synthetic")
    model = KneeModel.of(knee)
    eff = model.effect(effect)
    truth = {n: model.parameter(n).neutral if model.parameter(n).neutral is not None else model.theta()[
        model.index(n)] for n in eff.parameters}
    first = eff.parameters[0]
    par = model.parameter(first)
    truth[first] = (par.neutral or truth[first]) + 2.0 * par.meta.scatter * (abs(truth[first]) if par.meta.relative
                                                                              else 1.0)
    data = kneenlp.simulate(model, "set1", parameters=truth).measured("uniform:0.5", seed=3)
    path = tmp_path / "data.csv"
    data.to_csv(path, index=False)
    free = ["ACL.k", "MCL.k"]
    fit = identify(model, path, method=method, free=free, with_effects=[effect], weighted=True, noise="uniform:0.5",
                   nested_options={"max_evals": 300})
    r = fit.residuals
    wsum = float(np.sum(fit.weights * r**2))
    assert fit.objective == pytest.approx(wsum, rel=1e-9)
    if method == "simultaneous":
        assert fit.result.objective == pytest.approx(wsum, rel=1e-9)


def test_worked_law(example, monkeypatch):
    """Part 2: a law in one file, named by a knee file: the ACL follows it (its force at a strain is
    the cubic toe's, not the paper's), the knee moves differently, and identify recovers the ACL's
    stiffness from data it made."""
    from kneenlp.model.laws import NUMPY

    tmp, _, usage = example
    monkeypatch.chdir(tmp)
    scope: dict = {}
    exec(compile(usage, str(DOC), "exec"), scope)
    knee, fit = scope["knee"], scope["fit"]
    law = KneeModel.of(knee).element("ACL").law
    assert law.name == "cubic_toe" and KneeModel.of(knee).element("PCL").law.name == "toe_linear"
    eps = np.array([-0.01, 0.0, 0.02, 0.045, 0.08])
    assert np.allclose(law.tension(eps, 1000.0, 0.03, NUMPY), [0, 0, 1000 * 0.02**3 / (6.75 * 0.03**2), 15.0, 50.0])
    plain = kneenlp.simulate(kneenlp.Knee.named("synthetic"), "set3")
    assert np.abs(scope["kneenlp"].simulate(knee, "set3").q - plain.q).max() > 1e-4
    assert fit.success and abs(fit.params["ACL.k"] - 10000.0) <= 3 * fit.stderr["ACL.k"]


def test_user_element_consistent_across_methods(example):
    from compression_element import Compression

    model = KneeModel(kneenlp.Knee.named("synthetic"), extra_elements=[Compression()])
    data = kneenlp.simulate(model, "set1", parameters={"compression.force": 150.0}).measured("uniform:0.5", seed=2)
    from kneenlp.base.conventions import coordinate_columns, coords_from_user
    from kneenlp.experiment.measured import MeasuredData

    res = kneenlp.simulate(model, "set1")
    md = MeasuredData([s.trial for s in res.solutions], coords_from_user(data[coordinate_columns()].to_numpy()),
                      "set1")
    for method in ("simultaneous", "nested"):
        fit = identify(model, md, method=method, free=["ACL.k"], with_effects=["compression"],
                       nested_options={"max_evals": 200})
        assert fit.objective == pytest.approx(float(np.sum(fit.weights * fit.residuals**2)), rel=1e-9)
    prob = export_problem(model, md, free=["ACL.k"], with_effects=["compression"])
    assert prob.var_names[:2] == ["ACL.k", "compression.force"]
