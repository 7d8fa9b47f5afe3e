"""The paper's two methods on the same data: the simultaneous NLP and the nested Complex method,
their estimates, costs and largest relative parameter difference (``kneenlp compare-methods``)."""

from __future__ import annotations

from pathlib import Path

from kneenlp.experiment.measured import MeasuredData
from kneenlp.inference.identify import identify
from kneenlp.model.knee import Knee
from kneenlp.model.kneemodel import KneeModel


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
             "evaluations": f.evaluations, "evaluation_kind": "IPOPT iterations" if f.method == "simultaneous"
             else "rootfinder solves (trial equilibria)", "iterations": f.iterations,
             "seconds": f.seconds, "max_residual": f.max_residual, "status": f.status, "success": f.success}
            for f in fits]
    ref = fits[0].params
    rows[1]["max_relative_difference"] = max(abs(fits[1].params[n] - ref[n]) / abs(ref[n]) for n in ref)
    return {"units": {n: fits[0]._info(n).unit for n in fits[0].free}, "methods": rows}
