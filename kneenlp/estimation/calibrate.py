"""Calibrate a knee to a real experiment: what ``kneenlp identify`` does with measured data.

A real experiment (data of a ``laboratory`` experiment, :mod:`kneenlp.experiment.kind`, as
``import-laxity`` writes them) differs from data the model produced in two ways the fit must take up:

* the experiment's frames are not the model's: the registration (a constant offset of the five
  measured coordinates, :class:`~kneenlp.experiment.parts.Registration`) is fitted with the ligaments;
* nobody declares the noise: its level is estimated from the fit (the residual variance);
* a trial can be one no passive knee produces: the outlier test (:mod:`~kneenlp.estimation.outliers`)
  sets it aside, the fit is repeated without it, and the report names it (S192803:
  ``valgus_flex60``, docs/real-experiment.md).

Which ligament parameters the trials can determine is decided before the fit
(:func:`~kneenlp.estimation.choice.calibration_free`): the sensitivities of the measured coordinates to every ligament
parameter at the knee's own values (through each trial's equilibrium), with the registration's
columns, are ranked by a pivoted QR; a parameter is kept while its pivot is at least
:data:`PIVOT_TOLERANCE` of the largest, i.e. while it changes the coordinates in a direction the
parameters kept before it do not.  The rest stay at the knee's values (the report names them).

A ligament slack in every trial has no sensitivity at all, whatever the data say: at the knee's
values a slack PCL cannot be told from an absent one, and the fit could never engage it (its
gradient is zero).  So the sensitivities are taken at a *probe*: every group whose fibres stay
slack in every trial at the knee's values has its reference-strain offset raised until its most
stretched fibre reaches :data:`~kneenlp.estimation.choice.ENGAGE_STRAIN` in its most stretching
trial.  The fit starts at the probe with those offsets free (the data then decide whether the
group stays engaged), and the report names the groups engaged this way.

A robot's joint loads act at the robot's load-reference point, registered to the tibia like the
poses.  A few millimetres of mediolateral error there turn 200 N of drawer into an
internal-external moment of a newton-metre or more, where the knee is lax.  So for joint loads the
calibration frees the lateral shift of that point too (:class:`~kneenlp.experiment.parts.LoadPoint`;
S192803: 9 mm medial, sum of squares 531 -> 390, internal rotation RMS 2.8 -> 1.9 deg;
docs/real-experiment.md).

The solver is the simultaneous NLP (IPOPT, every trial's equilibrium a constraint), started at a
reduced-space Gauss-Newton fit (:mod:`kneenlp.solvers.reduced`: every iterate at equilibrium)
from the probe (:func:`polished`): the reduced fit cannot wander off from the knee's values, the
NLP converges to a KKT point (the reduced fit alone stops within the mesh contact's cost noise,
at a point that depends on the order of its unknowns).  IPOPT from the probe itself stopped at 80
iterations before priors were added, and with the load point free failed altogether; where the
reduced fit fails, the NLP with the scatter strategy's rescue is the fallback.

:func:`calibrate` returns the fit with the RMS per coordinate before (the knee's parameters) and
after; :meth:`Calibration.parameter_set` is the calibrated parameter file's content.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from kneenlp.base.keywords import keyword_options
from kneenlp.estimation.calibrated import (
    Calibration,
    CalibrationRecord,
    noise_per_observation,
    on_loading_path,
    prediction_variances,
)
from kneenlp.estimation.calibration_options import PRIOR_WEIGHT as PRIOR_WEIGHT
from kneenlp.estimation.calibration_options import CalibrationInputs, CalibrationOptions
from kneenlp.estimation.choice import (
    also_free_names,
    calibration_choice,
    check_calibration,
    engaged_priors,
    engaged_probe,
    from_params,
)
from kneenlp.estimation.fit import Fit, forked_fits
from kneenlp.estimation.minima import Search
from kneenlp.estimation.outliers import (
    MAX_OUTLIER_SHARE,
    SCREEN_ALPHA,
    HeldOutTrial,
    Outlier,
    deletion_test,
    residual_factors,
    screen,
)
from kneenlp.estimation.search import DEFAULT_STARTS, SCREEN_EVALUATIONS, OutlierTest, SearchSettings, Solves, search
from kneenlp.estimation.solve import ScatterSettings, reduced_fit, scatter_fit, solve_simultaneous
from kneenlp.estimation.statistics import effective_parameters
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.prediction.predict import predict
from kneenlp.solvers.nlp import NlpSolver

#: Residual evaluations of the reduced-space Gauss-Newton calibration (S192803 converges in 40).
MAX_EVALUATIONS = 150
#: IPOPT iterations of the fallback (the simultaneous NLP) when the reduced solve fails.
MAX_ITER = 80


def calibrate(model: KneeModel, data: MeasuredData, free: list[str] | None = None, **options) -> Calibration:
    """Fit ``free`` to the real experiment ``data``: reduced-space Gauss-Newton from the knee's
    values (or the probe), then the simultaneous NLP from there (:func:`polished`); the NLP with the
    scatter strategy's rescue where the reduced fit fails.  ``free`` defaults to the parameter
    table's ``free = true`` entries, else to the calibration's choice below.

    ``priors`` (``"default"``, ``"none"`` or a dict of :class:`~kneenlp.model.priors.Prior` by name,
    as :func:`~kneenlp.experiment.problem.resolve_priors`): with priors the fit is the MAP estimate
    and, unless ``free`` or ``pivot_tolerance`` says otherwise, every ligament parameter is fitted
    (each prior determines what the trials do not); without priors only those the trials determine
    are (:func:`~kneenlp.estimation.choice.calibration_free`).  The priors are weighed against the misfit's variance
    ``prior_weight`` (mm^2 or deg^2 per unit weight; default :data:`PRIOR_WEIGHT`), or
    ``"estimate"``: estimated from the fit itself (:func:`map_fit`).  For a robot's joint loads and
    the default ``free``,
    ``load_point`` frees the lateral shift of the point the robot's force acts at too;
    ``also_free``: parameters or effects (:func:`~kneenlp.estimation.choice.also_free_names`) fitted beside the default
    ``free``, e.g. attachments a segmentation may have misplaced; unless ``keep_outliers``, trials
    the outlier test flags (:mod:`~kneenlp.estimation.outliers`) are set aside one at a time and the
    fit repeated without them.  ``weighted``, ``with_effects`` and ``start`` as
    :func:`~kneenlp.estimation.identify.identify`'s; ``multistart`` > 1 refits from further starts
    about the fit and keeps the lowest (:func:`lowest_of_starts`, its starts shared out over
    ``workers`` processes).  ``starts`` > 1 replaces that chain of local steps by the global search
    (:func:`global_fit`; ``store``: where its finished solves are kept, and a rerun resumes them;
    its solves over ``workers`` processes or a :class:`~kneenlp.base.dask_cluster.DaskWorkers`);
    by default (None) the calibration is the global search from
    :data:`~kneenlp.estimation.search.DEFAULT_STARTS` starts, or the local chain where
    ``multistart`` > 1 asks for its further starts; ``starts=1`` is the local chain from the knee's
    values (a quick look, whose answer may depend on the path: docs/real-experiment.md).
    ``solver``, ``solver_options``
    and ``threads`` serve the fallback from the start (the simultaneous NLP, at most :data:`MAX_ITER` iterations
    unless ``solver_options`` say otherwise).

    ``params`` (:class:`~kneenlp.model.params.Parameters`, instead of ``free`` and ``priors``):
    its varied parameters are fitted with its priors, bounds and ties; its values that differ from
    the knee's start the fit there (:func:`~kneenlp.estimation.choice.from_params`)."""
    options, ties = resolved_options(keyword_options(CalibrationOptions, "calibrate", {"free": free, **options}), model)
    data.check_observed("a calibration (its outlier test and prediction checks)")
    check_calibration(data, options)
    extra = also_free_names(model, options.also_free or [])
    before = predict(model, data)
    before.check_side()
    theta, engaged = engaged_probe(model, data, model.theta())
    free, fixed = calibration_choice(model, data, options, theta, engaged)
    priors = options.priors
    if options.with_priors and engaged and isinstance(priors, str):
        priors = engaged_priors(model, theta, engaged, free)
    extra = [n for n in extra if n not in free]
    fixed = [n for n in fixed if n not in extra]
    # the misfit is estimated from the residuals, whatever noise is declared: on a real knee the model's
    # error, not the instrument's noise, is what the parameters' and predictions' uncertainty must carry
    # (S192803: declared 0.2 mm, misfit about 1.5 mm); a declared noise serves diagnose's verdict
    problem = {"noise": options.noise if options.weighted else None, "weighted": options.weighted,
               "with_effects": options.with_effects or (), "priors": priors,
               "prior_weight": None if options.estimate else float(options.prior_weight),
               **({} if options.params is None else {"bounds": options.params.bounds(), "ties": ties})}
    inputs = CalibrationInputs(model, data, theta, problem, options)
    found = None
    if options.starts > 1:
        fit, outliers, found = global_fit(inputs, [*free, *extra])
    else:
        fit, outliers = local_fit(inputs, free, extra)
    aside = np.array([t.id in {o.trial for o in outliers} for t in data.trials])
    record = CalibrationRecord(before, fixed, engaged, predict(model, fit.data, fit.params), outliers,
                               predict(model, data.subset(aside), fit.params) if outliers else None, found)
    return Calibration(fit, record)


def resolved_options(options: CalibrationOptions, model: KneeModel) -> tuple[CalibrationOptions, dict[str, str] | None]:
    """(``options`` with their ``params`` resolved into ``free``, ``priors`` and ``start``
    (:func:`~kneenlp.estimation.choice.from_params`) and the number of ``starts`` decided, the
    ``params``' ties or None)."""
    ties = None
    if options.params is not None:
        given = {"free": options.free, "priors": None if options.priors == "default" else options.priors,
                 "start": options.start, "also_free": options.also_free, "pivot_tolerance": options.pivot_tolerance}
        free, priors, start, ties = from_params(model, options.params, **given)
        options = dataclasses.replace(options, free=free, priors=priors, start=start)
    if options.starts is None:
        options = dataclasses.replace(options, starts=1 if options.multistart > 1 else DEFAULT_STARTS)
    return options, ties


def local_fit(inputs: CalibrationInputs, free: list[str], extra: list[str]) -> tuple[Fit, list[Outlier]]:
    """(the fit, the outliers set aside) of :func:`calibrate`'s chain of local steps: the reduced fit
    of ``free`` from the probe (the options' ``start`` over it; :func:`first_fit`), ``extra`` freed from
    there (:func:`with_also_free`), the outliers set aside unless ``keep_outliers``, the NLP's polish
    and ``multistart`` further starts about the fit (:func:`lowest_of_starts`)."""
    model, settings = inputs.model, inputs.options
    options = dict(inputs.problem)
    problem = IdentificationProblem.from_data(model, inputs.data, free, **options)
    # the start is the knee (or the probe), not a scatter draw; every iterate at equilibrium (module
    # docstring: IPOPT wandered on this problem, and from a good point made it worse)
    start = inputs.probe_values(problem.free) | problem.check_start(settings.start)
    fit = first_fit(problem, start, settings)
    options["prior_weight"] = fit.problem.prior_weight
    if extra:
        fit = with_also_free(fit, inputs, extra, options)
        options["prior_weight"] = fit.problem.prior_weight
    outliers: list[Outlier] = []
    if not settings.keep_outliers:
        fit, outliers = without_outliers(fit, options)
    if fit.method == "reduced":
        fit = polished(fit, settings.threads)
    if settings.multistart > 1:
        fit = lowest_of_starts(fit, settings.multistart, settings.seed, settings.threads, settings.workers)
    return fit, outliers

def global_fit(inputs: CalibrationInputs, free: list[str]) -> tuple[Fit, list[Outlier], Search]:
    """(the fit, the outliers set aside, the search) of :func:`calibrate`'s global search
    (:func:`~kneenlp.estimation.search.search`): ``free`` (the also-free parameters among them) from
    the probe (and the options' ``start`` over it) and Sobol points over the priors; the outlier test
    at the search's lowest minimum unless ``keep_outliers``; without priors the starts cover the
    default priors about the probe; a prior weight ``None`` in the problem's options: estimated once
    from the probe's fit (:func:`map_fit`), then held."""
    model, settings = inputs.model, inputs.options
    problem = IdentificationProblem.from_data(model, inputs.data, sorted(free, key=model.index), **inputs.problem)
    centre = inputs.probe_values(problem.free) | problem.check_start(settings.start)
    if inputs.problem["prior_weight"] is None and problem.priors:
        problem = map_fit(problem, centre, estimate=True, threads=settings.threads).problem
    test = None if settings.keep_outliers else OutlierTest(outlier_candidate, outlier_verdict, MAX_OUTLIER_SHARE)
    # a least-squares calibration's starts cover the default priors about the probe (it has none to draw from)
    draws = problem.priors or {n: model.parameter(n).default_prior(float(inputs.probe[model.index(n)]))
                               for n in problem.free}
    found = search(problem, centre, Solves(screen=screened, refine=refined, hop=hopped),
                   SearchSettings(starts=settings.starts, seed=settings.seed, workers=settings.workers,
                                  threads=settings.threads, outliers=test, store=settings.store, priors=draws))
    fit = found.best.fit.with_note(f"global search: {found.advice()}")
    for note in found.notes:
        fit = fit.with_note(note)
    return fit, list(found.outliers), found


def screened(problem: IdentificationProblem, start: dict[str, float], q0: np.ndarray | None, threads: int) -> Fit:
    """A start's screen in the global search: :data:`~kneenlp.estimation.search.SCREEN_EVALUATIONS`
    reduced-space evaluations (every iterate at equilibrium)."""
    return reduced_fit(problem, start, q0=q0, max_evaluations=SCREEN_EVALUATIONS, threads=threads)


def refined(problem: IdentificationProblem, start: dict[str, float], q0: np.ndarray | None, threads: int) -> Fit:
    """A solve of the global search that must converge (a screened start, a minimum without a
    candidate outlier): the NLP from ``start`` and the poses ``q0`` (:func:`hopped`); where it
    fails, the reduced-space fit from the same point and the NLP from its end (:func:`polished`)."""
    fit = hopped(problem, start, q0, threads)
    if fit.success:
        return fit
    fit = polished(reduced_fit(problem, start, q0=q0, max_evaluations=MAX_EVALUATIONS, threads=threads), threads)
    return on_loading_path(fit) if fit.success else fit


def hopped(problem: IdentificationProblem, start: dict[str, float], q0: np.ndarray | None, threads: int) -> Fit:
    """A hop of the global search: the simultaneous NLP from ``start`` and the poses ``q0``, nothing
    more (a hop the NLP cannot converge is a failed hop: the reduced-space rescue cost 5-8 s on
    S192803 and found no lower minimum than the hops that converged)."""
    fit = solve_simultaneous(problem, start, polish_solver(threads), q0=q0)
    return on_loading_path(fit) if fit.success else fit


def first_fit(problem: IdentificationProblem, start: dict[str, float], options: CalibrationOptions) -> Fit:
    """The calibration's fit of ``problem`` from ``start`` (SI): :func:`map_fit`, and where it does not
    converge the simultaneous NLP with the scatter strategy's rescue (at most :data:`MAX_ITER`
    iterations unless the ``options``' ``solver_options`` say otherwise; their ``seed``, ``solver``
    and ``threads``), kept if it converges or ends lower."""
    fit = map_fit(problem, start, estimate=options.estimate)
    if fit.success:
        return fit
    fallback = scatter_fit(fit.problem, start, ScatterSettings(
        seed=options.seed, restarts=0, solver=options.solver,
        solver_options=options.solver_options or {"ipopt": {"max_iter": MAX_ITER}}, threads=options.threads))
    fallback = fallback.with_note(f"reduced-space Gauss-Newton did not converge ({fit.status}); the simultaneous "
                                  "NLP followed")
    return fallback if fallback.success or fallback.map_objective < fit.map_objective else fit


def with_also_free(fit: Fit, inputs: CalibrationInputs, extra: list[str], options: dict) -> Fit:
    """``fit`` of the ``inputs``' data refitted with the parameters ``extra`` free as well, started at
    their values in the probe (neutral) and the fit's (``options``: those of the fit's problem); the
    refit is kept if it does not end higher."""
    # the extra parameters join from this fit, at their neutral values: from the probe, with the
    # ligaments not yet placed, S192803's cruciate attachments ran 8-11 mm to another minimum
    # (sum of squares 344; from the fit 296, docs/real-experiment.md)
    model = fit.problem.model
    problem = IdentificationProblem.from_data(model, inputs.data, [*fit.problem.free, *extra], **options)
    start = fit.params | inputs.probe_values(extra)
    refit = map_fit(problem, start, q0=fit.q_pred, estimate=inputs.options.estimate)
    if refit.map_objective <= fit.map_objective:
        return refit
    return fit.with_note(f"fitting {', '.join(extra)} as well did not lower the sum of squares: they stay at "
                         "the knee's values")


#: Spread of the calibration's further starts about its fit, in prior standard deviations.
START_SPREAD = 0.5


def lowest_of_starts(fit: Fit, starts: int, seed: int, threads: int = 2, workers: int = 1) -> Fit:
    """``fit`` or, if lower, a fit of the same problem from one of ``starts - 1`` other points: each
    free parameter with a prior moved :data:`START_SPREAD` of its prior sd (in the prior's own scale,
    seeded) from the fit, within its bounds; each fitted as the calibration fits (reduced space, then
    the NLP), the starts shared out over ``workers`` processes (the same ends as one after another).
    The MAP objective has neighbouring minima: the starts make the choice explicit, and the fit's
    note lists every start's end."""
    rng = np.random.default_rng([seed, starts])
    problem = fit.problem
    lower, upper = problem.lower, problem.upper
    points = []
    for _ in range(starts - 1):
        start = dict(fit.params)
        for i, name in enumerate(problem.free):
            prior = problem.priors.get(name)
            if prior is not None:
                moved = prior.transform(fit.params[name]) + START_SPREAD * prior.sd * rng.standard_normal()
                start[name] = float(np.clip(prior.untransform(moved), lower[i], upper[i]))
        points.append(start)

    processes = min(workers, len(points))
    inner = max(1, threads // processes) if processes > 1 else threads  # the processes share the cores

    def solve(start: dict[str, float]) -> Fit:
        other = map_fit(problem, start, estimate=False, threads=inner)
        return polished(other, inner) if other.success and other.method == "reduced" else other

    ends = [fit, *forked_fits(solve, points, workers, problem.model)]
    kept = min((i for i, f in enumerate(ends) if f.success), key=lambda i: ends[i].map_objective, default=0)
    listed = ", ".join(f"{f.map_objective:.6g}" + ("" if f.success else " (not converged)") for f in ends)
    return ends[kept].with_note(f"{starts} starts (the fit, then {START_SPREAD:g} prior sd about it): MAP "
                                f"objectives {listed}; start {kept + 1} kept (the lowest converged)")


#: IPOPT iterations of the simultaneous NLP from a reduced-space fit (S192803: 52).
POLISH_ITER = 150
#: Relative objective by which the NLP may end above the reduced-space fit it started at and still
#: be taken (its constraints hold to 1e-6 N, the reduced fit's poses to the forward solver's tolerance).
POLISH_RTOL = 1e-9


def polish_solver(threads: int = 2) -> NlpSolver:
    """IPOPT limited to :data:`POLISH_ITER` iterations: the NLP of :func:`polished` and of the global search's hops."""
    return NlpSolver("ipopt", {"ipopt": {"max_iter": POLISH_ITER}}, threads)


def polished(fit: Fit, threads: int = 2) -> Fit:
    """The simultaneous NLP (every trial's equilibrium a constraint; :func:`solve_simultaneous`)
    started at the reduced-space ``fit``: the calibration's solver.  The reduced fit is its
    globalisation (every iterate at equilibrium, so it cannot wander off from the knee's values), the
    NLP its convergence to a KKT point: the reduced fit stops within the mesh contact's cost noise, at
    a point that depends on the order of its unknowns.  The NLP starts at the reduced fit's poses: from
    the unloaded state some trials reach other equilibria than its continuation followed, and IPOPT
    ends in another minimum.  S192803 (benchmarks/bench_compare_real.py): MAP objective 561.76
    reduced, 552.94 after 52 IPOPT iterations (1.4 s).  The reduced fit is kept, and the message says
    so, when the NLP fails or ends above it."""
    nlp = solve_simultaneous(fit.problem, fit.params, polish_solver(threads), q0=fit.q_pred)
    start = f"reduced-space Gauss-Newton ({fit.iterations} evaluations, MAP objective {fit.map_objective:.6g})"
    if nlp.success and nlp.map_objective <= fit.map_objective * (1 + POLISH_RTOL):
        return nlp.after(fit).with_note(f"started at the {start}")
    why = nlp.status if not nlp.success else f"it ended above ({nlp.map_objective:.6g})"
    return fit.with_note(f"the simultaneous NLP from the {start} did not improve it ({why}): the reduced fit is kept")


#: Rounds of :func:`map_fit`'s prior weight (the misfit variance the priors are weighed against).
WEIGHT_ROUNDS = 4
#: ... stopped when the estimate changes by less than this share.
WEIGHT_TOL = 0.2


def map_fit(problem: IdentificationProblem, start: dict[str, float], q0: np.ndarray | None = None,
            estimate: bool = True, threads: int = 2) -> Fit:
    """The reduced-space fit of ``problem`` from ``start``; with priors, ``estimate`` and no declared noise, the
    prior weight (the misfit variance per unit weight, :attr:`IdentificationProblem.prior_weight`)
    is the fit's own residual variance over its effective degrees of freedom
    (:func:`~kneenlp.estimation.statistics.effective_parameters`), refitted from the last fit until
    it changes by less than :data:`WEIGHT_TOL` (at most :data:`WEIGHT_ROUNDS` fits): a prior is
    weighed against the misfit the model actually has, which on a real knee is the model's error
    more than the instrument's noise."""

    fit = reduced_fit(problem, start, q0=q0, max_evaluations=MAX_EVALUATIONS, threads=threads)
    if not problem.priors or problem.noise is not None or not estimate:
        return fit
    for _ in range(WEIGHT_ROUNDS - 1):
        weight = fit.objective / max(fit.n_observations - effective_parameters(fit), 1.0)
        if abs(weight / problem.prior_weight - 1) < WEIGHT_TOL:
            break
        problem = dataclasses.replace(problem, prior_weight=weight)
        refit = reduced_fit(problem, fit.params, q0=fit.q_pred, max_evaluations=MAX_EVALUATIONS, threads=threads)
        if not refit.success and fit.success:
            break
        fit = refit.after(fit)
    return fit


def without_outliers(fit: Fit, options: dict) -> tuple[Fit, list[Outlier]]:
    """``fit`` refitted without the trials the outlier test sets aside (:mod:`~kneenlp.estimation.outliers`:
    the screen's worst trial (:func:`outlier_candidate`), refitted without and predicted
    (:func:`outlier_verdict`); at most :data:`MAX_OUTLIER_SHARE` of the trials, one at a time), and
    those trials; ``options`` those of the fit's problem (noise, weights, effects).  The refit is a
    local one from ``fit`` (the global search refits by its own search, :func:`global_fit`)."""
    found: list[Outlier] = []
    limit = int(MAX_OUTLIER_SHARE * len(fit.data))
    while len(found) < limit:
        worst = outlier_candidate(fit)
        if worst is None:
            break
        keep = np.array([t.id != worst for t in fit.data.trials])
        problem = IdentificationProblem.from_data(fit.problem.model, fit.data.subset(keep), fit.free, **options)
        refit = reduced_fit(problem, fit.params, q0=fit.q_pred[keep], max_evaluations=MAX_EVALUATIONS)
        outlier, why = outlier_verdict(refit, fit.data.subset(~keep), len(fit.data))
        if why:
            fit = fit.with_note(f"{worst} not tested as an outlier: {why}")
        if outlier is None:
            break
        fit, found = refit, [*found, outlier]
    return fit, found


def outlier_candidate(fit: Fit) -> str | None:
    """The trial of ``fit`` whose residuals the outlier screen finds worst, if its adjusted p-value is
    below :data:`~kneenlp.estimation.outliers.SCREEN_ALPHA` (:func:`~kneenlp.estimation.outliers.screen`,
    the leverages from the fit's sensitivities); else None."""
    residuals = fit.data.q_user - fit.predicted_user
    chi2, p = screen(residuals, len(fit.free),
                     factors=residual_factors(fit.sensitivity, fit.problem.weights, noise_per_observation(fit)))
    worst = int(np.argmax(chi2))
    return fit.data.trials[worst].id if p[worst] < SCREEN_ALPHA else None


def outlier_verdict(without: Fit, held: MeasuredData, n_trials: int) -> tuple[Outlier | None, str]:
    """The deletion test (:func:`~kneenlp.estimation.outliers.deletion_test`) of the one trial of
    ``held`` predicted by ``without``, the fit of the other trials (``n_trials`` in all): the outlier or
    None, and why it was not tested ("" if it was): a fit that lost a trial's equilibrium, or a
    candidate predict cannot solve, keeps the trial."""
    alone = predict(without.problem.model, held, without.params)
    lost = not without.max_residual <= without.problem.equilibrium_tol
    why = ("the fit without it lost a trial's equilibrium" if lost
           else "predict finds no equilibrium for it without it" if not alone.converged[0] else "")
    if why:
        return None, why
    trial = HeldOutTrial(held.trials[0].id, alone.errors_user[0], noise_per_observation(without)[0],
                         prediction_variances(without, held, np.array([alone.solutions[0].q]))[0])
    outlier = deletion_test(trial, max(len(without.data) - len(without.free) / 5, 1.0), n_trials)
    return outlier, ""
