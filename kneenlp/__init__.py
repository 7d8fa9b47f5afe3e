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

import importlib

#: Where each public name lives; imported on first use (PEP 562), so ``import kneenlp`` and the
#: command line's start (``kneenlp --help``) do not load CasADi, SciPy and the meshes.
_HOMES = {
    "ConvergenceError": "kneenlp.base.errors",
    "InputError": "kneenlp.base.errors",
    "identify": "kneenlp.estimation.identify",
    "identification": "kneenlp.estimation.identify",
    "KneeModel": "kneenlp.experiment.kneemodel",
    "NoiseModel": "kneenlp.experiment.noise",
    "Protocol": "kneenlp.experiment.protocol",
    "Trial": "kneenlp.experiment.protocol",
    "Knee": "kneenlp.model.knee",
    "ParameterSet": "kneenlp.model.parameters",
    "Parameters": "kneenlp.model.params",
    "SimulationResult": "kneenlp.simulation",
    "simulate": "kneenlp.simulation",
}


def __getattr__(name: str):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'kneenlp' has no attribute {name!r}")
    return getattr(importlib.import_module(home), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *_HOMES])


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
    "identification",
    "identify",
    "simulate",
]
