"""The global search (kneenlp.estimation.search): its starts, its minima, its store, its answer.

Oracles: the priors' own quantiles (the starts), minima made by hand (the clustering), and the
search itself run another way (worker counts, a resumed store: the same ends bit for bit).
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.estimation.minima import SAME_PARAMETERS, Search, distinct_minima, standardised
from kneenlp.estimation.search import CENTRAL, SearchSettings, Solves, prior_starts, search
from kneenlp.estimation.solve import reduced_fit, solve_simultaneous
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.model.priors import Prior
from kneenlp.solvers.nlp import NlpSolver


def fake_problem(priors: dict, lower=(-np.inf, 0.0, -1.0), upper=(np.inf, np.inf, 3.0)):
    free = ["a", "b", "c"]
    return SimpleNamespace(free=free, n_free=3, priors=priors, lower=np.array(lower), upper=np.array(upper),
                           scales=np.ones(3))


PRIORS = {"a": Prior("normal", 2.0, 0.5), "b": Prior("lognormal", 1.0, 0.3)}


def test_starts_cover_each_priors_central_95_percent_and_follow_the_seed():
    problem = fake_problem(PRIORS)
    centre = {"a": 2.0, "b": 1.0, "c": 0.5}
    points = prior_starts(problem, centre, 65, seed=4)
    assert len(points) == 65 and points[0] == centre  # the centre first
    a, b, c = (np.array([p[n] for p in points[1:]]) for n in "abc")
    tail = (1 - CENTRAL) / 2
    lo_a, hi_a = stats.norm.ppf([tail, 1 - tail], 2.0, 0.5)
    assert lo_a <= a.min() < 2.0 < a.max() <= hi_a
    assert np.exp(-1.96 * 0.3) <= b.min() and b.max() <= np.exp(1.96 * 0.3) + 1e-12
    assert -1.0 <= c.min() and c.max() <= 3.0  # no prior: between the bounds
    # a Sobol sequence is balanced: each half of every prior holds about half the starts
    assert abs(np.mean(a < 2.0) - 0.5) < 0.05 and abs(np.mean(c < 1.0) - 0.5) < 0.05
    assert prior_starts(problem, centre, 65, seed=4) == points
    assert prior_starts(problem, centre, 65, seed=5)[1:] != points[1:]


def test_a_parameter_without_prior_or_finite_bounds_cannot_be_sampled():
    problem = fake_problem({"b": PRIORS["b"]}, upper=(np.inf, np.inf, 3.0))
    with pytest.raises(InputError, match=r"a is free without a prior and without finite bounds.*give it a prior"):
        prior_starts(problem, {"a": 0.0, "b": 1.0, "c": 0.0}, 8, seed=0)
    assert len(prior_starts(problem, {"a": 0.0, "b": 1.0, "c": 0.0}, 1, seed=0)) == 1  # one start needs no draw


def fake_fit(problem, objective, a, success=True, off=(), unstable=()):
    return SimpleNamespace(problem=problem, map_objective=objective, success=success, off_path=off,
                           unstable=unstable, params={"a": a, "b": 1.0, "c": 0.0}, max_residual=0.0)


def test_minima_are_ends_equal_in_objective_and_parameters_lowest_on_the_loading_path_first():
    """Ends equal in objective (1e-6) and parameters are one minimum; the minima rank stable and on
    the loading path first, then off it, then those with a trial at an unstable equilibrium."""
    problem = fake_problem(PRIORS)
    problem.equilibrium_tol = 1e-6
    step = SAME_PARAMETERS * 0.5 / 2  # a quarter of the tolerance, in the prior sd 0.5 of "a"
    ends = [("start 1", fake_fit(problem, 10.0, 2.0)),
            ("start 2", fake_fit(problem, 10.0 * (1 + 1e-8), 2.0 + step)),  # the same minimum
            ("start 3", fake_fit(problem, 10.0, 2.5)),  # the same objective elsewhere: another minimum
            ("start 4", fake_fit(problem, 9.0, 3.0, off=("valgus_flex60",))),  # lower, off the loading path
            ("start 5", fake_fit(problem, 1.0, 1.0, success=False)),  # not converged: no minimum
            ("start 6", fake_fit(problem, 8.0, 4.0, off=("varus_flex0",), unstable=("varus_flex0",))),
            ("hop 1.1", fake_fit(problem, 10.0, 2.0))]
    minima = distinct_minima(ends)
    assert [m.reached_by for m in minima] == [("start 1", "hop 1.1", "start 2"), ("start 3",), ("start 4",),
                                              ("start 6",)]
    assert standardised(problem, minima[1].fit.params)[0] == pytest.approx(1.0)
    found = Search(6, 0, np.zeros(6), ends, minima)
    # the best (stable, on the path) first, then the others within 1 % of the lowest found (8.0)
    assert [m.reached_by for m in found.competing()] == [("start 1", "hop 1.1", "start 2"), ("start 6",)]
    assert [m.reached_by[0] for m in found.competing(within=0.25)] == ["start 1", "start 3", "start 4", "start 6"]


def test_a_diagnosis_gives_its_figures_range_over_the_competing_minima():
    """The chi-square and each pattern's mean over the fits at a search's competing minima: their
    smallest and largest, by hand."""
    from kneenlp.adequacy.diagnosis import minima_spread
    from kneenlp.adequacy.patterns import Pattern

    r1 = np.zeros((3, 5))
    r1[:2, 2] = [2.0, 4.0]
    r2 = r1.copy()
    r2[:2, 2] = [1.0, 1.0]
    r2[2, 0] = 3.0
    fits = [SimpleNamespace(residuals=r, weights=None, free=["x"]) for r in (r1, r2)]
    lateral = Pattern("lateral_translation", "under external load", frozenset({0, 1}), 3.0, 2, 5.0)
    spread = minima_spread([lateral], fits, sigma=0.5)
    assert spread["minima"] == 2 and spread["pattern_means"] == [(1.0, 3.0)]
    assert spread["chi2"] == (pytest.approx((1 + 1 + 9) / 0.25), pytest.approx((4 + 16) / 0.25))


@pytest.fixture(scope="module")
def small_problem(knee, tmp_path_factory):
    """Set 1 on the synthetic knee with noise; the four stiffnesses and the ACL's reference strain
    free, with their default priors."""
    path = tmp_path_factory.mktemp("search") / "measured.csv"
    kneenlp.simulate(knee, "set1").measured("uniform:0.5", 3).to_csv(path, index=False)
    data = read_measured(path)
    model = KneeModel.of(knee)
    free = ["ACL.k", "PCL.k", "MCL.k", "LCL.k", "ACL.ref_strain"]
    return IdentificationProblem.from_data(model, data, free, priors="default", prior_weight=0.25)


def screen(problem, start, q0, threads):
    return reduced_fit(problem, start, q0=q0, max_evaluations=3, threads=threads)


def nlp(problem, start, q0, threads):
    return solve_simultaneous(problem, start, NlpSolver(threads=threads), q0=q0)


def test_the_search_gives_the_same_ends_with_one_or_two_workers_and_resumes_from_its_store(small_problem, tmp_path):
    centre = {n: small_problem.model.theta()[small_problem.model.index(n)] for n in small_problem.free}
    one = search(small_problem, centre, Solves(screen, nlp, nlp), SearchSettings(starts=6, seed=1, workers=1))
    two = search(small_problem, centre, Solves(screen, nlp, nlp),
                 SearchSettings(starts=6, seed=1, workers=2, store=tmp_path / "search"))
    assert one.best.fit.success and one.best.hits >= 1
    assert [label for label, _ in one.ends] == [label for label, _ in two.ends]
    assert [f.map_objective for _, f in one.ends] == [f.map_objective for _, f in two.ends]  # bit for bit
    assert one.best.fit.params == two.best.fit.params
    assert np.array_equal(one.screened, two.screened, equal_nan=True)
    assert len(list((tmp_path / "search").glob("*.json"))) >= len(two.ends) + 6

    def refused(*args):
        raise AssertionError("solved again: the store should have answered")

    again = search(small_problem, centre, Solves(refused, refused, refused),
                   SearchSettings(starts=6, seed=1, workers=2, store=tmp_path / "search"))
    assert again.best.objective == pytest.approx(two.best.objective, rel=1e-12)
    assert [m.reached_by for m in again.minima] == [m.reached_by for m in two.minima]
    assert "reached by" in "\n".join(two.lines()) and two.summary()["minima"][0]["hits"] == two.best.hits


@pytest.mark.parametrize("starts", [0, -3, 1001])
def test_a_number_of_starts_out_of_range_is_refused(small_problem, starts):
    with pytest.raises(InputError, match="starts from 1 to 1000"):
        search(small_problem, {}, Solves(screen, nlp, nlp), SearchSettings(starts=starts, seed=0))


def test_the_command_line_refuses_bad_starts_in_one_line(capsys):
    from pathlib import Path

    from kneenlp.cli import main

    problems = Path(__file__).resolve().parents[1] / "problems"
    for bad in ("0", "-2", "1001", "many"):
        assert main(["identify", "--problem", str(problems / "s192803"), "--starts", bad]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--starts" in err, err
    # the nested method has its own population
    assert main(["identify", "--problem", str(problems / "set1"), "--starts", "4", "--method", "nested"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--starts" in err, err
    # Dask runs the search's solves: without a search (a scatter fit's default, --starts 1) it has nothing to run
    for args in (["identify", "--problem", str(problems / "set1")],
                 ["cross-validate", "--problem", str(problems / "s192803"), "--starts", "1"]):
        assert main([*args, "--dask"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--dask" in err and "--starts N" in err, err


def test_a_scatter_fit_takes_the_global_search_as_an_option(knee, tmp_path):
    """Set 1 on the synthetic knee: the search's fit is the single NLP's minimum here (the NLP is robust
    on the paper's Sets), found from Sobol starts over the default priors."""
    from kneenlp.estimation.identify import identify

    path = tmp_path / "set1.csv"
    kneenlp.simulate(knee, "set1").measured("uniform:0.5", 7).to_csv(path, index=False)
    data = read_measured(path)
    single = identify(knee, data, seed=7, noise="uniform:0.5")
    found = identify(knee, data, seed=7, noise="uniform:0.5", starts=3, workers=2)
    assert found.success and found.starts == 3 and "global search of 3 starts" in found.message
    assert found.map_objective == pytest.approx(single.map_objective, rel=1e-6)
    with pytest.raises(InputError, match="--workers"):  # workers without a search: still a calibration's option
        identify(knee, data, noise="uniform:0.5", workers=2)


def test_an_interrupted_search_keeps_its_finished_solves_and_a_rerun_resumes_them(small_problem, tmp_path):
    import signal

    from kneenlp.base.interrupts import Interrupted

    centre = {n: small_problem.model.theta()[small_problem.model.index(n)] for n in small_problem.free}
    calls = []

    def interrupted_at_the_fifth(problem, start, q0, threads):
        calls.append(1)
        if len(calls) == 5:
            raise Interrupted(signal.SIGTERM)
        return screen(problem, start, q0, threads)

    with pytest.raises(Interrupted):
        search(small_problem, centre, Solves(interrupted_at_the_fifth, nlp, nlp),
               SearchSettings(starts=6, seed=2, store=tmp_path))
    assert len(list(tmp_path.glob("*.json"))) == 4  # the four finished screens, each written as it finished
    again = []

    def counted(problem, start, q0, threads):
        again.append(1)
        return screen(problem, start, q0, threads)

    resumed = search(small_problem, centre, Solves(counted, nlp, nlp),
                     SearchSettings(starts=6, seed=2, store=tmp_path))
    assert len(again) == 2  # the two screens not finished before
    fresh = search(small_problem, centre, Solves(screen, nlp, nlp), SearchSettings(starts=6, seed=2))
    assert resumed.best.fit.params == fresh.best.fit.params


def test_a_search_whose_solves_all_failed_keeps_the_best_failed_one_and_says_so():
    from kneenlp.estimation.minima import Search

    problem = fake_problem(PRIORS)
    problem.equilibrium_tol = 1e-6
    ends = [("start 1", fake_fit(problem, 5.0, 2.0, success=False)), ("start 2", fake_fit(problem, 4.0, 2.1,
                                                                                          success=False))]
    found = Search(2, 0, np.array([5.0, 4.0]), ends, distinct_minima(ends))
    assert found.minima == [] and found.best.hits == 0 and not found.found
    assert found.best.fit is ends[0][1]  # failed ends rank by index, never by an objective they did not reach
    assert "none of its 2 solves converged" in found.advice()


def test_the_search_on_a_dask_cluster_gives_the_local_answer_bit_for_bit(small_problem, tmp_path):
    """The same seed on a local Dask cluster (two worker processes, each building the model from
    what the search sends) and in this process: the same ends, the same kept minimum; the store
    written as the solves finish."""
    pytest.importorskip("dask.distributed")
    from kneenlp.base.dask_cluster import DaskWorkers

    centre = {n: small_problem.model.theta()[small_problem.model.index(n)] for n in small_problem.free}
    local = search(small_problem, centre, Solves(screen, nlp, nlp),
                   SearchSettings(starts=4, seed=2, workers=1, threads=1))
    remote = search(small_problem, centre, Solves(screen, nlp, nlp),
                    SearchSettings(starts=4, seed=2, workers=DaskWorkers(processes=2), store=tmp_path / "search"))
    assert [label for label, _ in local.ends] == [label for label, _ in remote.ends]
    assert [f.map_objective for _, f in local.ends] == [f.map_objective for _, f in remote.ends]
    assert local.best.fit.params == remote.best.fit.params
    assert remote.best.fit.problem.model is small_problem.model
    assert len(list((tmp_path / "search").glob("*.json"))) == len(remote.ends) + 4


def test_the_outlier_test_inside_the_search_judges_a_trial_by_the_searchs_own_minima(knee, tmp_path):
    """A trial moved 6 mm and 6 deg off (every coordinate) is named by the screen at the lowest
    minimum, tested against the lowest minimum of the search without it and set aside, with 1 and 2
    workers alike; the same search of the clean data sets nothing aside."""
    from kneenlp.estimation.calibrate import outlier_candidate, outlier_verdict
    from kneenlp.estimation.outliers import MAX_OUTLIER_SHARE
    from kneenlp.estimation.search import OutlierTest

    test = OutlierTest(outlier_candidate, outlier_verdict, MAX_OUTLIER_SHARE)
    kneenlp.simulate(knee, "set3").measured("uniform:0.5", 3).to_csv(tmp_path / "m.csv", index=False)
    small_problem = IdentificationProblem.from_data(KneeModel.of(knee), read_measured(tmp_path / "m.csv"),
                                                    ["ACL.k", "PCL.k", "MCL.k", "LCL.k", "ACL.ref_strain"],
                                                    priors="default", prior_weight=0.25)
    centre = {n: small_problem.model.theta()[small_problem.model.index(n)] for n in small_problem.free}
    clean = search(small_problem, centre, Solves(screen, nlp, nlp),
                   SearchSettings(starts=4, seed=2, outliers=test))
    assert clean.set_aside == () and clean.best.fit.problem.n_trials == small_problem.n_trials
    measured = small_problem.measured.copy()
    measured[5] += 6.0
    planted = dataclasses.replace(small_problem, measured=measured)
    found = [search(planted, centre, Solves(screen, nlp, nlp),
                    SearchSettings(starts=4, seed=2, outliers=test, workers=workers)) for workers in (1, 2)]
    trial = small_problem.trials[5].id
    assert [f.set_aside for f in found] == [(trial,), (trial,)]
    assert found[0].outliers[0].p_adjusted < 0.05 and found[0].best.fit.problem.n_trials == small_problem.n_trials - 1
    assert found[0].best.fit.params == found[1].best.fit.params
    assert any(label.endswith(f"without {trial}") for label, _ in found[0].ends)


def test_the_global_search_is_the_default_calibration_of_a_real_experiment_and_an_option_of_a_scatter_fit():
    """``search_starts``: a real experiment's calibration searches from DEFAULT_STARTS unless --starts
    or --multistart (the local chain's further starts) says otherwise; a scatter fit keeps one start,
    and Dask, which runs a search's solves, is refused without one."""
    from argparse import Namespace

    from kneenlp.base.errors import InputError
    from kneenlp.cli.starts import search_starts
    from kneenlp.estimation.search import DEFAULT_STARTS

    def args(**given):
        return Namespace(**({"starts": None, "multistart": 1, "dask": False, "scheduler": None} | given))

    assert search_starts(args(), calibration=True) == DEFAULT_STARTS
    assert search_starts(args(starts=1), calibration=True) == 1
    assert search_starts(args(multistart=4), calibration=True) == 1
    assert search_starts(args(), calibration=False) == 1
    assert search_starts(args(starts=8, dask=True), calibration=False) == 8
    with pytest.raises(InputError, match="--starts N"):
        search_starts(args(dask=True), calibration=False)


def test_the_kept_minimum_is_the_same_whatever_the_workers_blas_threads_or_last_digits_default_knee(tmp_path):
    """The default knee, noisy Set 1, the search from 4 starts: the kept minimum is the same (1e-6
    relative in objective, 1e-4 prior sd in every parameter) with one or two workers, NumPy's BLAS on
    one or two threads, and the data or the start moved by 1e-12 relative."""
    from threadpoolctl import threadpool_limits

    from kneenlp.estimation.identify import identify

    knee = kneenlp.Knee.default()
    path = tmp_path / "set1.csv"
    kneenlp.simulate(knee, "set1").measured("uniform:0.5", 3).to_csv(path, index=False)
    data = read_measured(path)
    nudged = dataclasses.replace(data, q=np.asarray(data.q) * (1 + 1e-12))
    start = {n: knee.parameters[n] * (1 + 1e-12) for n in knee.parameters.names()
             if n.endswith((".k", ".ref_strain"))}

    def kept(data=data, workers=1, blas=2, **options):
        with threadpool_limits(limits=blas, user_api="blas"):
            return identify(knee, data, seed=3, noise="uniform:0.5", starts=4, workers=workers, **options)

    base = kept()
    problem = base.problem
    for fit in (kept(workers=2), kept(blas=1), kept(data=nudged), kept(start=start)):
        assert fit.success and fit.map_objective == pytest.approx(base.map_objective, rel=1e-6)
        z = standardised(problem, fit.params) - standardised(problem, base.params)
        assert np.abs(z).max() <= 1e-4, np.abs(z).max()


@pytest.mark.slow
def test_the_kept_minimum_of_s192803_with_one_blas_thread_is_the_documented_one():
    """problems/s192803's global search in a fresh process with OpenBLAS on one thread
    (benchmarks/bench_global.py) keeps the MAP objective docs/real-experiment.md gives (measured with
    two threads, as installed; 1e-6 relative); test_doc_figures checks the installed setting's fit."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    quoted = float(re.search(r"MAP (\d+\.\d+) kept for BLAS 1/2 threads", (root / "docs" / "real-experiment.md")
                             .read_text()).group(1))
    out = subprocess.run([sys.executable, str(root / "benchmarks" / "bench_global.py"), "--settings", "blas1-workers2"],
                         capture_output=True, text=True, check=True).stdout
    got = float(out.split("MAP objective ")[1].split(",")[0])
    assert got == pytest.approx(quoted, rel=1e-6), out


def test_a_store_keys_the_models_structure_not_only_its_values(small_problem, tmp_path):
    """The same knee with its MCL over a cylinder has the same parameter values and data, but other
    equations: its solves get other keys, so a store never answers one knee's search with another's."""
    from kneenlp.estimation.search import fingerprint
    from tests.test_paths import RIM, _knee_with_wrap

    wrapped = KneeModel.of(_knee_with_wrap(tmp_path, RIM.format(side="positive")))
    assert np.array_equal(wrapped.theta(), small_problem.model.theta())
    other = IdentificationProblem.from_data(wrapped, small_problem.data, small_problem.free, priors="default",
                                            prior_weight=0.25)
    assert fingerprint(other, 1, 6, "screen", 0) != fingerprint(small_problem, 1, 6, "screen", 0)
    again = IdentificationProblem.from_data(small_problem.model, small_problem.data, small_problem.free,
                                            priors="default", prior_weight=0.25)
    assert fingerprint(again, 1, 6, "screen", 0) == fingerprint(small_problem, 1, 6, "screen", 0)


def test_a_cross_validation_keeps_its_searches_solves_and_resumes_them(small_problem, tmp_path, monkeypatch):
    """``cross_validate(store=...)`` keeps every global search's finished solves in the store's
    ``solves`` folder: a rerun takes them from there (nothing is solved again) and gives the same
    held-out errors bit for bit."""
    import kneenlp.estimation.search as search_module
    from kneenlp.validation import crossval

    data, model = small_problem.data, small_problem.model
    name = crossval.folds(data)[0][0]
    options = {"starts": 2, "store": tmp_path / "cv", "priors": "default", "free": ["ACL.k", "PCL.k", "MCL.k"]}
    (first,) = crossval.cross_validate(model, data, [name], **options)
    kept = sorted((tmp_path / "cv" / crossval.SOLVES).glob("*.json"))
    assert len(kept) >= 2 * 3  # the hold-out's search: two starts' screens and refinements, and its hops

    def refused(self, prob, stage, jobs, solve):
        keys = [search_module.fingerprint(prob, self.seed, self.starts, stage, i) for i in range(len(jobs))]
        fits = [self.store.load(prob, k) for k in keys]
        assert all(f is not None for f in fits), f"{stage}: solved again, the store should have answered"
        return fits

    monkeypatch.setattr(search_module._Runner, "__call__", refused)
    (again,) = crossval.cross_validate(model, data, [name], **options)
    assert np.array_equal(again.prediction.errors_user, first.prediction.errors_user, equal_nan=True)
