"""Identify ligament parameters from measured laxity data: ``identify(knee, data, ...) -> Fit``.

``method="simultaneous"`` solves the single NLP of :mod:`kneenlp.solvers.nlp` with IPOPT (or another
CasADi ``nlpsol`` plugin given by ``solver``); ``method="nested"`` runs the paper's Complex
optimizer around per-trial rootfinders (:mod:`kneenlp.solvers.nested`) on the same objective.

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

import time
from pathlib import Path

import casadi as ca
import numpy as np

from kneenlp.conventions import TO_USER, coords_to_user
from kneenlp.errors import InputError, unknown_name
from kneenlp.experiment.measured import MeasuredData, read_measured
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.protocol import Protocol, available_protocols
from kneenlp.inference.fit import Fit
from kneenlp.model.knee import Knee
from kneenlp.model.kneemodel import KneeModel
from kneenlp.simulation import model_for
from kneenlp.solvers.forward import ForwardSolver
from kneenlp.solvers.nlp import IdentificationNLP, build_nlp, check_free, default_free, map_threads

METHODS = ("simultaneous", "nested")
_NLP_CACHE: dict[tuple, IdentificationNLP] = {}


def paper_scatter(model: KneeModel, free: list[str], rng: np.random.Generator,
                  reference: dict[str, float] | None = None) -> dict[str, float]:
    """Uniform scatter around ``reference`` (default: the knee's parameter set), as in the paper:
    +-500 N on stiffnesses, +-0.02 on reference strains, +-10 % on other parameters (SI)."""
    ref = reference or dict(zip(model.parameter_names, model.theta(), strict=True))
    out = {}
    for n in free:
        info = model.parameter_info[model.index(n)]
        if info.neutral is not None:  # effect parameters start at their neutral value
            out[n] = info.neutral
            continue
        kind = n.rsplit(".", 1)[-1]
        half = {"k": 500.0, "ref_strain": 0.02}.get(kind, 0.1 * abs(ref[n]))
        out[n] = float(min(max(ref[n] + rng.uniform(-half, half), info.lower), info.upper))
    return out


def get_nlp(model: KneeModel, n_trials: int, free: list[str], solver: str, options: dict | None) -> IdentificationNLP:
    key = (id(model), n_trials, tuple(free), solver, repr(sorted((options or {}).items())), map_threads())
    nlp = _NLP_CACHE.get(key)
    if nlp is None or nlp.model is not model:
        nlp = build_nlp(model, n_trials, free, solver, options)
        _NLP_CACHE[key] = nlp
    return nlp


def sensitivities(model: KneeModel, data: MeasuredData, theta: np.ndarray, q: np.ndarray,
                  free: list[str]) -> np.ndarray:
    """``d q_user / d p_free`` (5T x n_free; mm or deg per SI parameter unit) at equilibrium poses
    ``q`` (SI), by the implicit-function theorem through each trial's equilibrium."""
    jac = _jacobians(model)
    idx = [model.index(n) for n in free]
    d_bias = TO_USER[:, None] * np.asarray(_bias_jacobian(model)(theta))[:, idx]  # registration effects
    rows = []
    for t, qi in zip(data.trials, q, strict=True):
        dq, dth = (np.asarray(v) for v in jac(qi, theta, t.load, t.flexion))
        try:
            rows.append(-TO_USER[:, None] * np.linalg.solve(dq, dth[:, idx]) + d_bias)
        except np.linalg.LinAlgError:  # singular equilibrium (e.g. a failed solve): least squares
            rows.append(-TO_USER[:, None] * (np.linalg.pinv(dq) @ dth[:, idx]) + d_bias)
    return np.vstack(rows)


def _bias_jacobian(model: KneeModel) -> ca.Function:
    fn = getattr(model, "_bias_jac", None)
    if fn is None:
        fn = model.measurement_bias.factory("bias_jac", ["theta"], ["jac:bias:theta"])
        model._bias_jac = fn
    return fn


def _forward_solver(model: KneeModel) -> ForwardSolver:
    fs = getattr(model, "_forward_solver", None)
    if fs is None:
        fs = ForwardSolver(model)
        model._forward_solver = fs
    return fs


def _jacobians(model: KneeModel) -> ca.Function:
    fn = getattr(model, "_jac_q_theta", None)
    if fn is None:
        fn = model.residual.factory("jac_q_theta", ["q", "theta", "load", "flexion"], ["jac:r:q", "jac:r:theta"])
        model._jac_q_theta = fn
    return fn


def identify(knee: Knee | KneeModel | None, data: MeasuredData | str | Path, method: str = "simultaneous", *,
             free: list[str] | None = None, start: dict[str, float] | None = None, seed: int = 0,
             noise: str | NoiseModel | None = None, weighted: bool = False, multistart: int = 1,
             solver: str = "ipopt", solver_options: dict | None = None,
             protocol: Protocol | str | None = None, restarts: int = 4,
             nested_options: dict | None = None, with_effects: list[str] | None = None) -> Fit:
    """Identify the ``free`` parameters of ``knee`` from measured ``data``.

    Parameters
    ----------
    knee : the knee (geometry + reference parameter set); ``None`` for the default knee.
    data : measured data or the path of a measured-data CSV (mm, deg).
    method : ``"simultaneous"`` (one IPOPT program for all trials and parameters).
    free : names of the parameters to identify (default: k and ref_strain of every ligament).
    start : starting values (SI) by name; missing ones are scattered like the paper (``seed``).
    noise : noise model of the measurements (e.g. ``"uniform:0.5"``): gives the noise variance of
        the covariance; without it the variance is estimated from the residuals.
    weighted : weight each coordinate by its inverse noise variance (needs ``noise``).
    multistart : number of starts; the best converged one is kept.
    restarts : extra scatter draws tried when no start has converged yet.
    with_effects : candidate effects (:mod:`kneenlp.model.effects`) whose parameters are freed too,
        starting at their neutral values (e.g. ``["posterior_capsule"]``).
    nested_options : for ``method="nested"``: ``max_evals``, ``max_seconds``, ``xtol``, ``ftol``
        of the Complex optimizer, or ``initial`` (a list of starting parameter dicts, SI).
    solver : CasADi nlpsol plugin (``ipopt``, ``sqpmethod``, ...), options in ``solver_options``.
    protocol : protocol the data must match (by default the one named in the data, if known).
    """
    if method not in METHODS:
        raise unknown_name("method", method, METHODS)
    model = model_for(knee or Knee.default())  # a KneeModel with user effects is accepted too
    if not isinstance(data, MeasuredData):
        data = read_measured(data)
    proto = protocol if isinstance(protocol, Protocol) or protocol is None else Protocol.load(protocol)
    if proto is None and data.protocol in available_protocols():
        proto = Protocol.load(data.protocol)
    if proto is not None:
        data.check_protocol(proto)
    free = list(free or default_free(model))
    for name in with_effects or []:
        free += [n for n in model.effect(name).free_names() if n not in free]
    free = check_free(model, free)
    noise_model = NoiseModel.parse(noise) if noise is not None else None
    if weighted and (noise_model is None or noise_model.std == 0):
        raise InputError("weighted fit needs a noise model with non-zero level", field="noise")
    weights = np.full((len(data), 5), 1.0 / noise_model.std**2 if weighted else 1.0)
    if start:
        for n in start:
            if n not in free:
                raise unknown_name("free parameter", n, free)
    rng = np.random.default_rng(seed)
    if method == "nested":
        return _nested(model, data, free, start, rng, seed, weights, noise_model, dict(nested_options or {}))
    best: Fit | None = None
    k = 0

    def good(f: Fit | None) -> bool:
        return f is not None and f.success and not _at_bounds(f) and not _implausible_misfit(f, noise_model)

    while k < max(1, multistart) or (not good(best) and k < max(1, multistart) + restarts):
        s = paper_scatter(model, free, rng)
        if k == 0 and start:
            s.update(start)
        fit = _simultaneous(model, data, free, s, weights, noise_model, solver, solver_options)
        if best is None or (good(fit) and not good(best)) or \
                (fit.success and good(fit) == good(best) and fit.objective < best.objective) or \
                (fit.success and not best.success):
            best = fit
        k += 1
    if best.success and _at_bounds(best):
        note = "ligament parameters at their bounds: a poor local minimum or a model that cannot fit the data"
        best.message = f"{best.message}; {note}" if best.message else note
    best.extra["starts"] = k
    if k > max(1, multistart):
        note = f"{k - max(1, multistart)} restart(s) after failed solves"
        best.message = f"{best.message}; {note}" if best.message else note
    return best


def _implausible_misfit(fit: Fit, noise: NoiseModel | None) -> bool:
    """With a known noise model, a misfit the noise cannot explain (chi-square p < 1e-9) marks a
    wrong local minimum worth a restart (the best fit is kept either way)."""
    if noise is None or noise.std <= 0:
        return False
    from scipy import stats

    chi2 = float(np.sum(fit.residuals**2)) / noise.std**2
    return bool(stats.chi2.sf(chi2, max(fit.residuals.size - len(fit.free), 1)) < 1e-9)


def _at_bounds(fit: Fit) -> bool:
    """True if a ligament parameter sits on its bound (the prototype's wrong-minimum signature)."""
    for n in fit.free:
        info = fit.model.parameter_info[fit.model.index(n)]
        if info.neutral is not None or n == "contact.modulus":
            continue
        span = info.upper - info.lower
        if min(fit.params[n] - info.lower, info.upper - fit.params[n]) <= 1e-6 * span:
            return True
    return False


def _noise_variance(noise_model, objective, weights, n_par):
    if noise_model is not None:
        return (np.full(weights.shape, noise_model.std**2),
                f"given ({noise_model}: std {noise_model.std:.4g} mm or deg)")
    s2 = objective / max(weights.size - n_par, 1) / float(np.mean(weights))
    return np.full(weights.shape, s2), f"estimated from residuals (std {np.sqrt(s2):.4g} mm or deg)"


def _nested(model, data, free, start, rng, seed, weights, noise_model, options) -> Fit:
    from kneenlp.solvers.nested import nested_fit

    initial = options.pop("initial", None)
    if initial is None:
        clouds = [paper_scatter(model, free, rng) for _ in range(2 * len(free) + 1)]
        if start:
            clouds[0].update(start)
        initial = clouds
    cloud = np.array([[c[n] for n in free] for c in initial])
    out = nested_fit(model, data, free, weights, cloud, seed=seed, **options)
    params = dict(zip(free, out["values"], strict=True))
    theta = model.theta(params)
    q = out["q"]
    max_res = float(np.max(out["residual"]))
    res = out["result"]
    psi = float(np.sum(weights * (coords_to_user(q) - data.q_user) ** 2))
    variance, source = _noise_variance(noise_model, psi, weights, len(free))
    return Fit(model=model, data=data, method="nested", free=list(free), params=params, theta=theta,
               objective=psi, status=res.message, success=bool(res.success) and max_res <= 1e-6,
               iterations=int(res.nit), seconds=out["seconds"], max_residual=max_res, q_pred=q,
               sensitivity=sensitivities(model, data, theta, q, free), weights=weights, noise_variance=variance,
               noise_source=source, start=dict(zip(free, cloud[0], strict=True)), evaluations=out["trial_solves"],
               message=f"{res.nfev} objective evaluations", solver="complex",
               extra={"objective_evaluations": res.nfev, "history": res.history})


def _simultaneous(model, data, free, start, weights, noise_model, solver, solver_options) -> Fit:
    t0 = time.perf_counter()
    nlp = get_nlp(model, len(data), free, solver, solver_options)
    theta0 = model.theta(start)
    # equilibrium-consistent start: Newton on all trials at once from the measured poses,
    # per-trial ramping for the few that fail; a trial that still fails starts at its data
    q0, res0 = _forward_solver(model).solve_batch(data.trials, theta0, data.q)
    ok = res0 <= 1e-6
    q0_user = np.where(ok[:, None], coords_to_user(q0), data.q_user)
    n_fail_start = int(np.sum(~ok))
    loads = np.array([t.load for t in data.trials])
    flex = np.array([t.flexion for t in data.trials])
    p = nlp.pack_p(model.theta(), data.q_user, weights, loads, flex)
    x0 = nlp.pack_x([start[n] for n in free], q0_user)
    t1 = time.perf_counter()
    sol = nlp.solver(x0=x0, p=p, lbx=nlp.lbx, ubx=nlp.ubx, lbg=0, ubg=0)
    seconds = time.perf_counter() - t1
    stats = nlp.solver.stats()
    values, q_user = nlp.unpack_x(sol["x"])
    params = dict(zip(free, values, strict=True))
    theta = model.theta(params)
    q = q_user / TO_USER
    g = np.asarray(sol["g"]).ravel()
    max_res = float(np.max(np.abs(g))) if g.size else 0.0
    sens = sensitivities(model, data, theta, q, free)
    objective = float(sol["f"])
    variance, source = _noise_variance(noise_model, objective, weights, len(free))
    success = bool(stats.get("success", False)) and max_res <= 1e-6
    msg = "" if n_fail_start == 0 else f"{n_fail_start} trial(s) could not be solved at the start; started at data"
    if bool(stats.get("success", False)) and max_res > 1e-6:
        msg = (msg + "; " if msg else "") + f"equilibrium residual {max_res:.2e} above 1e-6"
    return Fit(model=model, data=data, method="simultaneous", free=list(free), params=params, theta=theta,
               objective=objective, status=str(stats.get("return_status", "unknown")), success=success,
               iterations=int(stats.get("iter_count", -1)), seconds=seconds, max_residual=max_res, q_pred=q,
               sensitivity=sens, weights=weights, noise_variance=variance, noise_source=source,
               start=dict(start), build_seconds=nlp.build_seconds, evaluations=int(stats.get("iter_count", -1)),
               message=msg, solver=nlp.solver_name,
               extra={"start_seconds": t1 - t0})
