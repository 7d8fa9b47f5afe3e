"""The simultaneous identification NLP: ONE program for all trials and the ligament parameters.

Unknowns ``x = [p_free / scale, q_1 ... q_T in user units]``: the free parameters, scaled to order
one (k / 1e4 N, strains / 1e-2, modulus / 1e10 N/m^3), and the five free coordinates of every
trial in mm and deg (the units of the objective).  Equality constraints: every trial's
equilibrium residual (the model's one residual function, N m and N) is zero.  Objective: the
(optionally weighted) sum of squared differences between model and measured coordinates in mm and
deg, the paper's ``Psi^T Psi``.

The NLP is built once per (model, number of trials, free parameters, solver): all data enter as
the NLP parameter vector ``p = [theta (all parameters, SI), measured poses, weights, loads,
flexions]``, so refitting other data or other fixed values never rebuilds or recompiles it.

Speed choices: the residual is an MX graph around the vectorised contact (see
:mod:`kneenlp.model.contact`), mapped over trials with ``map(T, "thread", 2)`` so both cores evaluate
trials (serial in study workers, see :func:`set_map_threads`); it is *not* expanded to SX (that
would inline every contact point of every trial, the prototype's 75k-instruction-per-trial
mistake).  IPOPT gets exact first and second derivatives
from CasADi's AD (Lagrangian Hessian through the map) and uses MUMPS; the KKT system is tiny and
block-sparse, so linear algebra is negligible next to function evaluations.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from kneenlp.conventions import TO_USER
from kneenlp.errors import InputError, unknown_name
from kneenlp.model.kneemodel import KneeModel

# Scales and bounds of every parameter live in its ParameterInfo (kneenlp/parameters.py and
# kneenlp/effects.py): k / 1e4 N in [0, 1e5] N, strains / 1 % in [-30, 30] %, linear strain limit
# in [0.5, 10] %, modulus / 10 GN/m^3 in [0.1, 1000] GN/m^3.
#: Bounds of the coordinates in user units (deg, deg, mm, mm, mm): the physiological envelope.
Q_BOUNDS = np.array([30.0, 60.0, 25.0, 25.0, 25.0])

_MAP_THREADS = 2


def set_map_threads(n: int) -> None:
    """Threads of the trial map in NLPs built from now on (1 = serial).  Study workers set 1:
    they already run one process per core, and two threads each would oversubscribe the cores."""
    global _MAP_THREADS
    _MAP_THREADS = max(1, int(n))


def map_threads() -> int:
    return _MAP_THREADS


def default_free(model: KneeModel) -> list[str]:
    """k and reference strain of every ligament (8 values for the four-ligament knee)."""
    return [f"{lig}.{k}" for lig in model.ligament_names for k in ("k", "ref_strain")]


def check_free(model: KneeModel, free: list[str]) -> list[str]:
    for name in free:
        if name not in model.parameter_names:
            raise unknown_name("parameter", name, model.parameter_names)
    if len(set(free)) != len(free):
        raise InputError(f"free parameters repeated: {', '.join(free)}", field="free")
    if not free:
        raise InputError("no free parameters", field="free")
    return list(free)


@dataclass
class IdentificationNLP:
    """A built NLP solver with its layout; see module docstring."""

    model: KneeModel
    n_trials: int
    free: list[str]
    solver_name: str
    solver: ca.Function
    scales: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray
    build_seconds: float

    @property
    def n_free(self) -> int:
        return len(self.free)

    def pack_p(self, theta: np.ndarray, measured_user: np.ndarray, weights: np.ndarray,
               loads: np.ndarray, flexions: np.ndarray) -> np.ndarray:
        """NLP parameter vector from the data (shapes (n,), (T,5), (T,5), (T,6), (T,))."""
        return np.concatenate([theta, measured_user.ravel(), weights.ravel(), loads.ravel(), flexions])

    def pack_x(self, values: np.ndarray, q_user: np.ndarray) -> np.ndarray:
        """Decision vector from free parameter values (SI) and poses (T x 5, mm/deg)."""
        return np.concatenate([np.asarray(values) / self.scales, np.asarray(q_user).ravel()])

    def unpack_x(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free parameter values in SI, poses T x 5 in mm/deg)."""
        x = np.asarray(x, dtype=float).ravel()
        return x[: self.n_free] * self.scales, x[self.n_free :].reshape(self.n_trials, 5)


@dataclass
class NLPExpressions:
    """The symbolic identification NLP (MX): decision vector, data vector, objective, constraints."""

    x: ca.MX
    p: ca.MX
    f: ca.MX
    g: ca.MX
    scales: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray


def nlp_expressions(model: KneeModel, n_trials: int, free: list[str], parallel: str = "thread") -> NLPExpressions:
    """Build the NLP's expressions (see module docstring); ``parallel`` is the trial map's mode."""
    free = check_free(model, free)
    n_theta, nf, T = len(model.parameter_names), len(free), n_trials
    infos = [model.parameter_info[model.index(n)] for n in free]
    scales = np.array([i.scale for i in infos])
    xp = ca.MX.sym("p_free", nf)
    xq = ca.MX.sym("q_user", 5, T)
    par = ca.MX.sym("data", n_theta + 5 * T + 5 * T + 6 * T + T)
    theta_in = par[:n_theta]
    meas = ca.reshape(par[n_theta : n_theta + 5 * T], 5, T)
    w = ca.reshape(par[n_theta + 5 * T : n_theta + 10 * T], 5, T)
    loads = ca.reshape(par[n_theta + 10 * T : n_theta + 16 * T], 6, T)
    flex = ca.reshape(par[n_theta + 16 * T :], 1, T)
    # theta element by element, so that fixed parameters (e.g. the contact modulus) depend on no
    # decision variable structurally: the Hessian then never seeds the contact with parameter
    # directions (a dense selection matrix made it ~2x slower).
    pos = {n: j for j, n in enumerate(free)}
    theta = ca.vertcat(*[scales[pos[n]] * xp[pos[n]] if n in pos else theta_in[i]
                         for i, n in enumerate(model.parameter_names)])
    q_si = xq / ca.DM(TO_USER)  # deg, mm -> rad, m
    if parallel == "thread" and _MAP_THREADS > 1:
        mapped = model.residual.map(T, "thread", _MAP_THREADS)
    else:
        mapped = model.residual.map(T, "serial" if parallel == "thread" else parallel)
    g = ca.vec(mapped(q_si, theta, loads, flex))
    bias = model.measurement_bias(theta) * ca.DM(TO_USER)  # registration effects, mm / deg
    diff = xq + ca.repmat(bias, 1, T) - meas
    f = ca.sum1(ca.sum2(w * diff * diff))
    lo = np.array([i.lower for i in infos]) / scales
    hi = np.array([i.upper for i in infos]) / scales
    lbx = np.concatenate([lo, np.tile(-Q_BOUNDS, T)])
    ubx = np.concatenate([hi, np.tile(Q_BOUNDS, T)])
    return NLPExpressions(ca.vertcat(xp, ca.vec(xq)), par, f, g, scales, lbx, ubx)


def build_nlp(model: KneeModel, n_trials: int, free: list[str], solver: str = "ipopt",
              options: dict | None = None) -> IdentificationNLP:
    """Build the identification NLP solver (see module docstring)."""
    import time

    t0 = time.perf_counter()
    free = check_free(model, free)
    e = nlp_expressions(model, n_trials, free)
    nlp = {"x": e.x, "p": e.p, "f": e.f, "g": e.g}
    opts = dict(options or {})
    if solver == "ipopt":
        ipopt = {"tol": 1e-10, "acceptable_tol": 1e-9, "constr_viol_tol": 1e-9, "max_iter": 150,
                 "print_level": 0, "linear_solver": "mumps", "mu_strategy": "monotone",
                 "nlp_scaling_method": "gradient-based", "sb": "yes"}
        ipopt.update(opts.pop("ipopt", {}))
        opts = {"ipopt": ipopt, "print_time": False, "error_on_fail": False, **opts}
    else:
        opts = {"print_time": False, "error_on_fail": False, **opts}
    try:
        fn = ca.nlpsol(f"identify_{solver}", solver, nlp, opts)
    except RuntimeError as exc:
        raise InputError(f"cannot create NLP solver {solver!r}: {str(exc).splitlines()[-1]}",
                         field="solver") from None
    return IdentificationNLP(model, n_trials, free, solver, fn, e.scales, e.lbx, e.ubx, time.perf_counter() - t0)
