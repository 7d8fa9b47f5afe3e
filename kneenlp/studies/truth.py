"""What every sample of a study shares: the knee model and each protocol's true simulation.

:class:`StudyTruths` builds them on first use and keeps them for as long as its owner keeps it:
one per study run (:func:`~kneenlp.studies.study.run_study` makes it, or takes the caller's, and
hands it to the samples it solves in its own process and to the analysis), one per worker process
(each local worker keeps the run's, forked with it).  Nothing is memoised at module level: a knee file edited between
two studies is read again by the next one.
"""

from __future__ import annotations

from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.simulation import SimulationResult


class StudyTruths:
    """The model of knee file ``knee`` (None: the default knee) with user ``elements`` (import
    paths, ``"module:factory"``) and its noise-free simulation of each protocol, built on first use.

    Pickled (for a worker process that is not forked) it carries its arguments alone; the worker
    builds what it needs again."""

    def __init__(self, knee: str | None, elements: tuple[str, ...] = ()):
        self.knee, self.elements = knee, tuple(elements)
        self._model: KneeModel | None = None
        self._truths: dict[str, SimulationResult] = {}

    @classmethod
    def of(cls, spec) -> StudyTruths:
        """The truths of a study's knee and elements (``spec``: a
        :class:`~kneenlp.studies.study.StudySpec`)."""
        return cls(spec.knee, tuple(spec.elements))

    def __getstate__(self) -> dict:
        return {"knee": self.knee, "elements": self.elements}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["knee"], state["elements"])

    @property
    def model(self) -> KneeModel:
        """The knee's model with the user elements."""
        if self._model is None:
            from kneenlp.model.knee import Knee
            from kneenlp.model.plugins import load_elements

            k = Knee.load(self.knee) if self.knee else Knee.default()
            self._model = KneeModel(k, load_elements(self.elements))
        return self._model

    def truth(self, set_name: str) -> SimulationResult:
        """The noise-free simulation of protocol ``set_name`` at the knee's parameter set."""
        if set_name not in self._truths:
            from kneenlp.simulation import simulate

            res = simulate(self.model, set_name)
            if res.failed:
                raise InputError(f"truth simulation of {set_name} failed: "
                                 f"{', '.join(s.trial.id for s in res.failed)}")
            self._truths[set_name] = res
        return self._truths[set_name]
