"""What every sample of a study shares: the knee model and each protocol's true simulation.

Built once per process and study arguments (memoised on the arguments themselves, which are plain
strings, so the memo is valid for any process that computes them).
"""

from __future__ import annotations

from functools import lru_cache

from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.simulation import SimulationResult


@lru_cache(maxsize=4)
def study_model(knee: str | None, elements: tuple[str, ...] = ()) -> KneeModel:
    """The model of knee file ``knee`` (None: the default knee) with user ``elements`` (import paths)."""
    from kneenlp.model.knee import Knee
    from kneenlp.model.plugins import load_elements

    k = Knee.load(knee) if knee else Knee.default()
    return KneeModel(k, load_elements(elements)) if elements else KneeModel.of(k)


@lru_cache(maxsize=16)
def study_truth(knee: str | None, elements: tuple[str, ...], set_name: str) -> SimulationResult:
    """The noise-free simulation of protocol ``set_name`` at the knee's parameter set."""
    from kneenlp.simulation import simulate

    res = simulate(study_model(knee, elements), set_name)
    if res.failed:
        raise InputError(f"truth simulation of {set_name} failed: {', '.join(s.trial.id for s in res.failed)}")
    return res
