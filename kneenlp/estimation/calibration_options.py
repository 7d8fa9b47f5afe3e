"""The options of a real experiment's calibration (:func:`~kneenlp.estimation.calibrate.calibrate`),
checked in one place, and what its two ways of fitting start from."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kneenlp.base.dask_cluster import DaskWorkers
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.model.params import Parameters

#: The misfit variance (mm^2, deg^2) a calibration's priors are weighed against by default: the
#: misfit a calibrated laxity model reaches, about 1 mm and 1 deg.  Held out on S192803 it predicted
#: better than the weight estimated from the fit (which grows with the model's error, 5-12 mm^2:
#: the priors then hold the knee near values that do not fit; docs/priors.md).
PRIOR_WEIGHT = 1.0


@dataclass(frozen=True)
class CalibrationOptions:
    """:func:`~kneenlp.estimation.calibrate.calibrate`'s keyword arguments (its docstring), with
    ``free``; checked in one place (:func:`~kneenlp.base.keywords.keyword_options`)."""

    free: list[str] | None = None
    seed: int = 0
    noise: object = None
    load_point: bool = True
    pivot_tolerance: float | None = None
    also_free: list[str] | None = None
    keep_outliers: bool = False
    priors: str | dict | None = "default"
    prior_weight: float | str = PRIOR_WEIGHT
    weighted: bool = False
    with_effects: list[str] | tuple = ()
    start: dict[str, float] | None = None
    solver: str = "ipopt"
    solver_options: dict | None = None
    multistart: int = 1
    threads: int = 2
    workers: int | DaskWorkers = 1
    starts: int | None = None
    store: str | Path | None = None
    params: Parameters | None = None


    @property
    def with_priors(self) -> bool:
        """Whether the fit is a MAP estimate (priors other than none)."""
        return self.priors not in (None, "none")

    @property
    def estimate(self) -> bool:
        """Whether the prior weight is estimated from the fit (:func:`~kneenlp.estimation.calibrate.map_fit`)."""
        return self.prior_weight == "estimate"


@dataclass(frozen=True)
class CalibrationInputs:
    """What both ways of fitting a calibration start from (:func:`~kneenlp.estimation.calibrate.local_fit`,
    :func:`~kneenlp.estimation.calibrate.global_fit`):
    the ``model``, the real experiment's ``data``, the ``probe`` (the knee's parameter vector with
    the slack groups engaged, SI), the ``problem``'s keyword arguments
    (:meth:`IdentificationProblem.from_data`) and the calibration's ``options``."""

    model: KneeModel
    data: MeasuredData
    probe: np.ndarray
    problem: dict
    options: CalibrationOptions

    def probe_values(self, names: list[str]) -> dict[str, float]:
        """The probe's values of ``names`` (SI)."""
        return {n: float(self.probe[self.model.index(n)]) for n in names}
