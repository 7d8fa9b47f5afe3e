"""Ligament line elements with the toe + linear force-strain law of the paper (Eq. 1-3).

``f(eps) = 0`` for ``eps <= 0``; ``k eps^2 / (4 eps_l)`` for ``0 <= eps <= 2 eps_l``;
``k (eps - eps_l)`` for ``eps >= 2 eps_l`` (Blankevoort & Huiskes 1991), with ``k`` in N per unit
strain and the linear strain limit ``eps_l`` (0.03 by default).  The law is C1 (force and slope
continuous at both kinks); kneenlp uses it exactly, without smoothing: Newton and IPOPT converge
on it, and the identified parameters then refer to the paper's law, not an approximation.  It is
written branch-free as ``k t^2 / (4 eps_l) + k max(eps - 2 eps_l, 0)`` with
``t = min(max(eps, 0), 2 eps_l)``, identical to Eq. (1) and expressible in every NLP exchange
format (no conditionals; see :mod:`kneenlp.io.export`).

Strain ``eps = (l - l0) / l0`` with slack length ``l0 = l_r / (1 + eps_r)`` where ``l_r`` is the
length in the reference pose and ``eps_r`` the reference strain (Eq. 2-3).
"""

from __future__ import annotations

import casadi as ca
import numpy as np


def force_strain(eps, k, eps_l):
    """Tensile force (N) of Eq. (1) as a CasADi expression (or number) of strain ``eps``."""
    t = ca.fmin(ca.fmax(eps, 0), 2 * eps_l)
    return k * t * t / (4 * eps_l) + k * ca.fmax(eps - 2 * eps_l, 0)


def force_strain_numpy(eps: np.ndarray, k: float, eps_l: float) -> np.ndarray:
    """NumPy version of Eq. (1), used for checking and plotting."""
    eps = np.asarray(eps, dtype=float)
    return np.where(
        eps <= 0, 0.0, np.where(eps <= 2 * eps_l, k * eps**2 / (4 * eps_l), k * (eps - eps_l))
    )


def slack_length(reference_length, ref_strain):
    """Slack length ``l0 = l_r / (1 + eps_r)`` (Eq. 2), same unit as ``reference_length``."""
    return reference_length / (1 + ref_strain)
