"""The identification problem: one labelled experiment that every estimator and design consumes.

An :class:`IdentificationProblem` holds the model, the trials (what was done), the measured
coordinates (or none, for design), the noise model and weights, which parameters are free and the
values of the fixed ones.  It sits below the solvers (docs/architecture.md) and owns, once each:

* the free-vector encoding: the scaled parameters (:meth:`to_scaled`, :meth:`from_scaled`,
  :attr:`scaled_bounds`), the NLP's decision vector ``x = [p_free / scale, q (T x 5, mm and deg)]``
  (:meth:`to_x`, :meth:`from_x`, :meth:`x_bounds`) and the full parameter vector of scaled
  symbols (:meth:`theta_of_scaled`);
* the data-vector layout (:class:`DataLayout`: :meth:`data_vector` packs it, the NLP and export
  split it);
* the one equilibrium tolerance (:attr:`equilibrium_tol`,
  :data:`~kneenlp.base.conventions.EQUILIBRIUM_TOL`).

From it:

* the simultaneous NLP (:mod:`kneenlp.solvers.nlp`) takes its data vector, scales and bounds;
* the nested objective (:mod:`kneenlp.solvers.nested`) evaluates :meth:`objective`;
* :meth:`sensitivities` gives ``d y / d p`` through every trial's equilibrium (the covariance of
  a fit, the score tests of adequacy and the Fisher information of design all use it);
* export writes its NLP.

Every comparison of model and measurement goes through the model's ONE observation function
(:attr:`kneenlp.experiment.kneemodel.KneeModel.observation`): predicted coordinates in mm and deg,
including any measurement bias of the model's elements.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import casadi as ca
import numpy as np

from kneenlp.base.conventions import (
    EQUILIBRIUM_TOL,
    LOAD_SIZE,
    coords_from_user,
    coords_to_user,
    pose_envelope_user,
)
from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.keywords import keyword_options
from kneenlp.experiment.kind import SIMULATED, Experiment
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.problem_choices import ProblemChoices, check_free, free_names, resolve_priors
from kneenlp.experiment.protocol import Loading, Trial
from kneenlp.model.parameters import Parameter
from kneenlp.model.priors import Prior
from kneenlp.model.space import ParameterSpace


def prior_rows(values, centre, inv_sd, logs: Sequence[bool]):
    """``inv_sd * (transform(value) - centre)`` per free parameter, ``transform`` the log where
    ``logs`` says so: the priors' residual rows, for NumPy values and CasADi symbols alike (the
    MAP objective adds their squares; :meth:`IdentificationProblem.prior_data` gives ``centre``
    and ``inv_sd``)."""
    symbolic = isinstance(values, ca.SX | ca.MX)
    log = ca.log if symbolic else np.log
    rows = [(log(values[i]) if lg else values[i]) - centre[i] for i, lg in enumerate(logs)]
    return (ca.vertcat(*rows) if symbolic else np.array(rows, dtype=float)) * inv_sd


def held_values(trials) -> np.ndarray:
    """The values the apparatus holds each trial's coordinates at (T x 5, SI; NaN: free)."""
    out = np.full((len(trials), 5), np.nan)
    for k, t in enumerate(trials):
        for i, value in t.held:
            out[k, i] = value
    return out


@dataclass(frozen=True)
class DataLayout:
    """The NLP's data vector ``p``: the full parameter vector (SI), then per trial (trial-major)
    the measured coordinates (5, mm and deg), the weights (5, per mm^2 or deg^2), the load vector
    (:data:`~kneenlp.base.conventions.LOAD_SIZE`, N and N m), the flexion (rad) and, for a program
    holding its contact working sets as data, the working sets (``n_ws``)."""

    n_theta: int
    n_trials: int
    n_ws: int = 0
    n_prior: int = 0

    #: the parts in order, with the rows each trial has (the parts of :data:`ONCE` are one column)
    PARTS = ("theta", "prior_centre", "prior_inv_sd", "measured", "weights", "loads", "flexions", "working_sets")
    ONCE = ("theta", "prior_centre", "prior_inv_sd")

    def rows(self) -> dict[str, int]:
        """Rows per trial of each part (the parts of :data:`ONCE`: their length, once)."""
        return {"theta": self.n_theta, "prior_centre": self.n_prior, "prior_inv_sd": self.n_prior, "measured": 5,
                "weights": 5, "loads": LOAD_SIZE, "flexions": 1, "working_sets": self.n_ws}

    def slices(self) -> dict[str, slice]:
        """Where each part sits in ``p``."""
        out, start = {}, 0
        for name, rows in self.rows().items():
            size = rows if name in self.ONCE else rows * self.n_trials
            out[name] = slice(start, start + size)
            start += size
        return out

    @property
    def size(self) -> int:
        return self.slices()["working_sets"].stop

    def split(self, p: ca.MX | ca.SX) -> dict[str, ca.MX | ca.SX]:
        """The parts of a symbolic ``p``: ``theta`` a column, the others ``rows x T`` (one column a trial)."""
        rows = self.rows()
        return {name: p[sl] if name in self.ONCE else ca.reshape(p[sl], rows[name], self.n_trials)
                for name, sl in self.slices().items()}

    def pack(self, parts: Mapping[str, np.ndarray | None]) -> np.ndarray:
        """``p`` from its ``parts`` by name (:attr:`PARTS`, what :meth:`split` returns; the per-trial parts
        as ``T x rows`` arrays; ``working_sets`` may be left out for a layout without them)."""
        T = self.n_trials
        missing = [name for name in self.PARTS[:-1] if name not in parts]
        if missing or set(parts) - set(self.PARTS):
            raise ValueError(f"data parts {sorted(parts)}, expected {list(self.PARTS)}")
        working_sets = parts.get("working_sets")
        ws = np.zeros((T, 0)) if working_sets is None else np.asarray(working_sets, float)
        if ws.shape != (T, self.n_ws):
            raise ValueError(f"working sets of shape {ws.shape}, expected ({T}, {self.n_ws})")
        centre, inv_sd = (np.asarray(parts[n], float).ravel() for n in ("prior_centre", "prior_inv_sd"))
        if centre.size != self.n_prior or inv_sd.size != self.n_prior:
            raise ValueError(f"prior parts of sizes {centre.size}, {inv_sd.size}, expected {self.n_prior}")
        return np.concatenate([np.asarray(parts["theta"], float).ravel(), centre, inv_sd,
                               *(np.asarray(parts[n], float).reshape(T, -1).ravel()
                                 for n in ("measured", "weights", "loads", "flexions")), ws.ravel()])

    def describe(self) -> str:
        """The layout in words (units included), for export's sidecar."""
        return ("theta (all model parameters, SI, in 'parameters' order), the priors of the free parameters "
                "(centres: the mean in SI or, for a log-normal, the log of the median; then the inverse widths "
                "times the square root of the prior weight, 0 for none), measured coordinates (T x 5, "
                "mm/deg), weights (T x 5), loads (T x 15: force and moment, femoral frame; generalised forces; "
                "N and N m; the force's tibial point, m, and the tuberosity's weight), flexion (T, rad), "
                "then, only for contact='expansion', the contact working sets at the start poses (T x "
                "ws_size): per point x, y, z (m) and area (m^2) for sphere contact; for mesh contact the "
                "pose and the contact wrench's second-order expansion there "
                "(kneenlp.model.mesh_contact.WS_SIZE)")


@dataclass
class IdentificationProblem:
    """Model + trials + measurements (or none) + noise/weights + free and fixed parameters."""

    model: KneeModel
    trials: tuple[Trial, ...]
    free: list[str]
    measured: np.ndarray | None = None  # (T, 5) mm and deg
    weights: np.ndarray | None = None  # (T, 5) per mm^2 or deg^2; None: all 1
    noise: NoiseModel | None = None
    fixed: dict[str, float] = field(default_factory=dict)  # values (SI) replacing the knee's parameter set
    source: str | None = None
    protocol: str | None = None
    #: priors of free parameters by name (a free parameter without one is determined by the data alone)
    priors: dict[str, Prior] = field(default_factory=dict)
    #: the noise variance per unit weight (mm^2 or deg^2 times the weights) that puts the priors'
    #: ``z^2`` on the scale of the weighted sum of squares: the MAP objective is
    #: ``sum w r^2 + prior_weight * sum z^2`` (1 for a fit weighted by 1/variance)
    prior_weight: float = 1.0
    #: bounds (SI) of free parameters replacing their declared ones (a ``Parameters``' min and max)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: ties (:mod:`kneenlp.model.ties`) over the knee's own: a tied parameter follows the free ones
    ties: dict[str, str] = field(default_factory=dict)
    #: the experiment the data come from (what it observes; its load point is in the trials' loads)
    experiment: Experiment = SIMULATED

    def __post_init__(self) -> None:
        self.trials = tuple(self.trials)
        self.free = check_free(self.model, self.free)
        for n in self.fixed:
            self.model.index(n)
        for n, prior in self.priors.items():
            if n not in self.free:
                raise unknown_name("free parameter with a prior", n, self.free)
            self.model.parameter(n).check_prior(prior)
        for n, (lo, hi) in self.bounds.items():
            if n not in self.free:
                raise unknown_name("free parameter with bounds", n, self.free)
            if not lo < hi:
                raise InputError(f"lower bound {lo:g} not below upper {hi:g} (SI)", field=f"parameters.{n}")
        self.ties = {**self.model.knee.parameters.ties, **self.ties}
        for n in self.ties:
            if n in self.free:
                raise InputError("a tied parameter (expr) cannot be free: its value follows its tie",
                                 field=f"parameters.{n}")
        self.space = ParameterSpace(tuple(self.model.parameter_names), tuple(self.free), self.scales, self.lower,
                                    self.upper, self.ties)
        _ = self.space.order  # unknown names and cycles: an error now, not at the first solve
        if not (np.isfinite(self.prior_weight) and self.prior_weight > 0):
            raise InputError(f"prior weight must be > 0, got {self.prior_weight!r}", field="prior_weight")
        if self.weights is None:
            self.weights = np.ones((len(self.trials), 5))
        if self.measured is not None:
            self.measured = np.asarray(self.measured, dtype=float)
            if self.measured.shape != (len(self.trials), 5):
                raise InputError(f"measured coordinates have shape {self.measured.shape}, "
                                 f"expected ({len(self.trials)}, 5)", source=self.source)
            self.weights = np.where(self.observed, self.weights, 0.0)

    @property
    def measured_start(self) -> np.ndarray:
        """The measured poses as starts (T x 5, mm and deg): a coordinate the experiment does not
        observe at the knee's reference pose, a held one at its value."""
        start = np.where(np.isfinite(self.measured), self.measured, coords_to_user(self.model.knee.reference_pose[1]))
        held = held_values(self.trials)
        return np.where(np.isfinite(held), coords_to_user(np.nan_to_num(held)), start)

    @property
    def measured_q(self) -> np.ndarray:
        """:attr:`measured_start` in SI (rad, m)."""
        return coords_from_user(self.measured_start)

    @property
    def observed(self) -> np.ndarray:
        """Which coordinates of which trial were measured (T x 5, bool; NaN in ``measured``: not
        observed by the experiment, weighed zero).  A coordinate the apparatus holds is an input
        (the trial is held at its value), not an observation: weighed zero too."""
        held = np.isfinite(held_values(self.trials))
        return ~held if self.measured is None else np.isfinite(self.measured) & ~held

    @classmethod
    def from_data(cls, model: KneeModel, data: MeasuredData, free: Sequence[str] | None = None,
                  **choices) -> IdentificationProblem:
        """The problem of identifying ``free`` (default: k and ref_strain of every ligament, plus
        the parameters of ``with_effects``) from measured ``data``; ``choices`` (checked together,
        :class:`~kneenlp.experiment.problem_choices.ProblemChoices`): ``noise`` (a noise model or its
        spec), ``weighted`` (by 1/variance), ``fixed`` values (SI), ``with_effects``, ``priors`` as
        :func:`resolve_priors`; ``prior_weight`` the noise variance per unit weight the priors are
        weighed against (default: 1 for a weighted fit, the declared noise variance, else 1);
        ``bounds`` and ``ties`` as the fields'."""
        c = keyword_options(ProblemChoices, "from_data", choices)
        model.knee.check_flexions(data.trials, data.source)
        free = free_names(model, free, c.with_effects)
        noise_model = NoiseModel.parse(c.noise) if c.noise is not None else None
        weighted, prior_weight = c.weighted, c.prior_weight
        if weighted and (noise_model is None or noise_model.std == 0):
            raise InputError("weighted fit needs a noise model with non-zero level", field="noise")
        weights = np.full((len(data), 5), 1.0 / noise_model.std**2 if weighted else 1.0)
        if prior_weight is None:
            prior_weight = 1.0 if weighted or noise_model is None or noise_model.std == 0 else noise_model.std**2
        fixed = dict(c.fixed or {})
        return cls(model, tuple(data.trials), free, data.q_user, weights, noise_model, fixed,
                   data.source, data.protocol, resolve_priors(model, free, c.priors, fixed), float(prior_weight),
                   {n: b for n, b in (c.bounds or {}).items() if n in free}, dict(c.ties or {}), data.experiment)

    def without_trials(self, ids: Sequence[str]) -> IdentificationProblem:
        """The same problem without the trials ``ids`` (their measurements and weights too)."""
        keep = np.array([t.id not in set(ids) for t in self.trials])
        return replace(self, trials=tuple(t for t, k in zip(self.trials, keep, strict=True) if k),
                       measured=None if self.measured is None else self.measured[keep], weights=self.weights[keep])

    # ------------------------------------------------------------------ layout
    @property
    def n_trials(self) -> int:
        return len(self.trials)

    @property
    def n_free(self) -> int:
        return len(self.free)

    @property
    def parameters(self) -> list[Parameter]:
        """Metadata of the free parameters."""
        return [self.model.parameter(n) for n in self.free]

    @property
    def scales(self) -> np.ndarray:
        """Each free parameter's scale (SI): the encoding divides by it (order one)."""
        return np.array([p.scale for p in self.parameters])

    def bounds_of(self, name: str) -> tuple[float, float]:
        """(lower, upper) of a free parameter (SI): the problem's, else its declared ones."""
        return self.bounds.get(name) or self.model.parameter(name).bounds

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds (SI); a log-normal prior's floor where it is higher (:meth:`Prior.floor`)."""
        return np.array([max(self.bounds_of(n)[0], self.priors[n].floor()) if n in self.priors
                         else self.bounds_of(n)[0] for n in self.free])

    @property
    def upper(self) -> np.ndarray:
        return np.array([self.bounds_of(n)[1] for n in self.free])

    @property
    def equilibrium_tol(self) -> float:
        """The largest equilibrium residual (N or N m) of a pose counted as an equilibrium."""
        return EQUILIBRIUM_TOL

    @property
    def pose_bounds_user(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds (5, mm and deg) of every trial's pose: the physiological envelope
        (:data:`~kneenlp.base.conventions.POSE_ENVELOPE_USER`) about the knee's reference pose."""
        return pose_envelope_user(self.model.knee.reference_pose[1])

    def inside_pose_bounds(self, q: np.ndarray, margin: float = 0.99) -> np.ndarray:
        """Per trial: are the poses ``q`` (T x 5, SI) inside ``margin`` of the pose bounds?"""
        lo, hi = self.pose_bounds_user
        return np.all(np.abs(coords_to_user(q) - (lo + hi) / 2) < margin * (hi - lo) / 2, axis=1)

    # ------------------------------------------------------------------ the free-vector encoding
    def to_scaled(self, values: Mapping[str, float] | Sequence[float] | np.ndarray) -> np.ndarray:
        """The free parameters (SI, by name or in order) divided by their scales (:attr:`space`'s)."""
        return self.space.to_scaled(values)

    def from_scaled(self, x_scaled: np.ndarray) -> np.ndarray:
        """The free parameters (SI, in order) of scaled values (one point, or one per row)."""
        return self.space.from_scaled(x_scaled)

    @property
    def scaled_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the scaled free parameters."""
        return self.space.scaled_bounds

    def to_x(self, values: Mapping[str, float] | Sequence[float] | np.ndarray, q_user: np.ndarray) -> np.ndarray:
        """The NLP's decision vector: the scaled free parameters (``values`` SI), then every
        trial's pose (``q_user``, T x 5, mm and deg)."""
        return np.concatenate([self.to_scaled(values), np.asarray(q_user, dtype=float).ravel()])

    def from_x(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free parameter values in SI, poses T x 5 in mm and deg) of a decision vector."""
        x = np.asarray(x, dtype=float).ravel()
        return self.from_scaled(x[:self.n_free]), x[self.n_free:].reshape(self.n_trials, 5)

    def x_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the decision vector: the parameters' bounds (scaled), then
        the pose envelope of every trial (mm and deg)."""
        (lo_p, hi_p), (lo_q, hi_q) = self.scaled_bounds, self.pose_bounds_user
        return (np.concatenate([lo_p, np.tile(lo_q, self.n_trials)]),
                np.concatenate([hi_p, np.tile(hi_q, self.n_trials)]))

    def theta_of_scaled(self, x_scaled: ca.MX | ca.SX, theta: ca.MX | ca.SX) -> ca.MX | ca.SX:
        """The full parameter vector (SI, symbolic) of the scaled free parameters, the ties
        evaluated (:meth:`~kneenlp.model.space.ParameterSpace.theta_of_scaled`)."""
        return self.space.theta_of_scaled(x_scaled, theta)

    @property
    def loads(self) -> np.ndarray:
        return np.array([t.load for t in self.trials]).reshape(-1, LOAD_SIZE)

    @property
    def flexions(self) -> np.ndarray:
        return np.array([t.flexion for t in self.trials])

    @property
    def data(self) -> MeasuredData:
        """The measurements as :class:`MeasuredData` (SI poses)."""
        if self.measured is None:
            raise InputError("this problem has no measurements (a design problem)")
        return MeasuredData.from_user(list(self.trials), self.measured, self.protocol, self.source,
                                      experiment=self.experiment)

    def theta(self, values: Mapping[str, float] | Sequence[float] | np.ndarray | None = None) -> np.ndarray:
        """Full parameter vector (SI): fixed values, then the free ``values`` (dict or in order)."""
        if values is not None and not isinstance(values, Mapping):
            values = dict(zip(self.free, np.asarray(values, dtype=float).ravel(), strict=True))
        return self.space.tied(self.model.theta({**self.fixed, **(values or {})}))

    def values(self, theta: np.ndarray) -> dict[str, float]:
        """The free parameters' values (SI) in a full parameter vector."""
        return {n: float(theta[self.model.index(n)]) for n in self.free}

    # ------------------------------------------------------------------ the priors
    @property
    def prior_logs(self) -> tuple[bool, ...]:
        """Per free parameter: is its prior log-normal (its term is built on ``ln value``)?"""
        return tuple(n in self.priors and self.priors[n].log for n in self.free)

    def prior_data(self) -> tuple[np.ndarray, np.ndarray]:
        """(centres, inverse widths) per free parameter, the latter times ``sqrt(prior_weight)``
        (0 for a parameter without a prior): the data of :func:`prior_rows`."""
        centre = np.array([self.priors[n].centre if n in self.priors else 0.0 for n in self.free])
        inv_sd = np.array([np.sqrt(self.prior_weight) / self.priors[n].sd if n in self.priors else 0.0
                           for n in self.free])
        return centre, inv_sd

    def prior_residuals(self, values: Mapping[str, float] | Sequence[float] | np.ndarray) -> np.ndarray:
        """``sqrt(prior_weight) z`` per free parameter (0 without a prior) at ``values`` (SI)."""
        if isinstance(values, Mapping):
            values = [values[n] for n in self.free]
        return np.asarray(prior_rows(np.asarray(values, float), *self.prior_data(), self.prior_logs), float).ravel()

    def prior_jacobian(self, values: Mapping[str, float]) -> np.ndarray:
        """``d prior_residuals / d p`` (n_free x n_free, diagonal; per SI unit) at ``values`` (SI)."""
        v = np.array([values[n] for n in self.free], float)
        _, inv_sd = self.prior_data()
        return np.diag(inv_sd * np.where(self.prior_logs, 1.0 / np.where(self.prior_logs, v, 1.0), 1.0))

    def prior_objective(self, theta: np.ndarray) -> float:
        """The priors' share of the MAP objective, ``prior_weight * sum z^2``, at ``theta`` (SI)."""
        if not self.priors:
            return 0.0
        r = self.prior_residuals(self.values(theta))
        return float(r @ r)

    def map_objective(self, q: np.ndarray, theta: np.ndarray) -> float:
        """What a fit minimises: :meth:`objective` plus :meth:`prior_objective`."""
        return self.objective(q, theta) + self.prior_objective(theta)

    def layout(self, working_sets: bool = False) -> DataLayout:
        """The data vector's layout; ``working_sets``: with the contact working sets as data."""
        return DataLayout(len(self.model.parameter_names), self.n_trials,
                          self.model.ws_size if working_sets else 0, self.n_free)

    def data_vector(self, ws: np.ndarray | None = None) -> np.ndarray:
        """The NLP's parameter vector (:class:`DataLayout`): the full parameter vector (fixed
        values, SI) and the trials' data; for a program with its working sets as data (export),
        ``ws`` (T x ws_size, from :meth:`working_sets`).  Refitting other data never rebuilds the NLP."""
        meas = np.zeros((self.n_trials, 5)) if self.measured is None else np.where(self.observed, self.measured, 0.0)
        layout = self.layout(working_sets=ws is not None and np.size(ws) > 0)
        centre, inv_sd = self.prior_data()
        return layout.pack({"theta": self.theta(), "prior_centre": centre, "prior_inv_sd": inv_sd, "measured": meas,
                            "weights": self.weights, "loads": self.loads, "flexions": self.flexions,
                            "working_sets": None if ws is None or not np.size(ws) else ws})

    def working_sets(self, q: np.ndarray, theta: np.ndarray) -> tuple[list[list[np.ndarray]], np.ndarray]:
        """Each trial's contact working sets at poses ``q`` (T x 5, SI): indices and the packed
        inputs (T x ws_size)."""
        out = [self.model.working_set(qi, theta, t.flexion) for t, qi in zip(self.trials, q, strict=True)]
        return [o[0] for o in out], np.array([o[1] for o in out]).reshape(self.n_trials, self.model.ws_size)

    # ------------------------------------------------------------------ the one comparison
    def observe(self, q: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Predicted measurements (T x 5, mm and deg) of poses ``q`` (T x 5, SI)."""
        return self.model.observe(q, theta, self.loads, self.flexions)

    def residuals(self, q: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Model minus measured coordinates (T x 5, mm and deg)."""
        if self.measured is None:
            raise InputError("this problem has no measurements (a design problem)")
        return self.observe(q, theta) - self.measured

    def observed_residuals(self, q: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """:meth:`residuals` with 0 where the experiment observes nothing (they weigh zero)."""
        return np.where(self.observed, self.residuals(q, theta), 0.0)

    def objective(self, q: np.ndarray, theta: np.ndarray) -> float:
        """Weighted sum of squared residuals (mm^2 + deg^2 times the weights): the paper's Psi'Psi."""
        r, seen = self.residuals(q, theta), self.observed
        return float(np.sum(self.weights * np.where(seen, r, 0.0)**2)) if np.all(np.isfinite(r[seen])) else np.inf

    def sensitivities(self, q: np.ndarray, theta: np.ndarray, names: Sequence[str] | None = None,
                      with_poses: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """``d y / d p`` (5T x n; mm or deg per SI unit of each parameter ``names``, default the free
        ones) at equilibrium poses ``q`` (T x 5, SI): the implicit-function theorem through every
        trial's equilibrium, ``dq/dp = -(dr/dq)^-1 dr/dp``, then the observation's chain rule.
        ``with_poses``: ``dq/dp`` (T x 5 x n, SI) too (a first-order prediction of the poses)."""
        model = self.model
        idx = [model.index(n) for n in (self.free if names is None else names)]
        q = np.asarray(q, dtype=float).reshape(-1, 5)
        T = len(q)
        dq, dth = model.trial_derivatives(q, theta, Loading.of(self.trials), wrt_theta=True)
        dy_dq, dy_dth = (np.asarray(v).reshape(5, T, -1).transpose(1, 0, 2)
                         for v in model.observation_jacobians.map(T)(q.T, theta, self.loads.T,
                                                                            self.flexions[None, :]))
        dr_dp, dy_dp_direct = dth[:, :, idx], dy_dth[:, :, idx]
        if names is None and self.ties:  # through the ties: d theta / d p is not a selection
            J = self.space.jacobian(theta)
            dr_dp, dy_dp_direct = dth @ J, dy_dth @ J
        try:
            dq_dp = -np.linalg.solve(dq, dr_dp)
        except np.linalg.LinAlgError:  # a singular equilibrium (e.g. a failed solve): least squares there
            dq_dp = -np.stack([np.linalg.pinv(a) @ b for a, b in zip(dq, dr_dp, strict=True)])
        dy_dp = (dy_dq @ dq_dp + dy_dp_direct).reshape(5 * T, len(idx))
        return (dy_dp, dq_dp) if with_poses else dy_dp

    # ------------------------------------------------------------------ starts
    def scatter(self, rng: np.random.Generator, reference: Mapping[str, float] | None = None, *,
                spread_effects: bool = False) -> dict[str, float]:
        """A start like the paper's: uniform scatter around ``reference`` (default: the fixed
        values and the knee's parameter set) with each parameter's scatter width (SI).  Candidate
        parameters start at their neutral value, or scattered from it (towards the inside of a
        one-sided bound) with ``spread_effects`` (the nested Complex needs a spread population)."""
        ref = reference or self.values(self.theta())
        out = {}
        for p in self.parameters:
            if p.neutral is not None and not spread_effects:
                out[p.name] = p.neutral
                continue
            out[p.name] = p.scatter(p.neutral if p.neutral is not None else ref[p.name], rng)
        return out

    def check_start(self, start: Mapping[str, float] | None) -> dict[str, float]:
        for n in start or {}:
            if n not in self.free:
                raise unknown_name("free parameter", n, self.free)
        return dict(start or {})
