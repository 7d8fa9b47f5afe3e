"""The global calibration: a search of the whole prior for the MAP estimate, its competing minima shown.

A real knee's MAP objective has many local minima close together (S192803, 24 trials: 18 distinct
minima in 20 solves, the lowest at 299.59, 300.64, 302.44, within a prior sd of each other).  The
NLP's poses are free, so a trial where the knee is bistable may sit on either equilibrium, and each
choice of branches is a minimum of its own; a chain of local steps from one start ends in one of
them by the last digits of its arithmetic (the BLAS thread count moved it from 298.6 to 368.6).
The search (:func:`search`) makes the choice explicit:

1. **Starts** (:func:`prior_starts`): the prior's centre (the knee's values, the probe's offsets)
   and ``starts - 1`` scrambled Sobol points over every free parameter's central
   :data:`CENTRAL` of its prior (in the prior's own scale; clipped to the bounds), seeded.
2. **Screen**: :data:`SCREEN_EVALUATIONS` reduced-space Gauss-Newton evaluations from each start
   (every iterate at equilibrium): cheap, and it ranks starts by where they lead, not where they are.
3. **Refine**: the :data:`REFINED` best screened starts to convergence by the simultaneous NLP
   from the screen's end (its poses too).  The NLP's MAP objective is the one compared and reported.
4. **Deepen** (monotone basin hopping): from the lowest minimum, :data:`HOPS_PER_ROUND` hops per
   round, each every free parameter moved by :data:`HOP_STEP` prior sd in a seeded random direction
   and solved by the NLP from the minimum's poses; the lowest hop is taken if it is lower by more
   than :data:`SAME_OBJECTIVE` (relative); it stops after :data:`PATIENCE` rounds without one, or
   :data:`MAX_ROUNDS`.  The number of hops per round is fixed, so the workers change the wall time only.
5. **Outliers** (``outliers``, an :class:`OutlierTest`): the caller's screen at the lowest minimum
   names a candidate trial; the :data:`REFINED` lowest distinct minima are re-converged without it
   (the NLP from their own parameters and poses) and deepened, and the candidate is tested against
   the lowest minimum of that search (predicted by it): an outlier is set aside and the search goes
   on without it; otherwise the search with every trial stands.  The test runs before the search
   with every trial is deepened, so that a trial set aside costs no deepening of a problem the
   search then leaves; when the candidate is kept, the search with every trial is deepened and
   the candidate its lowest minimum names, if another, is tested in turn.  Both sides of the test
   are minima of a search, not of a local refit, so whether a trial is set aside does not turn on
   the last digits of a path (a local refit without it set valgus_flex60 aside or not for a 1e-12
   change of the data).
6. **Minima** (:func:`distinct_minima`): every converged end clustered by objective
   (:data:`SAME_OBJECTIVE`) and parameters (:data:`SAME_PARAMETERS` prior sd); each minimum with how
   many solves reached it.  Ends with trials off the loading path (``Fit.off_path``: equilibria
   ``predict`` does not reach from the unloaded state) rank after the rest, and ends with a trial at
   an unstable equilibrium (``Fit.unstable``: no loading ends there) after those.  Fewer than
   :data:`ENOUGH_HITS` solves for the lowest is reported: the search may not have found the global MAP.

Everything is a function of the problem, the seed and the number of starts; the jobs of a stage are
independent and shared out over ``workers`` forked processes (:mod:`kneenlp.base.forked`) in a
fixed order.  With a ``store`` directory each finished solve is written there at once (atomic JSON,
keyed by the problem's fingerprint, the stage and the start), and a rerun with the same problem,
seed and starts takes the finished ones from it (an interrupted search resumes).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
from scipy import stats
from scipy.stats import qmc

from kneenlp.base.atomic import write_text_atomic
from kneenlp.base.dask_cluster import DaskWorkers
from kneenlp.base.errors import InputError
from kneenlp.base.forked import one_blas_thread
from kneenlp.estimation.fit import Fit, forked_fits
from kneenlp.estimation.minima import (
    SAME_OBJECTIVE,
    Search,
    distinct_minima,
    from_standardised,
    ranked,
    rounded,
    standardised,
    standing,
)
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.problem_file import MAX_STARTS
from kneenlp.solvers.result import SolverResult

#: Share of each prior the starts cover (its central quantiles).
CENTRAL = 0.95
#: Starts of a real experiment's calibration by default: on S192803 (48 free parameters) 16 starts
#: reach the lowest minimum with 12 of 20 solves, in about 90 s on 2 cores (benchmarks/bench_global.py).
DEFAULT_STARTS = 16
#: Reduced-space evaluations of a start's screen.
SCREEN_EVALUATIONS = 8
#: Screened starts refined to convergence.
REFINED = 4
#: Hops per round of the deepening (fixed: the workers do not change what is computed).  With 2,
#: S192803 with the neutral zone kept 360.775 or 360.307 by a 1e-12 change of its data or start;
#: with 4 every setting keeps 360.307 (5-6 solves; benchmarks/bench_global.py).
HOPS_PER_ROUND = 4
#: Step of a hop, in prior sd of every free parameter.
HOP_STEP = 0.3
#: Rounds of the deepening without a lower minimum before it stops, and its most rounds.
PATIENCE = 4
MAX_ROUNDS = 12


def check_sampleable(problem: IdentificationProblem, priors: dict) -> None:
    """Refuse a free parameter that has neither a prior (in ``priors``) nor finite bounds: the starts
    cannot cover it."""
    for i, name in enumerate(problem.free):
        if name not in priors and not (np.isfinite(problem.lower[i]) and np.isfinite(problem.upper[i])):
            raise InputError(f"{name} is free without a prior and without finite bounds, so the global search cannot "
                             "draw starts for it: give it a prior (a 'prior' in the problem's [parameters] table, "
                             "or --priors default), finite bounds, or --starts 1", field=name)


def prior_starts(problem: IdentificationProblem, centre: dict[str, float], starts: int, seed: int,
                 priors: dict | None = None) -> list[dict]:
    """``centre`` and ``starts - 1`` scrambled Sobol points over the central :data:`CENTRAL` of every
    free parameter's prior (``priors``, default the problem's; uniform between the bounds for one
    without a prior), seeded."""
    priors = problem.priors if priors is None else priors  # a least-squares fit's starts cover its defaults
    if starts > 1:
        check_sampleable(problem, priors)
    points = [dict(centre)]
    if starts <= 1:
        return points
    sobol = qmc.Sobol(problem.n_free, scramble=True, seed=np.random.default_rng([seed, starts]))
    u = sobol.random_base2(int(np.ceil(np.log2(starts - 1))))[:starts - 1]  # the first of a balanced 2^m
    u = (1 - CENTRAL) / 2 + CENTRAL * u
    for row in u:
        point = {}
        for i, name in enumerate(problem.free):
            prior = priors.get(name)
            if prior is not None:
                value = prior.untransform(prior.centre + prior.sd * stats.norm.ppf(row[i]))
            else:
                value = problem.lower[i] + row[i] * (problem.upper[i] - problem.lower[i])
            point[name] = float(np.clip(value, problem.lower[i], problem.upper[i]))
        points.append(point)
    return points


def fingerprint(problem: IdentificationProblem, *parts: object) -> str:
    """A key of ``problem`` (the model's structure, its free parameters, priors and weights, the
    knee's values, the data) and ``parts``: the store's file names."""
    h = hashlib.sha256()
    priors = sorted((n, p.shape, repr(p.mean), repr(p.sd)) for n, p in problem.priors.items())
    h.update(json.dumps([_package_version(), model_structure(problem.model), problem.free, priors,
                         repr(problem.prior_weight),
                         [t.id for t in problem.trials], [repr((t.load.tolist(), t.flexion)) for t in problem.trials],
                         list(parts)]).encode())
    for array in (problem.model.theta(), np.asarray(problem.data.q, float), np.asarray(problem.weights, float)):
        h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()[:20]


def model_structure(model: KneeModel) -> list:
    """What makes a model's equations besides its values: its parts, parameters and every bundle's
    path (a knee whose ligament wraps a bone and the same knee straight share their values), and the
    knee file's text."""
    source = model.knee.source
    text = Path(source).read_bytes() if source and Path(source).is_file() else b""
    paths = [[type(b.path).__name__ for b in lig.bundles] for lig in model.knee.ligaments.values()]
    return [[type(p).__name__ for p in model.parts], model.parameter_names, paths, hashlib.sha256(text).hexdigest()]


def _package_version() -> str:
    """The installed package's version (a store's solves are kneenlp's of that version); ``source``
    when it runs from a checkout that is not installed."""
    try:
        return version("kneenlp")
    except PackageNotFoundError:
        return "source"


class Store:
    """Finished solves of a search on disk (module docstring); ``None`` directory: nothing kept."""

    def __init__(self, directory: str | Path | None):
        self.directory = None if directory is None else Path(directory)

    def _path(self, key: str) -> Path | None:
        return None if self.directory is None else self.directory / f"{key}.json"

    def load(self, problem: IdentificationProblem, key: str) -> Fit | None:
        path = self._path(key)
        if path is None or not path.exists():
            return None
        try:
            d = json.loads(path.read_text())
            q = np.array(d["q"], float)
            kept = SolverResult(d.get("solver", "ipopt"), {n: d["params"][n] for n in problem.free}, q,
                                d.get("map_objective", np.nan), d["success"], d["status"], d["iterations"],
                                d.get("evaluations", 0), 0.0, d["max_residual"])  # its time was spent before
            return Fit.build(problem, d["method"], problem.theta(d["params"]), q, status=d["status"],
                             success=d["success"], max_residual=d["max_residual"], message=d["message"],
                             start=d["start"], solver=kept.solver, result=kept, off_path=tuple(d["off_path"]),
                             unstable=tuple(d.get("unstable", ())))
        except (OSError, ValueError, KeyError, TypeError):
            return None  # a damaged record is solved again

    def save(self, key: str, fit: Fit) -> None:
        path = self._path(key)
        if path is None:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps({
            "method": fit.method, "params": fit.params, "q": np.asarray(fit.q_pred).tolist(), "status": fit.status,
            "success": bool(fit.success), "iterations": int(fit.iterations), "evaluations": int(fit.evaluations),
            "solver": fit.solver, "map_objective": float(fit.map_objective), "max_residual": float(fit.max_residual),
            "message": fit.message, "start": fit.start, "off_path": list(fit.off_path),
            "unstable": list(fit.unstable)}))


Solve = Callable[[IdentificationProblem, dict[str, float], "np.ndarray | None", int], Fit]


@dataclass(frozen=True)
class OutlierTest:
    """The outlier test inside a search (module docstring): ``candidate(fit)`` the trial the screen
    finds worst at a minimum (or None); ``verdict(without, held, n_trials)`` the deletion test of
    the trial ``held`` (measured data of one trial) predicted by ``without``, the lowest minimum
    without it: (an outlier record or None, why it was not tested or ""); at most ``share`` of the
    trials are set aside."""

    candidate: Callable[[Fit], str | None]
    verdict: Callable[[Fit, object, int], tuple[object, str]]
    share: float


@dataclass(frozen=True)
class Solves:
    """How the search solves the problem from a start (SI values, poses or None, threads): ``screen``
    the cheap screen, ``refine`` the refinement to convergence (also of the minima without a
    candidate outlier), ``hop`` a hop's solve."""

    screen: Solve
    refine: Solve
    hop: Solve


@dataclass(frozen=True)
class SearchSettings:
    """What a search does besides its solves (:func:`search`): ``starts`` (the centre and ``starts - 1``
    Sobol points over ``priors``, default the problem's) from ``seed``; ``workers``: forked
    processes, or a :class:`~kneenlp.base.dask_cluster.DaskWorkers` (each solve on a Dask worker with
    one thread; the same solves, so the same answer), sharing ``threads``; ``store``: the directory
    of its finished solves (None: none kept); ``refined`` screened starts are refined;
    ``deepen=False`` leaves out the basin hopping (a scatter fit's search, where the NLP is robust
    and the hops would only cost); ``outliers``: the outlier test the search runs (None: every trial
    is kept)."""

    starts: int
    seed: int
    workers: int | DaskWorkers = 1
    threads: int = 2
    store: str | Path | None = None
    refined: int = REFINED
    deepen: bool = True
    priors: dict | None = None
    outliers: OutlierTest | None = None


def search(problem: IdentificationProblem, centre: dict[str, float], solves: Solves,
           settings: SearchSettings) -> Search:
    """The global search of ``problem`` (module docstring) from ``centre`` and ``settings.starts - 1``
    Sobol points, by ``solves`` (:class:`Solves`) and ``settings`` (:class:`SearchSettings`)."""
    starts, seed, workers, threads = settings.starts, settings.seed, settings.workers, settings.threads
    if not 1 <= starts <= MAX_STARTS:
        raise InputError(f"expected a whole number of starts from 1 to {MAX_STARTS}, got {starts}", field="--starts")
    points = prior_starts(problem, centre, starts, seed, settings.priors)
    client, cluster = workers.connect() if isinstance(workers, DaskWorkers) else (None, None)
    try:
        if client is None:
            processes = max(1, min(workers, len(points)))
            inner = max(1, threads // processes) if processes > 1 else threads
            run = _Runner(Store(settings.store), seed, starts, processes, inner)
        else:
            from kneenlp.estimation.dask_solves import register_model

            register_model(client, problem.model)
            run = _Runner(Store(settings.store), seed, starts, client, 1)
        return _search(problem, points, run, solves, settings)
    finally:
        for part in (client, cluster):
            if part is not None:
                part.close()


@dataclass(frozen=True)
class _Runner:
    """Runs a stage's solves: those the store holds read from it, the rest solved over ``workers``
    (a number of forked processes, each solve with ``threads``, or a Dask client), each written to
    the store as it finishes.  Every solve runs with NumPy's and SciPy's BLAS on one thread, in this
    process too: a BLAS on two threads sums in another order, and the last digits it moves chose
    another minimum of S192803 with the neutral zone (360.307 with one worker, 360.775 with two)."""

    store: Store
    seed: int
    starts: int
    workers: object
    threads: int

    def __call__(self, prob: IdentificationProblem, stage: str, jobs: list[tuple[dict, np.ndarray | None]],
                 solve: Solve) -> list[Fit]:
        keys = [fingerprint(prob, self.seed, self.starts, stage, i) for i in range(len(jobs))]
        done = [self.store.load(prob, k) for k in keys]
        todo = [i for i, d in enumerate(done) if d is None]
        if not isinstance(self.workers, int):  # a Dask client
            from kneenlp.estimation.dask_solves import dask_fits

            for k, fit in dask_fits(self.workers, solve, prob, [jobs[i] for i in todo]):
                self.store.save(keys[todo[k]], fit)
                done[todo[k]] = fit
            return done

        def work(i: int) -> Fit:
            with one_blas_thread():  # as in a forked or Dask worker: the same arithmetic whatever the workers
                fit = solve(prob, jobs[i][0], jobs[i][1], self.threads)
            self.store.save(keys[i], fit)
            return fit

        for i, fit in zip(todo, forked_fits(work, todo, self.workers, prob.model), strict=True):
            done[i] = fit
        return done


def _search(problem: IdentificationProblem, points: list[dict], run: _Runner, solves: Solves,
            settings: SearchSettings) -> Search:
    """:func:`search`'s stages from the starts ``points``."""
    seed, starts, refine, hop = run.seed, run.starts, solves.refine, solves.hop
    outliers, refined, deepen = settings.outliers, settings.refined, settings.deepen
    screened = run(problem, "screen", [(p, None) for p in points], solves.screen)
    order = ranked(screened, screened=True)[:refined]
    ends = [(f"start {i + 1}", f) for i, f in zip(order, run(
        problem, "refine", [(screened[i].params, screened[i].q_pred) for i in order], refine), strict=True)]
    found, notes = [], []
    limit = int(outliers.share * problem.n_trials) if outliers is not None else 0
    deepened, retained = not deepen, set()  # whether ``ends`` are deepened; candidates tested and kept
    while True:
        lowest = ends[ranked([f for _, f in ends])[0]][1]
        worst = outliers.candidate(lowest) if len(found) < limit and lowest.success else None
        if worst is None or worst in retained:
            if deepened:
                break
            ends, deepened = ends + _deepen(problem, ends, run, hop), True
            continue  # the deepened lowest minimum may name another candidate
        rows = np.array([t.id != worst for t in problem.trials])
        kept_problem = problem.without_trials([worst])
        again = run(kept_problem, f"without {worst}",
                    [(m.fit.params, np.asarray(m.fit.q_pred)[rows]) for m in distinct_minima(ends)[:refined]], refine)
        kept_ends = [(f"minimum {i + 1} without {worst}", f) for i, f in enumerate(again)]
        if deepen:
            kept_ends += _deepen(kept_problem, kept_ends, run, hop)
        without = kept_ends[ranked([f for _, f in kept_ends])[0]][1]
        outlier, why = outliers.verdict(without, lowest.data.subset(~rows), problem.n_trials + len(found))
        if why:
            notes.append(f"{worst} not tested as an outlier: {why}")
        if outlier is None:
            retained.add(worst)
            continue
        found.append(outlier)
        ends, problem, retained, deepened = kept_ends, kept_problem, set(), True  # kept_ends: deepened
    screen_objectives = np.array([f.map_objective if f.max_residual <= f.problem.equilibrium_tol else np.nan
                                  for f in screened])
    return Search(starts, seed, screen_objectives, ends, distinct_minima(ends), tuple(found), tuple(notes))


def _deepen(problem: IdentificationProblem, ends: list[tuple[str, Fit]], run: _Runner,
            hop: Solve) -> list[tuple[str, Fit]]:
    """The deepening's hops (module docstring), labelled ``hop R.K``, seeded by ``run``'s seed and starts."""
    fits = [f for _, f in ends]
    best = fits[ranked(fits)[0]]
    if not best.success:
        return []
    rng = np.random.default_rng([run.seed, run.starts, 7])
    out: list[tuple[str, Fit]] = []
    misses = 0
    for round_ in range(MAX_ROUNDS):
        centre = standardised(problem, best.params)
        jobs = [(from_standardised(problem, centre + HOP_STEP * rng.standard_normal(problem.n_free)), best.q_pred)
                for _ in range(HOPS_PER_ROUND)]
        hops = run(problem, f"hop {round_} from {best.map_objective:.9g}", jobs, hop)
        out += [(f"hop {round_ + 1}.{k + 1}", f) for k, f in enumerate(hops)]
        lowest = hops[ranked(hops)[0]]
        if _better(lowest, best):
            best, misses = lowest, 0
        else:
            misses += 1
            if misses >= PATIENCE:
                break
    return out


def _better(a: Fit, b: Fit) -> bool:
    """``a`` ranks before ``b`` (:func:`ranked`) by more than :data:`SAME_OBJECTIVE`."""
    standing_a, standing_b = standing(a, a.success), standing(b, b.success)
    if standing_a != standing_b or not a.success:
        return standing_a < standing_b
    return rounded(a.map_objective) < rounded(b.map_objective * (1 - SAME_OBJECTIVE))
