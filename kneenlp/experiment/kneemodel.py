"""The CasADi model of a knee: the sum of its force elements, ONE equilibrium residual function.

``KneeModel(knee).residual`` is the function ``(q, theta, load, flexion, ws) -> r``:

* ``q`` (5): free coordinates ``[varus, internal, lateral, anterior, proximal]`` (rad, m),
* ``theta`` (n): all model parameters in :attr:`KneeModel.parameter_names` order (SI),
* ``load`` (:data:`~kneenlp.base.conventions.LOAD_SIZE`, :func:`~kneenlp.base.conventions.load_vector`):
  a force and a pure moment (femoral frame, N, N m), generalised forces added to ``r`` as they are
  (a robot's joint loads) and the force's tibial point (the experiment's, or the tuberosity),
* ``flexion`` (1): prescribed flexion (rad),
* ``ws``: the contact working sets of the trial *taken at the pose q* (:meth:`KneeModel.working_set`:
  the points that can touch and, for mesh contact, the expansion of the contact at q; empty when no
  contact element uses working sets): every solver evaluates the residual with the working sets of
  the pose it evaluates (:mod:`kneenlp.model.workingsets`),
* ``r`` (5): generalised forces of all elements + load for the five free coordinates (N m for the
  rotations, N for the translations); equilibrium is ``r = 0``.  The flexion moment is reacted.

``KneeModel.observation`` is THE map from a pose to what is measured, ``(q, theta, load, flexion) -> y``
with ``y`` the five coordinates in mm and deg plus the experiment's measurement bias (which may
depend on the prescribed flexion: :class:`~kneenlp.experiment.parts.FemoralOrigin`).

A ``KneeModel`` is the knee (:class:`~kneenlp.model.knee.Knee`: its force elements) in an
experiment (:class:`~kneenlp.experiment.parts.Measurement`: the flexion the experiment
prescribes, its frames, its registration, where it applies its load): the residual adds the knee's
forces and the load where the experiment applies it; the observation reads the pose as the
experiment reads it.

The forward Newton solver, the simultaneous NLP, the nested objective, sensitivities and export all
call these functions.  They are built once per model with the parameters as symbols, so changing
a parameter value never rebuilds them.  Structure (for the speed of derivatives): an SX function
gives every staged element's probe, the staged elements' MX surface functions give their
wrenches, and an SX balance function adds every other element and the load and projects all onto
the generalised coordinates (see :mod:`kneenlp.model.elements`).
"""

from __future__ import annotations

import dataclasses
from functools import cached_property
from typing import Literal

import casadi as ca
import numpy as np

from kneenlp.base.compiled import BufferedCall, compiled
from kneenlp.base.conventions import LOAD_SIZE
from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.modes import PriorChoice
from kneenlp.experiment.contact_sets import ContactSets
from kneenlp.experiment.functions import OBSERVATION_INPUTS, ModelFunctions
from kneenlp.experiment.parts import ExperimentPart, Measurement, registration_effects
from kneenlp.experiment.protocol import Loading
from kneenlp.model import ties as tie_rules
from kneenlp.model.effects import (
    Effect,
    attachment_effects,
    builtin_groups,
    bundle_group_effects,
)
from kneenlp.model.elements import ForceElement, Output, Part
from kneenlp.model.kinematics import joint_coordinates
from kneenlp.model.knee import Knee
from kneenlp.model.parameters import Parameter, ParameterSet, with_unit
from kneenlp.model.params import Parameters, make_params
from kneenlp.model.solvercache import SolverCache


def check_set_names(params, info: dict[str, Parameter]) -> None:
    """Every value of the knee's parameter set names a parameter of the model, in a unit of its kind."""
    src = params.source or params.name
    for name in dict.fromkeys([*params.names(), *params.priors, *params.bounds, *params.free]):
        if name not in info:
            raise unknown_name("parameter", name, list(info), source=src).with_context(field=name)
        fld = f"{params.table}.{name}"
        if name in params.values:  # every way of giving a value passes here: file, --parameters, calibration
            lo, hi = info[name].bounds
            if not lo <= params.values[name] <= hi:
                f, unit = info[name].to_user, info[name].unit
                where = "its bounds" if name in params.bounds else f"the range of a {info[name].meta.text}"
                raise InputError(f"value {with_unit(params.values[name] * f, unit)} outside {where} "
                                 f"[{lo * f:g}, {hi * f:g}]" + ("" if unit == "1" else f" {unit}"), source=src,
                                 field=fld + (".bounds" if name in params.bounds else ""))
        unit = params.meta.get(name)
        if unit is not None and unit not in dict(info[name].meta.file_units):
            raise InputError(f"unit {unit!r} does not suit {name} ({info[name].meta.text}); use one of "
                             f"{', '.join(dict(info[name].meta.file_units))}", source=src, field=fld)
        if name in params.priors:
            info[name].check_prior(params.priors[name], src, f"{fld}.prior")
    tie_rules.ordered(params.ties, info, source=src)


def check_sign(info: Parameter, lower: float, source: str | None, table: str) -> None:
    """Declared bounds may move a parameter's range, not past a sign it cannot change: a lower bound
    below 0 for a quantity that is never negative (a stiffness, a scale), or at 0 for one that is
    always positive (a linear strain limit, a modulus)."""
    own = info.bounds[0]
    if (own >= 0 and lower < 0) or (own > 0 and lower <= 0):
        f, unit = info.to_user, info.unit
        raise InputError(f"lower bound {with_unit(lower * f, unit)} lets {info.name} be "
                         f"{'negative' if lower < 0 else 'zero'}, which a {info.meta.text} cannot be (its range "
                         f"starts at {with_unit(own * f, unit)})", source=source, field=f"{table}.{info.name}.bounds")


#: How far (in units of a parameter's scale) a value given to the model may lie beyond its bounds:
#: the bound tolerance of the solvers that produce values (IPOPT relaxes bounds by 1e-8 relative).
BOUND_SLACK = 1e-6


def _called(items: list, name: str, what: str):
    """The item of ``items`` whose ``name`` is ``name``; else the one-line error naming the known ones."""
    found = next((e for e in items if e.name == name), None)
    if found is None:
        raise unknown_name(what, name, [e.name for e in items])
    return found


class KneeModel(ModelFunctions, ContactSets):
    """Symbolic equilibrium model of a :class:`~kneenlp.model.knee.Knee` (built once, reused).

    ``extra_elements`` adds user parts (e.g. a candidate effect, see ``docs/architecture.md``): force
    elements join the knee's own and the built-in candidate elements, experiment parts
    (:class:`~kneenlp.experiment.parts.ExperimentPart`) join ``measurement`` (default: the
    standard parts, :meth:`Measurement.standard`, every one neutral until fitted).
    """

    def __init__(self, knee: Knee, extra_elements: list[Part] | None = None,
                 measurement: Measurement | None = None):
        self.knee = knee
        extra = list(extra_elements or [])
        #: the arguments that build this model again (in another process: a Dask worker)
        self.arguments = (knee, extra, measurement)
        wrong = [e for e in extra if not isinstance(e, ForceElement | ExperimentPart)]
        if wrong:
            raise InputError(f"{type(wrong[0]).__name__} is neither a ForceElement nor an ExperimentPart",
                             field="elements")
        own = [*knee.elements(), *knee.structure_candidates()]
        experiment = measurement or Measurement.standard()
        #: the knee's force elements (its own, the built-in candidates, the user's)
        self.elements: list[ForceElement] = [*own, *[e for e in extra if isinstance(e, ForceElement)]]
        #: how the experiment measured the knee (its frames, registration, flexion, load point)
        self.measurement = experiment.with_parts([e for e in extra if isinstance(e, ExperimentPart)])
        #: every part with parameters, in the parameter vector's order
        self.parts: list[Part] = [*own, *experiment.parts, *extra]
        names = [e.name for e in self.parts]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"two parts of the model are called {dup[0]!r}", field="elements")
        self.ligament_names = list(knee.ligaments)
        self.compartment_names = list(knee.compartments)
        params: dict[str, Parameter] = {}
        for e in self.parts:
            for p in e.parameters():
                if p.name in params and params[p.name] != p:
                    raise InputError(f"parameter {p.name!r} declared twice with different metadata",
                                     field=e.name)
                params.setdefault(p.name, p)
        for name, (lo, hi) in knee.parameters.bounds.items():  # the parameter file's bounds replace the kind's
            if name in params:
                check_sign(params[name], lo, knee.parameters.source or knee.parameters.name, knee.parameters.table)
                params[name] = dataclasses.replace(params[name], lower=lo, upper=hi)
        self.parameters: list[Parameter] = list(params.values())
        check_set_names(knee.parameters, params)
        self.parameter_names = [p.name for p in self.parameters]
        self._index = {n: i for i, n in enumerate(self.parameter_names)}
        self.effects: list[Effect] = [Effect(e.name, e.description, tuple(e.frees()))
                                      for e in self.parts if e.candidate]
        if any(e.name == "registration" for e in self.effects):
            self.effects += registration_effects()
        self.effects += builtin_groups([n for n in self.ligament_names if not knee.ligaments[n].grouped])
        self.effects += bundle_group_effects([n for n in self.ligament_names if knee.ligaments[n].grouped])
        self.effects += attachment_effects(self.ligament_names)
        #: solvers built for this model (forward rootfinders, identification NLPs, working sets), each
        #: built once and keyed by what changes it (:class:`~kneenlp.model.solvercache.SolverCache`)
        self.solvers = SolverCache()
        self._build()

    @classmethod
    def of(cls, knee: Knee | KneeModel) -> KneeModel:
        """``knee``'s model in the standard experiment, built anew; a :class:`KneeModel` (e.g. one
        built with extra user parts) is returned as it is.  The model keeps the solvers built for
        it (:attr:`solvers`): pass the model, not the knee, to reuse them."""
        return knee if isinstance(knee, KneeModel) else cls(knee)

    def trial_derivatives(self, q: np.ndarray, theta: np.ndarray, loading: Loading, threads: int = 2,
                          wrt_theta: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The residuals (T x 5) and dr/dq (T x 5 x 5), or with ``wrt_theta`` dr/dq and dr/dtheta (T x 5 x
        n_theta), at the poses ``q`` (T x 5, SI) under ``loading`` (loads and flexions of T trials), each
        with the working sets of its own pose (order 1, :meth:`working_data_batch`): what Newton's
        iteration and the implicit-function sensitivities evaluate.  One buffered call
        (:class:`~kneenlp.base.compiled.BufferedCall`) of :attr:`jacobians` (or its ``(r, dr/dq)`` twin)
        mapped over the trials, built once per size: on ``threads`` threads, serially where the function
        is compiled (:func:`~kneenlp.base.compiled.compiled`: a trial takes it microseconds, and two
        threads did not pay up to 64 trials; S192803, 2 cores)."""
        q = np.ascontiguousarray(q, dtype=float).reshape(-1, 5)
        n, threads = len(q), min(threads, len(q))
        ws = self.working_data_batch(q, theta, loading.flexions, threads, order=1)

        def build() -> BufferedCall:
            one = self.jacobians if wrt_theta else self._residual_and_jacobian
            vm = one.is_a("SXFunction") or one.is_a("MXFunction")
            return BufferedCall(one.map(n, "thread", threads) if threads > 1 and vm else one.map(n))

        first, second = self.solvers.get(("trial_derivatives", n, threads, wrt_theta), build)(
            q, np.tile(theta, n), loading.loads, loading.flexions, ws)  # column-major: trial by trial
        width = len(self.parameter_names) if wrt_theta else 5
        first = first.reshape(n, 5, 5).transpose(0, 2, 1) if wrt_theta else first.reshape(n, 5)
        return first, second.reshape(n, width, 5).transpose(0, 2, 1)

    def evaluate(self, q: np.ndarray, theta: np.ndarray, load: np.ndarray, flexion: float) -> np.ndarray:
        """The equilibrium residual (5) at a pose with the working sets of that pose (numeric)."""
        return np.asarray(self.residual(q, theta, load, flexion, self.working_data(q, theta, flexion, order=0))).ravel()

    # ------------------------------------------------------------------ helpers
    @property
    def outputs(self) -> list[tuple[ForceElement, Output]]:
        """Every element's outputs, in the order of the ``details`` function's ``outputs``."""
        return [(e, o) for e in self.elements for o in e.outputs()]

    def parameter(self, name: str) -> Parameter:
        """Metadata of parameter ``name``."""
        return self.parameters[self.index(name)]

    def theta(self, values: dict[str, float] | None = None) -> np.ndarray:
        """Full parameter vector (SI): the knee's parameter set, candidate parameters at neutral,
        other defaults of the elements, ``values`` (by name) overriding."""
        return self._theta_of(self.knee.parameters, values)

    def reference_coordinates(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """The knee's imaged pose (``[reference_pose]``) as the model's coordinates at ``theta``:
        flexion (rad) and the five free coordinates (rad, m) of the experiment's tibial axes, the
        knee's own unless the experiment turns them (:class:`~kneenlp.experiment.parts.TibialAxes`)."""
        flexion, q = self.knee.reference_pose
        turn = np.asarray(self.turn(theta), float)
        if np.array_equal(turn, np.eye(3)):
            return flexion, np.asarray(q, float)
        R, p = self.knee.reference_transform
        return joint_coordinates(R @ turn, p)

    def _theta_of(self, params: ParameterSet, values: dict[str, float] | None = None) -> np.ndarray:
        values = dict(values or {})
        for n, v in values.items():  # the API's values pass the range check a file's values pass (a
            # solver's own bound tolerance, IPOPT's relaxation of 1e-8, stays inside BOUND_SLACK)
            lo, hi = self.parameter(n).bounds
            slack = BOUND_SLACK * self.parameter(n).scale
            if not lo - slack <= v <= hi + slack:
                p = self.parameter(n)
                raise InputError(f"{n} = {v * p.to_user:g} {p.unit} outside the range of a {p.meta.text} "
                                 f"[{lo * p.to_user:g}, {hi * p.to_user:g}] {p.unit}", field=n)
        out = []
        for p in self.parameters:
            if p.name in values:
                out.append(float(values[p.name]))
            elif p.name in params:  # a calibration may set a candidate (e.g. the registration)
                out.append(params[p.name])
            elif p.neutral is not None:
                out.append(p.neutral)
            elif p.default is not None:
                out.append(p.default)
            else:
                raise InputError(f"parameter set {params.name} lacks {p.name}", source=params.source,
                                 field=p.name)
        if params.ties:  # the parameter file's ties (kneenlp.model.ties)
            tied = tie_rules.tied(dict(zip(self.parameter_names, out, strict=True)), params.ties)
            out = [tied[n] for n in self.parameter_names]
        return np.array(out, dtype=float)

    def make_params(self, priors: PriorChoice | Literal["declared"] = "declared") -> Parameters:
        """Every parameter of the model as one :class:`~kneenlp.model.params.Parameters`
        (:func:`~kneenlp.model.params.make_params`)."""
        return make_params(self, priors)

    def observe(self, q: np.ndarray, theta: np.ndarray, loads: np.ndarray, flexions) -> np.ndarray:
        """Measured coordinates (T x 5, mm and deg) of poses ``q`` (T x 5, SI) under their trials'
        ``loads`` (T x ``LOAD_SIZE``) at their prescribed ``flexions`` (T, rad) and ``theta``."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        flexions = np.broadcast_to(np.asarray(flexions, float), (len(q),))
        loads = np.broadcast_to(np.asarray(loads, float).reshape(-1, LOAD_SIZE), (len(q), LOAD_SIZE))
        return np.asarray(self.observation.map(len(q))(q.T, theta, loads.T, flexions[None, :])).T

    def bias_user(self, theta: np.ndarray, flexion: float = 0.0) -> np.ndarray:
        """Measurement bias (mm, deg) that the experiment adds to the model's coordinates at the
        neutral pose and ``flexion`` (rad) without a load."""
        return self.observe(np.zeros(5), theta, np.zeros(LOAD_SIZE), flexion)[0]

    def effect(self, name: str) -> Effect:
        """The candidate effect called ``name``."""
        return _called(self.effects, name, "effect")

    def element(self, name: str) -> Part:
        """The part (force element or experiment part) called ``name``."""
        return _called(self.parts, name, "force element or experiment part")

    def index(self, name: str) -> int:
        """Position of parameter ``name`` in ``theta``."""
        try:
            return self._index[name]
        except KeyError:
            raise unknown_name("parameter", name, self.parameter_names) from None

    @cached_property
    def jacobians(self) -> ca.Function:
        """``(q, theta, load, flexion, ws) -> (dr/dq, dr/dtheta)`` with the working sets ``ws`` of
        the pose ``q`` (:meth:`working_set`): the implicit-function sensitivities of one trial
        (:meth:`pose_derivatives` maps it)."""
        return self._trial_derivatives("jac_q_theta", wrt_theta=True)

    @cached_property
    def _residual_and_jacobian(self) -> ca.Function:
        """``(q, theta, load, flexion, ws) -> (r, dr/dq)`` of one trial: Newton's (:meth:`pose_derivatives`)."""
        return self._trial_derivatives("residual_and_jacobian", wrt_theta=False)

    def _trial_derivatives(self, name: str, wrt_theta: bool) -> ca.Function:
        """One trial's ``(dr/dq, dr/dtheta)`` or ``(r, dr/dq)``: SX where contact uses working sets
        (a few operations on their data: ~1.5x faster than MX), MX without them (contact over every
        surface point as constants: expanded, 474k operations a trial on the synthetic knee, 5x slower);
        an SX one compiled to C where the machine allows (:func:`~kneenlp.base.compiled.compiled`)."""
        sym = ca.SX.sym if self.ws_size else ca.MX.sym
        residual = self.residual.expand() if self.ws_size else self.residual
        q, theta = sym("q", 5), sym("theta", len(self.parameter_names))
        load, flexion, ws = sym("load", LOAD_SIZE), sym("flexion"), sym("ws", self.ws_size)
        r = residual(q, theta, load, flexion, ws)
        outs = [ca.densify(v) for v in ([ca.jacobian(r, q), ca.jacobian(r, theta)] if wrt_theta else
                                        [r, ca.jacobian(r, q)])]
        return compiled(ca.Function(name, [q, theta, load, flexion, ws], outs, ["q", "theta", "load", "flexion", "ws"],
                                    ["jac_r_q", "jac_r_theta"] if wrt_theta else ["r", "jac_r_q"]))

    @cached_property
    def observation_jacobians(self) -> ca.Function:
        """``(q, theta, load, flexion) -> (dy/dq, dy/dtheta)`` of :attr:`observation`."""
        return self.observation.factory("observation_jac", OBSERVATION_INPUTS, ["jac:y:q", "jac:y:theta"])
