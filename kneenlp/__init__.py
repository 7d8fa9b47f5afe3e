"""kneenlp: identify knee ligament properties from laxity tests, and say how far to trust them.

Public API (see README.md)::

    import kneenlp
    knee = kneenlp.Knee.default()                 # the embedded default right knee
    protocol = kneenlp.Protocol.load("set3")      # Table 2 of the laxity-noise paper
    result = kneenlp.simulate(knee, protocol)     # forward laxity simulation
    result.table()                                # pandas table in mm / deg / N
    fit = kneenlp.identify(knee, "measured.csv")  # the one fit entry point (CLI: kneenlp identify)
    print(fit.report())
"""

from kneenlp.base.errors import ConvergenceError, InputError
from kneenlp.estimation.identify import identify
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.protocol import Protocol, Trial
from kneenlp.model.knee import Knee
from kneenlp.model.parameters import ParameterSet
from kneenlp.simulation import SimulationResult, simulate

__version__ = "0.1.0"

__all__ = [
    "ConvergenceError",
    "InputError",
    "Knee",
    "KneeModel",
    "NoiseModel",
    "ParameterSet",
    "Protocol",
    "SimulationResult",
    "Trial",
    "identify",
    "simulate",
]
