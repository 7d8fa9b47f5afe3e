"""Optimal laxity protocols: choose at most N load cases that identify the ligaments best.

The predicted covariance of the free parameters for a protocol comes from the sensitivities of
the simultaneous NLP at assumed parameter values (the Gauss-Newton / Fisher information
``F = sum_i S_i' S_i / sigma^2`` over the protocol's trials, ``S_i = d q_i / d p`` from the
implicit-function theorem through trial i's equilibrium).  Parameters are compared in relative
terms (``d q / d log p``), so the criteria weigh ACL.k and MCL.ref_strain alike:

* ``A``: sum of relative variances, ``trace(F^-1)``;
* ``D``: ``-log det(F) / n``;
* ``W``: the worst parameter's relative standard error;
* ``R``: the worst ratio of a parameter's standard error to its standard error under a reference
  protocol (default Set 4): below 1 the design is predicted tighter than the reference for
  every parameter.

Robustness to the parameter guess: the criterion is averaged over several parameter sets (the
knee's own and ``robust - 1`` draws of the paper's scatter, +-500 N, +-0.02).  The design is a
greedy forward selection followed by Fedorov exchanges (swap a chosen case for a candidate while
the criterion improves).  The result is a normal protocol file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kneenlp.base.atomic import write_text_atomic
from kneenlp.base.errors import InputError
from kneenlp.base.keywords import keyword_options
from kneenlp.base.modes import Criterion, checked
from kneenlp.estimation.statistics import fisher_information
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.protocol import Protocol, Trial, trial_id
from kneenlp.model.knee import Knee
from kneenlp.model.params import default_free
from kneenlp.solvers.forward import forward_solver

#: Designs made before one simulates with every trial converged (each drops the failed cases).
MAX_REDESIGNS = 5
#: The paper's largest magnitude per direction (N or N m).
PAPER_MAXIMA = {"anterior": 134.0, "posterior": 67.0, "internal": 2.0, "external": 2.0, "varus": 10.0,
                "valgus": 10.0}


#: Candidate flexions (deg): up to 60 deg for single-bundle knees (unstable beyond, as in the paper's
#: discussion), up to 90 deg for knees with multi-bundle ligaments.
FLEXIONS = (0.0, 15.0, 30.0, 45.0, 60.0)
FLEXIONS_MULTI_BUNDLE = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)


def default_flexions(knee) -> tuple[float, ...]:
    """:data:`FLEXIONS_MULTI_BUNDLE` if any ligament of ``knee`` (a Knee or KneeModel) is a bundle
    group, else :data:`FLEXIONS`."""
    ligaments = getattr(knee, "ligaments", None) or knee.knee.ligaments
    return FLEXIONS_MULTI_BUNDLE if any(lig.grouped for lig in ligaments.values()) else FLEXIONS


def candidate_pool(flexions=FLEXIONS, levels=(1.0, 0.6, 0.2)) -> Protocol:
    """Every direction at ``levels`` x the paper's maxima and every flexion, plus no-load trials."""
    trials = [Trial(trial_id("none", 0.0, f), f, {}, "none", 0.0) for f in flexions]
    comps = {"anterior": ("anterior_force", 1), "posterior": ("anterior_force", -1), "varus": ("varus_moment", 1),
             "valgus": ("varus_moment", -1), "internal": ("internal_moment", 1),
             "external": ("internal_moment", -1)}
    for d, top in PAPER_MAXIMA.items():
        comp, sign = comps[d]
        for lv in levels:
            m = round(top * lv, 4)
            for f in flexions:
                trials.append(Trial(trial_id(d, m, f), f, {comp: sign * m}, d, m))
    return Protocol("pool", tuple(trials), "candidate pool", "all directions, levels and flexions")


def reference_units(problem: IdentificationProblem, theta: np.ndarray) -> np.ndarray:
    """What "relative" means for each free parameter: its value, or for a parameter whose value is
    0 (a bundle group's reference-strain offset) its kind's scale (1 % strain)."""
    values = np.array([theta[problem.model.index(n)] for n in problem.free])
    return np.where(values != 0, values, problem.scales)


def relative_information(problem: IdentificationProblem, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-trial Fisher information of ``problem``'s trials in relative parameter units, shape
    (n_trials, n, n), at parameters ``theta`` with the problem's noise level, and which trials
    reached equilibrium (n_trials,).

    Trials without equilibrium contribute nothing (and :func:`design` never proposes them)."""
    sols = forward_solver(problem.model).solve(list(problem.trials), theta)
    ok = np.array([s.converged for s in sols])
    q = np.array([s.q for s in sols])
    info = fisher_information(problem.sensitivities(q, theta) * reference_units(problem, theta),
                              problem.noise.std)  # per unit relative change
    info[~ok] = 0.0
    return info, ok


def relative_standard_errors(info: np.ndarray) -> np.ndarray:
    """Linearised relative standard error of each parameter from a total information matrix;
    ``inf`` for a parameter the information does not determine (a component in its null space),
    never the 0 a pseudo-inverse would give."""
    w, v = np.linalg.eigh((info + info.T) / 2)
    null = w <= 1e-10 * max(float(w.max()), 1e-300)
    cov = (v[:, ~null] / w[~null]) @ v[:, ~null].T
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return np.where(np.any(np.abs(v[:, null]) > 1e-6, axis=1), np.inf, se)


def criterion_value(info: np.ndarray, kind: str, reference_se: np.ndarray | None = None) -> float:
    """Criterion of a total information matrix (smaller is better); inf if singular."""
    n = info.shape[0]
    sign, logdet = np.linalg.slogdet(info)
    if sign <= 0 or logdet < -700:
        return np.inf
    if kind == "D":
        return -logdet / n
    cov = np.linalg.inv(info)
    if kind == "A":
        return float(np.trace(cov))
    if kind == "R":
        return float(np.max(np.sqrt(np.diag(cov)) / reference_se))
    return float(np.sqrt(np.max(np.diag(cov))))


@dataclass
class DesignResult:
    """A designed protocol and its predicted performance (relative standard errors, fractions)."""

    protocol: Protocol
    criterion: Criterion
    value: float
    predicted_rse: dict[str, float]  # at the knee's parameter set
    free: list[str]
    history: list[tuple[int, float]] = field(default_factory=list)
    #: candidate load cases left out: no equilibrium at the knee's parameters, in the pool or in a
    #: designed protocol as simulate solves it
    infeasible: list[str] = field(default_factory=list)

    def to_toml(self) -> str:
        header = [f"Designed by kneenlp: {self.criterion}-optimal, {len(self.protocol)} load cases.",
                  "Predicted relative standard errors (uniform noise, linearised): "
                  + ", ".join(f"{n} {rse_text(v)}" for n, v in self.predicted_rse.items())]
        if self.infeasible:
            header.append(f"Left out (no equilibrium on this knee): {', '.join(self.infeasible)}")
        return self.protocol.to_toml(header)


def rse_text(value: float) -> str:
    """A relative standard error for people: percent, or "not identified" (infinite)."""
    return f"{100 * value:.2f} %" if np.isfinite(value) else "not identified"


def predicted_rse(model: KneeModel, protocol: Protocol, free: list[str], noise: str | NoiseModel,
                  theta: np.ndarray | None = None) -> dict[str, float]:
    """Linearised relative standard error of each free parameter for ``protocol``."""
    problem = IdentificationProblem(model, protocol.trials, free, noise=NoiseModel.parse(noise))
    theta = problem.theta() if theta is None else theta
    se = relative_standard_errors(relative_information(problem, theta)[0].sum(axis=0))
    return {n: float(v) for n, v in zip(free, se, strict=True)}


@dataclass(frozen=True)
class DesignOptions:
    """:func:`design`'s keyword options (its docstring), checked in one place."""

    pool: Protocol | None = None
    free: list[str] | None = None
    noise: str = "uniform:0.5"
    robust: int = 3
    seed: int = 0
    name: str | None = None
    reference: Protocol | str = "set4"


@dataclass(frozen=True)
class _DesignTask:
    """What is designed: the ``problem`` of the ``pool``'s trials, at most ``max_cases`` of them, the
    protocol's ``name`` and the ``noise`` its description names."""

    problem: IdentificationProblem
    pool: Protocol
    max_cases: int
    name: str
    noise: str


def design(knee: Knee | None = None, max_cases: int = 22, criterion: Criterion = "A", **options) -> DesignResult:
    """Choose at most ``max_cases`` trials of ``pool`` minimising ``criterion`` (see module doc).

    Keyword options: ``pool`` (default :func:`candidate_pool` at the knee's default flexions),
    ``free`` (default every ligament's k and reference strain), ``noise`` (``"uniform:0.5"``),
    ``robust`` (3 parameter sets), ``seed`` (0), ``name`` (``designed_<criterion><max_cases>``) and
    ``reference`` (``"set4"``, criterion ``R``'s protocol).

    Three steps: the criterion at the knee's parameters and the robustness draws, the greedy and
    exchange selection of the cases, and the check that ``simulate`` solves every chosen case (the
    design is made again without those it does not)."""
    from kneenlp.experiment.kneemodel import KneeModel

    opts = keyword_options(DesignOptions, "design", options)
    checked("criterion", criterion, Criterion, field="--criterion")
    if max_cases < 1:
        raise InputError(f"must be >= 1, got {max_cases}", field="--max-cases")
    knee = knee or Knee.default()
    model = KneeModel.of(knee)
    pool = opts.pool or candidate_pool(default_flexions(model))
    problem = IdentificationProblem(model, pool.trials, list(opts.free or default_free(model)),
                                    noise=NoiseModel.parse(opts.noise))
    crit, feasible = _RobustCriterion.at_draws(problem, criterion, opts.robust, opts.seed, opts.reference)
    task = _DesignTask(problem, pool, max_cases, opts.name or f"designed_{criterion}{max_cases}", opts.noise)
    history: list = []
    proto, chosen = _simulated_design(crit, task, feasible, history)
    rse = predicted_rse(model, proto, problem.free, opts.noise)
    infeasible = [pool.trials[i].id for i in range(len(pool)) if not feasible[i]]
    return DesignResult(proto, criterion, crit.value(chosen), rse, problem.free, history, infeasible)


@dataclass(frozen=True)
class _RobustCriterion:
    """A design criterion averaged over parameter sets: ``thetas`` (the knee's own first, then the
    robustness draws), the per-trial information of every pool trial at each, shape (R, T, n, n) in
    relative parameter units, and for criterion ``R`` the reference protocol's relative standard
    errors at each; ``ridge`` keeps a sum of few trials' information invertible."""

    kind: str
    thetas: list[np.ndarray]
    infos: np.ndarray
    ref_se: list[np.ndarray | None]
    ridge: np.ndarray

    @classmethod
    def at_draws(cls, problem: IdentificationProblem, kind: str, robust: int, seed: int,
                 reference: Protocol | str) -> tuple[_RobustCriterion, np.ndarray]:
        """The criterion over the knee's parameters and ``robust - 1`` draws of the paper's scatter
        (from ``seed``), and which pool trials reach equilibrium at the knee's parameters."""
        rng = np.random.default_rng(seed)
        thetas = [problem.theta()] + [problem.theta(problem.scatter(rng)) for _ in range(max(0, robust - 1))]
        computed = [relative_information(problem, th) for th in thetas]
        infos = np.array([c[0] for c in computed])  # (R, T, n, n)
        # a candidate without equilibrium at the knee's parameters is never proposed; at a robustness draw
        # it adds no information (and the designed protocol is checked at every draw below)
        feasible = computed[0][1].copy()
        ref_se: list[np.ndarray | None] = [None] * len(thetas)
        if kind == "R":
            ref = reference if isinstance(reference, Protocol) else Protocol.load(reference)
            ref_problem = IdentificationProblem(problem.model, ref.trials, problem.free, noise=problem.noise)
            ref_se = [relative_standard_errors(relative_information(ref_problem, th)[0].sum(axis=0))
                      for th in thetas]
        return cls(kind, thetas, infos, ref_se, 1e-9 * np.eye(len(problem.free))), feasible

    def value(self, selected: list[int]) -> float:
        """The criterion of the pool trials ``selected`` (smaller is better; inf for none)."""
        if not selected:
            return np.inf
        tot = self.infos[:, selected].sum(axis=1) + self.ridge
        return float(np.mean([criterion_value(m, self.kind, r) for m, r in zip(tot, self.ref_se, strict=True)]))


def _select(crit: _RobustCriterion, candidates: list[int], max_cases: int, pool: Protocol,
            history: list) -> list[int]:
    """Greedy forward selection, then Fedorov exchanges, among ``candidates`` (pool indices),
    sorted by flexion, direction and decreasing magnitude; each step's size and criterion value is
    appended to ``history``."""
    value, infos = crit.value, crit.infos
    chosen: list[int] = []
    while len(chosen) < min(max_cases, len(candidates)):
        best, best_v = None, np.inf
        for c in candidates:
            if c in chosen:
                continue
            v = value([*chosen, c]) if len(chosen) + 1 >= 2 else -np.trace(infos[:, c].mean(axis=0))
            if v < best_v:
                best, best_v = c, v
        chosen.append(best)
        history.append((len(chosen), value(chosen)))
    improved, passes = True, 0
    while improved and passes < 10:
        improved, passes = False, passes + 1
        current = value(chosen)
        for i in range(len(chosen)):
            for c in candidates:
                if c in chosen:
                    continue
                trial = [*chosen[:i], c, *chosen[i + 1 :]]
                v = value(trial)
                if v < current * (1 - 1e-9):
                    chosen, current, improved = trial, v, True
        history.append((len(chosen), current))
    return sorted(chosen, key=lambda i: (pool.trials[i].flexion_deg, pool.trials[i].direction,
                                         -pool.trials[i].magnitude))


def _simulated_design(crit: _RobustCriterion, task: _DesignTask, feasible: np.ndarray,
                      history: list) -> tuple[Protocol, list[int]]:
    """The designed protocol of ``task`` and its pool indices, made again without the cases that fail
    as ``simulate`` solves it at the knee's parameters (marked infeasible in ``feasible``), at most
    :data:`MAX_REDESIGNS` times."""
    problem, pool, name, noise = task.problem, task.pool, task.name, task.noise
    solver = forward_solver(problem.model)
    criterion = crit.kind
    for _ in range(MAX_REDESIGNS):
        candidates = [i for i in range(len(pool)) if feasible[i]]
        if not candidates:
            raise InputError("no candidate load case reaches equilibrium on this knee", field="pool")
        chosen = _select(crit, candidates, task.max_cases, pool, history)
        proto = Protocol(name, tuple(pool.trials[i] for i in chosen), f"{criterion}-optimal design, {len(chosen)} "
                         "cases", f"kneenlp design: {criterion}-optimal for {len(problem.free)} parameters, robust "
                         f"over {len(crit.thetas)} parameter sets, noise {noise}")
        # the protocol as `simulate` solves it (its own order and warm starts) at the knee's values: a
        # case that converged only warm-started from the pool's previous trial is left out, and the
        # design made again without it (at a robustness draw a case may fail: the synthetic knee's
        # 60 deg cases do, and it has no design without them that is as good as Set 4)
        failed = {i for i, sol in zip(chosen, solver.solve(proto.trials, crit.thetas[0]), strict=True)
                  if not sol.converged}
        if not failed:
            return proto, chosen
        feasible[list(failed)] = False
    raise InputError(f"no design of this pool simulates with every trial converged after {MAX_REDESIGNS} tries",
                     field="pool")


def write_protocol(result: DesignResult, path: str | Path) -> Path:
    """Write the designed protocol (atomically); the file loads back as the same protocol."""
    path = Path(path)
    write_text_atomic(path, result.to_toml())
    Protocol.load(path)  # the written file is a normal, valid protocol
    return path
