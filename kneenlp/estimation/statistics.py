"""Least-squares statistics, each computed in one place: noise variance, chi-square test, the
weighted SVD and rank, Gauss-Newton covariance from sensitivities, and the information criteria.

Units: residuals in mm and deg; sensitivities ``S`` in mm or deg per SI unit of each parameter
(5T x n); ``scales`` the parameters' NLP scales (SI), used to compare directions of different units.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats

from kneenlp.experiment.noise import NoiseModel

#: Relative singular-value threshold below which a parameter direction counts as undetermined.
RANK_TOL = 1e-6


def noise_variance(noise: NoiseModel | None, objective: float, weights: np.ndarray,
                   n_free: int) -> tuple[np.ndarray, str]:
    """Per-observation noise variance (T x 5, mm^2 or deg^2) and where it came from: the given
    noise model, else estimated from the weighted residual sum ``objective``."""
    if noise is not None:
        return (np.full(weights.shape, noise.std**2),
                f"given ({noise}: std {noise.std:.4g} mm or deg)")
    seen = weights[weights > 0]  # the observed coordinates: an experiment may not measure some
    s2 = objective / max(seen.size - n_free, 1) / float(np.mean(seen))
    return np.full(weights.shape, s2), f"estimated from residuals (std {np.sqrt(s2):.4g} mm or deg)"


def chi_square_test(residuals: np.ndarray, weights: np.ndarray | None, variance: np.ndarray | float,
                    n_free: int) -> tuple[float, int, float]:
    """``(chi2, dof, p)`` with ``chi2 = sum r^2 / sigma^2`` (whatever weights the fit used) on
    ``N - n_free`` degrees of freedom; ``weights`` is accepted for a uniform call signature."""
    r = np.asarray(residuals, float).ravel()
    var = np.broadcast_to(np.asarray(variance, float), np.shape(residuals)).ravel()
    seen = np.isfinite(r)  # NaN: a coordinate the experiment does not observe
    r, var = r[seen], var[seen]
    chi2 = float(np.sum(r**2 / var))
    dof = max(r.size - n_free, 1)
    return chi2, dof, float(stats.chi2.sf(chi2, dof))


def information_criteria(wrss: float, n_observations: int, n_free: int) -> tuple[float, float]:
    """``(AIC, BIC)`` of a weighted least-squares fit: ``N ln(WRSS/N) + 2 p`` and
    ``N ln(WRSS/N) + p ln N`` with ``WRSS = sum w r^2`` the fit's own objective (mm^2 + deg^2 times
    the weights).  This is -2 times the Gaussian log-likelihood with the variances known up to one
    common factor (``sigma_i^2 = s^2 / w_i``, ``s^2`` maximised out) plus the penalty; its constant
    ``-sum ln w_i`` is the same for every model fitted to the same data and weights, so it is dropped
    and only differences between such models mean anything.  With unit weights it is the ordinary
    ``N ln(RSS/N)`` form; a weighted fit must use its weighted sum (the unweighted RSS of a weighted
    fit is not what the fit minimised and ranks models differently when the weights differ)."""
    n = n_observations
    base = n * np.log(max(wrss, 1e-300) / n)
    return float(base + 2 * n_free), float(base + n_free * np.log(n))


def weighted_svd(sensitivity: np.ndarray, weights: np.ndarray,
                 scales: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(U, singular values, V')`` of the weighted, scaled sensitivity matrix ``sqrt(W) S D``
    (``S``: 5T x n, mm or deg per SI unit; ``weights``: one per row; ``D``: the parameters' scales):
    its rank is how many parameter directions the data determine (:func:`svd_rank`) and the rows
    of ``V'`` beyond it are the directions they do not."""
    w = np.sqrt(np.asarray(weights, float).ravel())[:, None]
    return np.linalg.svd(w * np.asarray(sensitivity, float) * np.asarray(scales, float), full_matrices=True)


def svd_rank(singular_values: np.ndarray) -> int:
    """Numerical rank from singular values (relative threshold :data:`RANK_TOL`)."""
    sv = np.asarray(singular_values)
    return int(np.sum(sv > RANK_TOL * sv.max())) if sv.size and sv.max() > 0 else 0


def gauss_newton_covariance(sensitivity: np.ndarray, weights: np.ndarray, variance: np.ndarray,
                            scales: np.ndarray, names: Sequence[str] | None = None) -> np.ndarray:
    """Linearised covariance of least-squares estimates (SI units of the parameters).

    Sandwich form ``A^-1 S' W Sigma W S A^-1`` with ``A = S' W S`` (``sigma^2 (S'S)^-1`` for an
    unweighted fit with equal noise), computed in scaled units with the rank cut of
    :func:`svd_rank`.  Parameters in a direction the data do not determine get infinite variance
    (and NaN covariances).
    """
    s = np.asarray(sensitivity, float)
    w = np.asarray(weights, float).ravel()
    sig = np.broadcast_to(np.asarray(variance, float), (s.shape[0],)) if np.ndim(variance) == 0 else \
        np.asarray(variance, float).ravel()
    d = np.asarray(scales, float)
    ss = s * d
    _, sv_w, vt_w = weighted_svd(s, w, d)
    rank = svd_rank(sv_w)
    a_s = ss.T @ (w[:, None] * ss)
    b_s = ss.T @ ((w * sig * w)[:, None] * ss)
    u, sv, vt = np.linalg.svd(a_s)
    keep = sv > (1e-12 * sv.max() if sv.size else 0)
    keep[rank:] = False
    inv = (vt[keep].T / sv[keep]) @ u[:, keep].T
    cov = (inv @ b_s @ inv.T) * np.outer(d, d)
    for i in range(rank, s.shape[1]):  # undetermined directions
        for j in np.flatnonzero(np.abs(vt_w[i]) > 0.05):
            cov[j, :] = cov[:, j] = np.nan
            cov[j, j] = np.inf
    return cov


def fisher_information(sensitivity: np.ndarray, sigma: float) -> np.ndarray:
    """Per-trial Fisher information ``S_t' S_t / sigma^2`` (T x n x n) of sensitivities (5T x n)."""
    n = sensitivity.shape[1]
    blocks = np.asarray(sensitivity, float).reshape(-1, 5, n)
    return np.einsum("tki,tkj->tij", blocks, blocks) / sigma**2


def effective_parameters(fit) -> float:
    """The effective number of parameters of a (MAP) fit: the trace of its hat matrix,
    ``tr(A_d' A_d (A_d' A_d + A_p' A_p)^-1)`` with ``A_d`` the weighted data rows and ``A_p`` the
    priors' rows (:meth:`~kneenlp.estimation.fit.Fit.with_prior_rows`); the number of free
    parameters without priors.  A parameter its prior alone determines counts 0, one the data
    alone determine 1."""
    s, w, _ = fit.with_prior_rows(1.0)
    a = np.sqrt(w)[:, None] * s * np.asarray(fit.scales, float)
    n_data = 5 * fit.problem.n_trials
    data, total = a[:n_data].T @ a[:n_data], a.T @ a
    return float(np.trace(np.linalg.pinv(total, rcond=1e-12, hermitian=True) @ data))
