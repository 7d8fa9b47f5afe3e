"""kneenlp: identify knee ligament properties from laxity tests, and say how far to trust them.

Public API (see README.md)::

    import kneenlp
    knee = kneenlp.Knee.default()                 # the embedded default right knee
    protocol = kneenlp.Protocol.load("set3")      # Table 2 of the laxity-noise paper
    result = kneenlp.simulate(knee, protocol)     # forward laxity simulation
    result.table()                                # pandas table in mm / deg / N
"""

from .errors import ConvergenceError, InputError
from .knee import Knee
from .model import KneeModel
from .noise import NoiseModel
from .parameters import ParameterSet
from .protocol import Protocol, Trial
from .simulate import SimulationResult, simulate

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
    "simulate",
]
