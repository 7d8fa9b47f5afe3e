"""A fit's posterior as ArviZ InferenceData (netCDF): ``posterior.nc`` beside ``calibrated.toml``.

The posterior is the Laplace approximation (:mod:`kneenlp.model.posterior`); its draws (seeded,
``CHAINS`` x ``DRAWS``, display units: N, %, mm, deg, ...) fill the ``posterior`` group, one
variable per parameter, so that ``arviz.summary``, ``plot_posterior`` and ``plot_pair`` work on it.
``observed_data`` holds the measured coordinates (trial x coordinate, deg and mm).  Parameters a
direction nothing determined leaves with an infinite variance have no draws (``attrs`` names them).
ArviZ is optional (``pip install 'kneenlp[arviz]'``): :func:`available` says whether it is there.
"""

from __future__ import annotations

import importlib.util
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kneenlp.base.conventions import coordinate_columns
from kneenlp.model.posterior import Posterior

if TYPE_CHECKING:
    from kneenlp.estimation.fit import Fit

CHAINS = 4
DRAWS = 1000


def available() -> bool:
    """Is ArviZ installed?"""
    return importlib.util.find_spec("arviz") is not None


def posterior_draws(posterior: Posterior, values: Mapping[str, float], seed: int,
                    chains: int = CHAINS, draws: int = DRAWS) -> tuple[dict[str, np.ndarray], list[str]]:
    """({name: (chains, draws) array, SI}, names without draws): normal draws about ``values`` (SI)
    with the posterior's covariance, from ``seed``."""
    cov = np.asarray(posterior.covariance, float)
    finite = np.isfinite(np.diag(cov))
    names = [n for n, f in zip(posterior.names, finite, strict=True) if f]
    mean = np.array([values[n] for n in names])
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(mean, cov[np.ix_(finite, finite)], size=(chains, draws), method="eigh")
    return {n: x[..., i] for i, n in enumerate(names)}, [n for n, f in zip(posterior.names, finite, strict=True)
                                                         if not f]


def write_inference_data(path: str | Path, fit: Fit, posterior: Posterior, seed: int = 0) -> Path:
    """Write ``path`` (netCDF; module docstring): draws of ``fit``'s free parameters from its
    ``posterior`` about its values, in their display units, beside its data."""
    values, data = fit.params, fit.data
    units = {n: (fit.info(n).unit, fit.info(n).to_user) for n in fit.free}
    with warnings.catch_warnings():  # ArviZ announces its refactor on import: not the user's concern here
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az

    draws, undetermined = posterior_draws(posterior, values, seed)
    idata = az.from_dict(
        posterior={n: v * units[n][1] for n, v in draws.items()},
        observed_data={"measured": data.q_user},
        coords={"trial": [t.id for t in data.trials], "coordinate": coordinate_columns()},
        dims={"measured": ["trial", "coordinate"]},
        attrs={"method": f"{posterior.method}: normal draws about the fitted values (bounds not applied), seed {seed}",
               "units": "; ".join(f"{n} [{units[n][0]}]" for n in draws),
               "no_draws_infinite_variance": ", ".join(undetermined) or "none",
               "source": data.source or "", "inference_library": "kneenlp"})
    path = Path(path)
    idata.to_netcdf(str(path))
    return path
