"""Solving an identification problem: the scatter strategy's starts and restarts, the
simultaneous NLP's solve judged, the reduced-space fit, the rescue, the nested method.

Start: parameters from ``start`` (dict, SI) or the paper's scatter around the knee's parameter
set (uniform +-500 N on every k, +-0.02 on every reference strain, +-10 % on other kinds; seeded);
poses solved forward at the starting parameters, so the start satisfies every equilibrium
constraint.  (Starting at the noisy measured poses sent a prototype to wrong minima with
stiffnesses at their bounds.)  ``multistart=N`` runs N starts (the first as above, the others
fresh scatter draws) and keeps the best converged one.  A start whose solve fails (IPOPT wanders
off from an indefinite-Hessian region, about one seed in ten on Sets 1-3 in our measurements)
is followed by up to ``restarts`` fresh draws (default 4); so is a solve that ends with a ligament
parameter on its bound (k = 0 or 1e5 N, strain at +-30 %: the wrong-minimum signature of the
prototype), and, when the noise model is given, a solve whose misfit the noise cannot explain
(chi-square p < 1e-9).  The best fit is kept and records how many starts were used.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from kneenlp.estimation.fit import Fit
from kneenlp.estimation.starts import best_fit, run_starts
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.model.mesh_contact import RIM_SHARE
from kneenlp.solvers.forward import rim_note
from kneenlp.solvers.nlp import NlpSolver, solve_nlp
from kneenlp.solvers.reduced import reduced_least_squares, tolerance

if TYPE_CHECKING:
    from kneenlp.estimation.search import SearchSettings

#: Relative cost change at which a reduced-space fit hands over to IPOPT (:func:`reduced_then_nlp`,
#: the rescue of a failed start).  Measured on
#: the default knee's slowest adequacy case (a PCL attachment moved 4.2 mm, Set 4, two rescues): the
#: reduced fit's own tolerance (1e-5) took 41-44 evaluations (10.3-10.8 s) before IPOPT converged in
#: 9-10 iterations; 1e-2 took 12-17 evaluations (3.8-4.9 s), IPOPT 17-21 iterations, the same optimum
#: (objective 120.3424 both).  The adequacy refits (from the base fit, a closer start) gained
#: nothing from it (4 refits 30-32 s against 27 s: the early stop still took 10-27 evaluations, and
#: one polish failed): they keep the reduced fit to its tolerance.
RESCUE_TOL = 1e-2


@dataclass(frozen=True)
class ScatterSettings:
    """The scatter strategy's settings (module docstring; as :func:`~kneenlp.estimation.identify.identify`'s
    keyword arguments): the scatter's ``seed``, ``method`` (``"simultaneous"`` or ``"nested"``),
    ``multistart`` starts and ``restarts`` extra draws, the NLP's ``solver``, ``solver_options`` and
    ``threads``, the nested method's ``nested_options``."""

    seed: int = 0
    method: str = "simultaneous"
    multistart: int = 1
    restarts: int = 4
    solver: str = "ipopt"
    solver_options: dict | None = None
    threads: int = 2
    nested_options: dict | None = None

    @property
    def nlp(self) -> NlpSolver:
        """The simultaneous NLP's solver of these settings."""
        return NlpSolver(self.solver, self.solver_options, self.threads)


def scatter_fit(problem: IdentificationProblem, start: dict[str, float],
                settings: ScatterSettings = ScatterSettings()) -> Fit:
    """The fit of ``problem`` by the scatter strategy (module docstring): ``start`` (SI, checked)
    fills the first start, the rest is scattered from ``settings.seed``; the other settings as
    :func:`~kneenlp.estimation.identify.identify`'s keyword arguments."""
    seed, multistart = settings.seed, settings.multistart
    rng = np.random.default_rng(seed)
    if settings.method == "nested":
        return nested_fit_of(problem, start, rng, seed, dict(settings.nested_options or {}))

    def good(f: Fit) -> bool:
        return f.success and not at_bounds(f) and not implausible_misfit(f)

    def rank(f: Fit) -> tuple[bool, bool, float]:  # good first, then converged, then the lower objective
        return good(f), f.success, -f.map_objective if f.success else 0.0

    def solve(k: int) -> Fit:
        s = problem.scatter(rng)
        if k == 0 and start:
            s.update(start)
        fit = solve_simultaneous(problem, s, settings.nlp)
        if not fit.success and settings.solver == "ipopt":
            fit = _rescued(problem, s, fit, settings.nlp)
        return fit

    fits = run_starts(solve, at_least=multistart, at_most=max(1, multistart) + settings.restarts,
                      done=lambda fits: good(best_fit(fits, rank)))
    best, k = best_fit(fits, rank), len(fits)
    if best.success and at_bounds(best):
        best = best.with_note("ligament parameters at their bounds: a poor local minimum or a model that cannot "
                              "fit the data")
    if k > max(1, multistart):
        best = best.with_note(f"{k - max(1, multistart)} restart(s) after failed solves")
    return dataclasses.replace(best, starts=k)


#: Screened starts a scatter fit's global search refines (``scatter_search``), and the reduced-space
#: evaluations of its screen: the NLP is robust on the paper's Sets, so the search's worth there is a
#: cheap look at where each start leads (default knee, noisy Set 4, 20 seeds, 4 starts: the truth's basin in
#: 20 of 20, 2.2x the single NLP's time; 3.6x with a loading path per start: benchmarks/bench_global_scatter.py).
SCATTER_REFINED = 1
SCATTER_SCREEN = 3


def scatter_search(problem: IdentificationProblem, start: dict[str, float], settings: SearchSettings) -> Fit:
    """The scatter strategy's fit by the global search (:mod:`~kneenlp.estimation.search`): the first
    scatter start (``start`` over it) and ``settings.starts - 1`` Sobol points over the free parameters'
    priors (their defaults, centred on the knee's values, where the fit is least squares), each
    screened by :data:`SCATTER_SCREEN` reduced-space evaluations (Newton from the measured poses: the
    paper's trials have one equilibrium, so no loading path per start); the :data:`SCATTER_REFINED` best
    solved by the NLP (with the rescue); no basin hopping (``settings``: the search's ``starts``,
    ``seed``, ``workers``, ``threads`` and ``store``).  The kept fit's message gives the search's minima."""
    from kneenlp.estimation.search import Solves, search
    from kneenlp.experiment.problem import resolve_priors

    draws = problem.priors or resolve_priors(problem.model, problem.free, "default")
    centre = problem.scatter(np.random.default_rng(settings.seed)) | dict(start)

    def screen(p: IdentificationProblem, s: dict, q0, t: int) -> Fit:
        return reduced_fit(p, s, q0=p.measured_q if q0 is None else q0,
                           max_evaluations=SCATTER_SCREEN, threads=t)

    def nlp(p: IdentificationProblem, s: dict, q0, t: int) -> Fit:
        fit = solve_simultaneous(p, s, NlpSolver(threads=t), q0=q0)
        return fit if fit.success else _rescued(p, s, fit, NlpSolver(threads=t))

    settings = dataclasses.replace(settings, refined=SCATTER_REFINED, deepen=False, priors=draws)
    found = search(problem, centre, Solves(screen=screen, refine=nlp, hop=nlp), settings)
    starts = settings.starts
    minima = ", ".join(f"{m.objective:.6g} ({m.hits})" for m in found.minima)
    return dataclasses.replace(found.best.fit.with_note(f"global search of {starts} starts: minima (solves) {minima}"),
                               starts=starts)


def reduced_fit(problem: IdentificationProblem, start: dict[str, float], q0: np.ndarray | None = None,
                **options) -> Fit:
    """The fit of ``problem`` by reduced-space Gauss-Newton from ``start`` (SI; poses warm-started
    from ``q0``, SI): :func:`~kneenlp.solvers.reduced.reduced_least_squares` (``options``:
    ``max_evaluations``, ``tol``, ``threads``) as a :class:`Fit`."""
    r = reduced_least_squares(problem, start, q0=q0, **options)
    return Fit.build(problem, "reduced", problem.theta(r.values), r.q, status=r.status,
                     success=r.success and r.max_residual <= problem.equilibrium_tol, max_residual=r.max_residual,
                     start=dict(start), message="reduced-space Gauss-Newton", solver=r.solver, result=r)


def reduced_then_nlp(problem: IdentificationProblem, start: dict[str, float], q0: np.ndarray | None = None,
                     solver_options: dict | None = None, threads: int = 2) -> tuple[Fit, Fit | None, int]:
    """Reduced-space Gauss-Newton from ``start`` (every iterate at equilibrium) stopped early, at a
    relative cost change of :data:`RESCUE_TOL`, then the simultaneous NLP (IPOPT) from where it
    stopped; if the NLP fails from there, the reduced-space fit is finished (:func:`reduced_fit`)
    and the NLP tried once more from its end.  Returns the NLP's last fit (judge its ``success``),
    the finished reduced fit (``None`` when the first NLP succeeded) and the reduced evaluations."""
    coarse = reduced_fit(problem, start, q0=q0, threads=threads, tol=max(RESCUE_TOL, tolerance(problem.model)))
    nlp = NlpSolver("ipopt", solver_options, threads)
    fit = solve_simultaneous(problem, coarse.result.values, nlp).after(coarse)
    if fit.success or not coarse.result.success:
        return fit, None, coarse.evaluations
    finished = reduced_fit(problem, coarse.result.values, q0=coarse.result.q, threads=threads).after(coarse)
    again = solve_simultaneous(problem, problem.values(finished.theta), nlp)
    return again.after(finished), finished, finished.evaluations


def _rescued(problem: IdentificationProblem, start: dict[str, float], failed: Fit, nlp: NlpSolver) -> Fit:
    """A second try after IPOPT failed from ``start``: :func:`reduced_then_nlp` from the same start
    (``nlp``'s options and threads); the better of the tries is returned, its message saying so."""
    fit, _, evaluations = reduced_then_nlp(problem, start, solver_options=nlp.options, threads=nlp.threads)
    if not fit.success or (failed.success and failed.map_objective <= fit.map_objective):
        return failed
    note = (f"rescued: IPOPT failed from the start ({failed.status}); a reduced-space Gauss-Newton start "
            f"({evaluations} evaluations) led it to the solution")
    return fit.after(failed).with_note(note)


def implausible_misfit(fit: Fit) -> bool:
    """With a known noise model, a misfit the noise cannot explain (chi-square p < 1e-9) marks a
    wrong local minimum worth a restart (the best fit is kept either way)."""
    noise = fit.problem.noise
    if noise is None or noise.std <= 0:
        return False
    return bool(stats.chi2.sf(fit.chi_square(noise.std), fit.dof) < 1e-9)


def at_bounds(fit: Fit) -> bool:
    """True if a ligament parameter sits on its bound (the prototype's wrong-minimum signature)."""
    on_bound = fit.at_bounds(("k", "ref_strain", "lin_strain"), tol=1e-6)
    return any(fit.problem.model.parameter(n).neutral is None for n in on_bound)


def nested_fit_of(problem: IdentificationProblem, start: dict, rng: np.random.Generator, seed: int,
                  options: dict) -> Fit:
    from kneenlp.solvers.nested import nested_fit

    initial = options.pop("initial", None)
    if initial is None:  # the paper's population; effect parameters spread from neutral too
        initial = [problem.scatter(rng, spread_effects=i > 0) for i in range(2 * problem.n_free + 1)]
        if start:
            initial[0].update(start)
    cloud = np.array([[c[n] for n in problem.free] for c in initial])
    r = nested_fit(problem, cloud, seed=seed, **options)
    return Fit.build(problem, "nested", problem.theta(r.values), r.q, status=r.status,
                     success=r.success and r.max_residual <= problem.equilibrium_tol, max_residual=r.max_residual,
                     start=dict(zip(problem.free, cloud[0], strict=True)), solver=r.solver, result=r)


def solve_simultaneous(problem: IdentificationProblem, start: dict[str, float], nlp: NlpSolver | None = None,
                       q0: np.ndarray | None = None) -> Fit:
    """One solve of the simultaneous NLP from ``start`` (SI values of every free parameter) by
    ``nlp`` (default IPOPT, 2 threads; :func:`~kneenlp.solvers.nlp.solve_nlp`; poses from ``q0``, SI, if
    given), judged: a success needs the solver's, every trial at equilibrium
    (:attr:`~kneenlp.experiment.problem.IdentificationProblem.equilibrium_tol`) and no contact point
    left out of the working sets; more than :data:`~kneenlp.model.mesh_contact.RIM_SHARE`
    of a compartment's force from beyond the femoral surface's open edge is noted."""
    r = solve_nlp(problem, start, nlp or NlpSolver(), q0)
    tol = problem.equilibrium_tol
    success = r.success and r.max_residual <= tol and r.left_out <= 0
    notes = []
    if r.started_at_data:
        notes.append(f"{r.started_at_data} trial(s) had no equilibrium inside the pose envelope at the start; "
                     "started at data")
    if r.success and r.max_residual > tol:
        notes.append(f"equilibrium residual {r.max_residual:.2e} above {tol:g}")
    if r.left_out > 0:
        notes.append(f"a contact point outside the working sets penetrates {1e3 * r.left_out:.3f} mm: enlarge "
                     "contact.working_set in the knee file (or the contact left the represented femoral surface)")
    if r.rim > RIM_SHARE:
        notes.append(rim_note(r.rim))
    return Fit.build(problem, "simultaneous", problem.theta(r.values), r.q, status=r.status, success=success,
                     max_residual=r.max_residual, start=dict(start), message="; ".join(notes), solver=r.solver,
                     result=r)
