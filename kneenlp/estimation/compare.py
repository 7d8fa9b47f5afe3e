"""The paper's two methods on the same data: the simultaneous NLP and the nested Complex method,
their estimates, costs and largest relative parameter difference (``kneenlp compare-methods``).

On a real experiment (:func:`compare_calibration`) the problem is the calibration's (MAP with the
default priors, registration and load point, every trial): the reduced-space Gauss-Newton fit,
IPOPT from the calibration's start, IPOPT from the reduced fit (the calibration's solver,
:func:`~kneenlp.estimation.calibrate.polished`) and the nested Complex method from the same start,
its best objective reported after 1k, 5k, 20k and 75k rootfinder solves (trial equilibria)."""

from __future__ import annotations

from pathlib import Path

from kneenlp.base.errors import InputError
from kneenlp.estimation.identify import identify
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.model.knee import Knee


def compare_methods(knee: Knee | KneeModel | None, data: MeasuredData | str | Path, *, seed: int = 0,
                    max_evals: int = 20000, max_seconds: float | None = None) -> dict:
    """Identify ``data`` with both methods (nested: at most ``max_evals`` objective evaluations and
    ``max_seconds``).  Returns ``{"units": display unit per free parameter, "methods": one row per
    method}``; a row holds the objective (mm^2 + deg^2), the estimates (display units), evaluations,
    iterations, seconds, largest equilibrium residual (N or N m), status and success, and the
    nested row the largest relative difference of its estimates from the simultaneous ones."""
    fits = [identify(knee, data, seed=seed),
            identify(knee, data, method="nested", seed=seed,
                     nested_options={"max_evals": max_evals, "max_seconds": max_seconds})]
    rows = [{"method": f.method, "objective": f.objective, "params": f.params_user(),
             "evaluations": f.iterations if f.method == "simultaneous" else f.equilibrium_solves,
             "evaluation_kind": "IPOPT iterations" if f.method == "simultaneous"
             else "rootfinder solves (trial equilibria)", "iterations": f.iterations,
             "seconds": f.seconds, "max_residual": f.max_residual, "status": f.status, "success": f.success}
            for f in fits]
    ref = fits[0].params
    rows[1]["max_relative_difference"] = max(abs(fits[1].params[n] - ref[n]) / abs(ref[n]) for n in ref)
    return {"units": {n: fits[0].info(n).unit for n in fits[0].free}, "methods": rows}


#: Rootfinder solves (trial equilibria) after which the nested method's best objective is reported.
CHECKPOINTS = (1_000, 5_000, 20_000, 75_000)


def compare_calibration(model: KneeModel, data: MeasuredData, *, seed: int = 0, max_solves: int = CHECKPOINTS[-1],
                        max_seconds: float | None = None) -> dict:
    """The methods on a real experiment's calibration problem (module docstring).  Returns
    ``{"problem": ..., "methods": rows, "nested_checkpoints": {solves: best MAP objective}}``; a row
    holds the MAP objective (mm^2 + deg^2), evaluations and their kind, seconds, the largest
    equilibrium residual (N or N m), status and success (a fit stopped at a cap is not converged)."""
    import numpy as np

    from kneenlp.estimation.calibrate import MAX_EVALUATIONS, calibrate, polish_solver
    from kneenlp.estimation.choice import engaged_probe
    from kneenlp.estimation.solve import nested_fit_of, reduced_fit, solve_simultaneous
    from kneenlp.solvers.nlp import NlpSolver

    problem = calibrate(model, data, keep_outliers=True, seed=seed).fit.problem  # the calibration's problem
    theta, _ = engaged_probe(model, data, model.theta())
    start = {n: float(theta[model.index(n)]) for n in problem.free}
    reduced = reduced_fit(problem, start, max_evaluations=MAX_EVALUATIONS)
    direct = solve_simultaneous(problem, start, NlpSolver("ipopt", {"ipopt": {"max_iter": 500}}))
    from_reduced = solve_simultaneous(problem, reduced.params, polish_solver(),
                                      q0=reduced.q_pred)  # as polished() does, reported whatever it reaches
    rng = np.random.default_rng(seed)
    evals = int(np.ceil(max_solves / problem.n_trials))
    if evals < 2 * problem.n_free + 1:  # the Complex's first population alone
        raise InputError(f"the nested method needs at least {(2 * problem.n_free + 1) * problem.n_trials} solves "
                         f"here ({2 * problem.n_free + 1} starting points x {problem.n_trials} trials)",
                         field="--max-solves")
    nested = nested_fit_of(problem, start, rng, seed, {"max_evals": evals, "max_seconds": max_seconds})
    history = nested.result.history
    checkpoints = {}
    for solves in CHECKPOINTS:
        done = history[history[:, 0] * problem.n_trials <= solves]
        if solves <= max_solves and len(done):
            checkpoints[solves] = float(done[-1, 1])

    def row(name, fit, count, kind):
        return {"method": name, "map_objective": fit.map_objective, "objective": fit.objective,
                "evaluations": int(count), "evaluation_kind": kind, "seconds": fit.seconds,
                "max_residual": fit.max_residual, "status": fit.status, "success": fit.success}

    rows = [row("reduced", reduced, reduced.evaluations, "residual evaluations (each solves every trial)"),
            row("simultaneous (from the start)", direct, direct.iterations, "IPOPT iterations"),
            row("simultaneous (from the reduced fit)", from_reduced.after(reduced), from_reduced.iterations,
                "IPOPT iterations after the reduced fit"),
            row("nested", nested, nested.equilibrium_solves, "rootfinder solves (trial equilibria)")]
    return {"problem": {"trials": problem.n_trials, "free": problem.n_free, "priors": bool(problem.priors),
                        "prior_weight": problem.prior_weight},
            "methods": rows, "nested_checkpoints": checkpoints}
