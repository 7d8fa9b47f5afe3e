"""Identify ligament parameters from measured laxity data: ``identify(knee, data, ...) -> Fit``,
the one entry point of the Python API and of ``kneenlp identify``.

**Strategy** (``strategy=``; docs/priors.md):

* ``"calibration"``: a real experiment's calibration (:func:`~kneenlp.estimation.calibrate.calibrate`):
  MAP with the default priors, the experiment's registration and the robot's load point fitted
  with every ligament parameter, started at the knee's values (a probe engaging groups slack in
  every trial), the outlier test; the fit's ``calibration`` holds what it found (the RMS before,
  the engaged groups, the outliers, ``predict``'s check).
* ``"scatter"``: the paper's identification: least squares by default, started at a seeded
  scatter around the knee's values, with restarts (below).
* ``"auto"`` (default): ``"calibration"`` for data of a real knee's experiment (as the data
  declare it: :class:`~kneenlp.experiment.kind.Experiment`) fitted by the simultaneous method,
  ``"scatter"`` otherwise (data the model produced, and the nested method).

``method="simultaneous"`` solves the single NLP of :mod:`kneenlp.solvers.nlp` with IPOPT (or another
CasADi ``nlpsol`` plugin given by ``solver``); ``method="nested"`` runs the paper's Complex
optimizer around per-trial rootfinders (:mod:`kneenlp.solvers.nested`) on the same objective.

How a fit starts and restarts, and the solves themselves: :mod:`kneenlp.estimation.solve`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from pathlib import Path

from kneenlp.base.errors import InputError
from kneenlp.base.keywords import refuse_unknown
from kneenlp.base.modes import Method, Strategy, checked
from kneenlp.estimation.calibrate import calibrate
from kneenlp.estimation.calibrated import Calibration
from kneenlp.estimation.choice import real_experiment
from kneenlp.estimation.fit import Fit
from kneenlp.estimation.search import SearchSettings
from kneenlp.estimation.solve import ScatterSettings, scatter_fit, scatter_search
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData, read_measured
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.path_checks import path_jumps
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.protocol import Protocol, available_protocols
from kneenlp.model.knee import Knee
from kneenlp.model.params import Parameters

#: Options only a calibration takes (:func:`~kneenlp.estimation.calibrate.calibrate`), by CLI flag.
CALIBRATION_OPTIONS = {"pivot_tolerance": "--pivot-tolerance", "also_free": "--also-free",
                       "keep_outliers": "--keep-outliers", "load_point": "--no-load-point", "workers": "--workers",
                       "starts": "--starts", "store": "--out"}
#: Options of the global search, which the scatter strategy takes too (``starts`` > 1).
SEARCH_OPTIONS = ("starts", "store", "workers")


@dataclass(frozen=True)
class IdentifyOptions:
    """:func:`identification`'s (and :func:`identify`'s) keyword arguments (its docstring), checked in
    one place (:meth:`from_kwargs`); ``calibration`` holds the calibration's own options that were
    given (:data:`CALIBRATION_OPTIONS`)."""

    free: list[str] | None = None
    start: dict[str, float] | None = None
    seed: int = 0
    noise: str | NoiseModel | None = None
    weighted: bool = False
    multistart: int = 1
    solver: str = "ipopt"
    solver_options: dict | None = None
    protocol: Protocol | str | None = None
    restarts: int = 4
    nested_options: dict | None = None
    with_effects: list[str] | None = None
    fixed: dict[str, float] | None = None
    threads: int = 2
    priors: str | dict | None = None
    prior_weight: float | str | None = None
    strategy: Strategy = "auto"
    calibration: dict = field(default_factory=dict)

    @classmethod
    def from_kwargs(cls, **options) -> IdentifyOptions:
        """The options named in ``options``, the calibration's own apart; an unknown strategy or a
        name :func:`identify` does not take is refused (TypeError for the name)."""
        checked("strategy", options.get("strategy", "auto"), Strategy)
        own = {f.name for f in fields(cls)} - {"calibration"}
        refuse_unknown("identify", options, own | set(CALIBRATION_OPTIONS))
        return cls(**{k: v for k, v in options.items() if k in own},
                   calibration={k: v for k, v in options.items() if k not in own})

    def scatter(self, method: Method) -> ScatterSettings:
        """The scatter strategy's settings of these options fitted by ``method``."""
        return ScatterSettings(seed=self.seed, method=method, multistart=self.multistart, restarts=self.restarts,
                               solver=self.solver, solver_options=self.solver_options, threads=self.threads,
                               nested_options=self.nested_options)


def identify(knee: Knee | KneeModel | None, data: MeasuredData | str | Path, params: Parameters | None = None,
             method: Method = "simultaneous", **options) -> Fit:
    """Identify parameters of ``knee`` from measured ``data``: the fit of :func:`identification`
    (``params`` and ``options`` as its)."""
    return identification(knee, data, params, method, **options).fit


def identification(knee: Knee | KneeModel | None, data: MeasuredData | str | Path, params: Parameters | None = None,
                   method: Method = "simultaneous", **options) -> Calibration:
    """Identify the ``free`` parameters of ``knee`` from measured ``data`` by ``strategy`` (module
    docstring).

    Parameters
    ----------
    knee : the knee (geometry + reference parameter set) or a :class:`KneeModel` (e.g. with user
        elements); ``None`` for the default knee.
    data : measured data or the path of a measured-data CSV (mm, deg).
    params : :class:`~kneenlp.model.params.Parameters` (``model.make_params()``; instead of ``free``,
        ``fixed``, ``priors``, ``with_effects``): the varied ones fitted with their priors, bounds, ties.
    method : ``"simultaneous"`` (one IPOPT program for all trials and parameters) or ``"nested"``.
    free : names of the parameters to identify (default: k and ref_strain of every ligament).
    start : starting values (SI) by name; missing ones are scattered like the paper (``seed``).
    noise : noise model of the measurements (e.g. ``"uniform:0.5"``): gives the noise variance of
        the covariance; without it the variance is estimated from the residuals.
    weighted : weight each coordinate by its inverse noise variance (needs ``noise``).
    multistart : number of starts (the best converged kept); restarts : extra draws while none converged.
    with_effects : candidate effects (:mod:`kneenlp.model.effects`) whose parameters are freed too,
        starting at their neutral values (e.g. ``["posterior_capsule"]``).
    fixed : values (SI, by name) of fixed parameters replacing the knee's parameter set, as
        ``simulate(parameters=...)`` does.
    nested_options : for ``method="nested"``: ``max_evals``, ``max_seconds``, ``xtol``, ``ftol``
        of the Complex optimizer, or ``initial`` (a list of starting parameter dicts, SI).
    solver : CasADi nlpsol plugin (``ipopt``, ``sqpmethod``, ...), options in ``solver_options``.
    protocol : protocol the data must match (by default the one named in the data, if known).
    threads : threads of the NLP's trial map and of the trials' Newton (1 in study workers, which run one
        process per core).
    priors : ``None``/``"none"`` (least squares, the paper's), ``"default"`` (every free parameter's
        prior from the knee's parameter file or the shipped defaults, centred on the knee's values:
        the MAP estimate) or a dict of :class:`~kneenlp.model.priors.Prior` by name over the defaults
        (docs/priors.md).
    prior_weight : the noise variance per unit weight the priors are weighed against (mm^2 or deg^2;
        default: 1 for a weighted fit, the declared noise's variance, else 1); for a calibration
        also ``"estimate"`` (:func:`~kneenlp.estimation.calibrate.map_fit`).
    strategy : ``"auto"``, ``"calibration"`` or ``"scatter"`` (module docstring).
    pivot_tolerance, also_free, keep_outliers, load_point, workers, starts, store : a calibration's
        own options (``workers``: the processes its further starts share; ``starts`` > 1: the global
        search, ``store`` the directory of its finished solves; :func:`~kneenlp.estimation.calibrate.calibrate`).

    Returns the :class:`~kneenlp.estimation.calibrated.Calibration`: the :class:`Fit` and, for a real
    experiment's calibration, what it found besides (its ``record``; an identification has none).
    """
    _check_names(params, method)
    opts = IdentifyOptions.from_kwargs(**options)
    model = KneeModel.of(knee or Knee.default())
    data = checked_data(data, opts.protocol)
    if resolve_strategy(opts.strategy, data, method) == "calibration":
        found = calibration(model, data, params, opts)
        return dataclasses.replace(found, fit=noted_path_jumps(found.fit))
    chosen = {"free": opts.free, "fixed": opts.fixed, "priors": opts.priors, "with_effects": opts.with_effects or ()}
    if params is not None:
        chosen = scatter_params(model, params, chosen)
    calibration_options = dict(opts.calibration)
    search_options = {}
    if calibration_options.get("starts", 1) > 1:  # the global search's options: a scatter fit's too
        search_options = {k: calibration_options.pop(k) for k in SEARCH_OPTIONS if k in calibration_options}
    _check_scatter(calibration_options, opts.prior_weight)
    problem = IdentificationProblem.from_data(model, data, noise=opts.noise, weighted=opts.weighted,
                                              prior_weight=opts.prior_weight, **chosen)
    start = problem.check_start(opts.start)
    if search_options:
        if method != "simultaneous":
            raise InputError("the global search solves the simultaneous NLP; --method nested has its own "
                             "population", field="--starts")
        return Calibration(noted_path_jumps(scatter_search(problem, start, SearchSettings(
            seed=opts.seed, threads=opts.threads, **search_options))))
    return Calibration(noted_path_jumps(scatter_fit(problem, start, opts.scatter(method))))


def noted_path_jumps(fit: Fit) -> Fit:
    """``fit`` with a note naming the trials whose fitted pose puts a wrapped ligament path where
    it is not smooth (:func:`~kneenlp.experiment.path_checks.path_jumps`)."""
    problem = fit.problem
    notes = path_jumps(problem.model, fit.q_pred, fit.theta, [t.flexion for t in problem.trials])
    found = [f"trial {t.id}: {n}" for t, n in zip(problem.trials, notes, strict=True) if n]
    return fit.with_note("wrapped paths at a discontinuity: " + "; ".join(found)) if found else fit


def scatter_params(model: KneeModel, params: Parameters, given: dict) -> dict:
    """What a scatter fit takes of ``params`` (:meth:`IdentificationProblem.from_data`'s keyword
    arguments): its varied parameters, every value that differs from the knee's (the fixed values
    and the varied ones' reference), their priors (None: none), bounds and ties; refused beside any
    of ``given`` (``free``, ``fixed``, ``priors``, ``with_effects``)."""
    moved = params.checked_against(model, given)
    return {"free": params.free, "fixed": moved, "priors": params.priors(), "bounds": params.bounds(),
            "ties": params.ties()}


def _check_names(params: object, method: Method) -> None:
    """Refuse a method given in place of ``params``, and an unknown method (:func:`identify`)."""
    if isinstance(params, str):
        raise TypeError("identify()'s third argument is a Parameters (model.make_params()); give the method by "
                        f"name: method={params!r}")
    checked("method", method, Method)


def _check_scatter(calibration_options: dict, prior_weight: float | str | None) -> None:
    """Refuse a calibration's own options in a fit by the scatter strategy."""
    for name, flag in CALIBRATION_OPTIONS.items():
        if name in calibration_options:
            raise InputError(f"{flag} changes what a real experiment's calibration fits; this fit is not one "
                             "(data of no laboratory experiment, --method nested, or --strategy scatter)",
                             field=flag)
    if prior_weight == "estimate":
        raise InputError("'estimate' is for a real experiment's calibration; give a variance (mm^2, deg^2)",
                         field="--prior-weight")


def checked_data(data: MeasuredData | str | Path, protocol: Protocol | str | None) -> MeasuredData:
    """``data`` (read if a path) checked against ``protocol``, by default the one named in the data if known."""
    if not isinstance(data, MeasuredData):
        data = read_measured(data)
    proto = protocol if isinstance(protocol, Protocol) or protocol is None else Protocol.load(protocol)
    if proto is None and data.protocol in available_protocols():
        proto = Protocol.load(data.protocol)
    if proto is not None:
        data.check_protocol(proto)
    return data


def calibration(model: KneeModel, data: MeasuredData, params: Parameters | None,
                options: IdentifyOptions) -> Calibration:
    """:func:`identification`'s calibration strategy: :func:`~kneenlp.estimation.calibrate.calibrate`
    with the ``options`` it takes (``priors`` and ``prior_weight`` where given) and ``params``."""
    if options.fixed:
        raise InputError("a calibration starts from the knee's parameter file: put the values there "
                         "(--parameters) instead of fixing them here", field="fixed")
    given = {"seed": options.seed, "noise": options.noise, "weighted": options.weighted,
             "with_effects": options.with_effects, "start": options.start, "solver": options.solver,
             "solver_options": options.solver_options, "multistart": options.multistart, "threads": options.threads,
             **options.calibration, **({} if params is None else {"params": params}),
             **({} if options.priors is None else {"priors": options.priors}),
             **({} if options.prior_weight is None else {"prior_weight": options.prior_weight})}
    return calibrate(model, data, options.free, **given)


def resolve_strategy(strategy: Strategy, data: MeasuredData, method: Method = "simultaneous") -> Strategy:
    """``"calibration"`` or ``"scatter"``: what ``strategy`` (``"auto"`` included) means for ``data``
    fitted by ``method`` (module docstring); a calibration by the nested method is refused."""
    if strategy == "auto":
        return "calibration" if method == "simultaneous" and real_experiment(data) else "scatter"
    if strategy == "calibration" and method != "simultaneous":
        raise InputError("a calibration is solved by the simultaneous method; --method nested fits by the "
                         "scatter strategy", field="--strategy")
    return strategy
