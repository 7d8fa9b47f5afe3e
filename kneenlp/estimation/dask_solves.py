"""The global search's solves on Dask workers (``--dask`` / ``--scheduler``).

A solve needs its problem's model, whose compiled CasADi functions do not pickle.  What builds it
does (:attr:`KneeModel.arguments`: the knee, the user's parts, the measurement): a worker plugin
(Dask's own mechanism for per-worker state) carries them to every worker, which builds the model
once (the same graph, so the same numbers) and solves the problems sent without their model.
Every solve runs with one thread; what is solved is fixed by the search, so the workers change the
wall time only.  Imported only when a search runs on Dask (an optional dependency).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator

import numpy as np
from distributed import WorkerPlugin, as_completed, get_worker

from kneenlp.base.forked import one_blas_thread
from kneenlp.estimation.fit import Fit
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.problem import IdentificationProblem

PLUGIN_NAME = "kneenlp-search-knee"


class KneePlugin(WorkerPlugin):
    """Holds what builds the search's model on each worker, and the model built at the first solve."""

    name = PLUGIN_NAME

    def __init__(self, arguments: tuple):
        self.arguments = arguments
        self.model: KneeModel | None = None

    def model_of(self) -> KneeModel:
        if self.model is None:
            self.model = KneeModel(*self.arguments)
        return self.model


def without_model(problem: IdentificationProblem) -> IdentificationProblem:
    """A shallow copy of ``problem`` that pickles: its model left out."""
    out = copy.copy(problem)
    out.model = None
    return out


def _remote(solve: Callable, problem: IdentificationProblem, start: dict[str, float], q0: np.ndarray | None) -> Fit:
    """``solve`` on a worker: ``problem`` gets the worker's model for the solve, and its fit goes back without it."""
    plugin = get_worker().plugins[PLUGIN_NAME]
    problem = copy.copy(problem)
    problem.model = plugin.model_of()
    with one_blas_thread():  # one thread a worker, its BLAS too
        fit = solve(problem, start, q0, 1)
    fit.problem.model = None
    return fit


def dask_fits(client, solve: Callable, problem: IdentificationProblem,
              jobs: list[tuple[dict[str, float], np.ndarray | None]]) -> Iterator[tuple[int, Fit]]:
    """``(k, solve(problem, *jobs[k]))`` as each job finishes on ``client``'s workers; every fit
    with ``problem``'s model again."""
    sent = without_model(problem)
    futures = {client.submit(_remote, solve, sent, start, q0, pure=False): k for k, (start, q0) in enumerate(jobs)}
    for future in as_completed(futures):
        fit = future.result()
        fit.problem.model = problem.model
        yield futures[future], fit


def register_model(client, model: KneeModel) -> None:
    """Send what builds ``model`` to every worker of ``client`` (and to those that join later)."""
    client.register_plugin(KneePlugin(model.arguments))
