"""How a :class:`~kneenlp.experiment.kneemodel.KneeModel` builds its CasADi functions (a part of it).

:class:`ModelFunctions` builds, once per model and with the parameters as symbols: the SX probes
of the staged elements, the SX balance of every force and the load projected on the generalised
coordinates, the observation, the pose, and from them the MX residual and details that take each
staged element's surface function with its slice of the working sets (module docstring of
:mod:`kneenlp.experiment.kneemodel`).

Pose data (:class:`~kneenlp.model.elements.PoseData`): numbers a plain element's expression needs
that are computed outside CasADi at each pose (a ligament path's taut string over a bone,
:mod:`kneenlp.geometry.taut_path`).  They are the working sets' last part, so every solver takes
them at each pose it evaluates, as it takes contact's, with the same zero derivative: the element's
expression of them carries the exact derivatives.
"""

from __future__ import annotations

from functools import cached_property

import casadi as ca
import numpy as np

from kneenlp.base.conventions import HELD, HELD_AT, LOAD_SIZE, LOADED, PRELOAD, PRELOAD_AT, coords_to_user
from kneenlp.base.errors import InputError
from kneenlp.base.modes import Layout
from kneenlp.model.elements import Pose, PoseData, StagedElement
from kneenlp.model.kinematics import generalized_forces, tibial_pose

#: The held coordinates' equations ``HOLD_SCALE (q - value)``: a knee's stiffness in each coordinate
#: (N m/rad, N/m), so that Newton's Jacobian keeps its scale.
HOLD_SCALE = (100.0, 100.0, 1e5, 1e5, 1e5)


def preload_wrench(load: ca.SX, R: ca.SX, tuberosity: np.ndarray) -> tuple[ca.SX, ca.SX]:
    """The force and moment about the tibial origin (femoral frame) of a compressive preload acting
    at a point of its own (:func:`~kneenlp.base.conventions.load_vector`; zero for most experiments)."""
    at = ca.DM(tuberosity) * load[PRELOAD_AT][3] + load[PRELOAD_AT][:3]
    return load[PRELOAD], ca.cross(R @ at, load[PRELOAD])


def held_residual(residual: ca.SX, q: ca.SX, load: ca.SX) -> ca.SX:
    """The residual with the held coordinates prescribed: a held coordinate's equation is its value,
    ``HOLD_SCALE (q - value)`` (the apparatus carries its generalised force); exact, the mask being
    0 or 1."""
    held = load[HELD]
    return (1 - held) * residual + held * ca.DM(HOLD_SCALE) * (q - load[HELD_AT])


#: The observation function's inputs (:attr:`KneeModel.observation`).
OBSERVATION_INPUTS = ["q", "theta", "load", "flexion"]



class ModelFunctions:
    """The building of a model's CasADi functions (module docstring), a part of
    :class:`~kneenlp.experiment.kneemodel.KneeModel` (whose ``elements``, ``measurement``, ``knee``
    and ``parameter_names`` it uses)."""

    # ------------------------------------------------------------------ construction
    def _build(self) -> None:
        """The model's CasADi functions (module docstring): SX probes, balance and observation,
        then the MX residual and details through the staged elements' surfaces."""
        probes, balance, probe_sizes = self._build_balance()
        self._build_residual(probes, balance, probe_sizes)

    def _build_balance(self) -> tuple[ca.Function, ca.Function, list[int]]:
        """The SX functions: the staged elements' probes ``(q, flexion, theta)``, the balance of
        every force and the load ``(q, flexion, theta, load, pose data, staged forces, staged
        moments) -> (r, plain outputs)``, and :attr:`observation`, :attr:`pose`, :attr:`turn`."""
        q = ca.SX.sym("q", 5)
        flexion = ca.SX.sym("flexion")
        theta = ca.SX.sym("theta", len(self.parameter_names))
        load = ca.SX.sym("load", LOAD_SIZE)
        values = {n: theta[i] for i, n in enumerate(self.parameter_names)}
        flex_e = self.measurement.flexion(flexion, values)
        # q and the flexion are the experiment's Grood-Suntay coordinates; the experiment may turn
        # its tibial axes from the model's (TibialAxes): the tibia's own frame is then R C^T
        R_exp, p, axes = tibial_pose(flex_e, q)
        turn = self.measurement.turn(values)
        R = R_exp if turn is None else R_exp @ turn.T
        self.turn = ca.Function("tibial_axes", [theta], [ca.SX.eye(3) if turn is None else turn])
        staged = [e for e in self.elements if isinstance(e, StagedElement)]
        plain = [e for e in self.elements if not isinstance(e, StagedElement)]
        #: what the plain elements need computed outside CasADi at each pose (a path over a bone)
        self.pose_data: list[PoseData] = [d for e in plain for d in e.pose_data()]
        data = {d.key: ca.SX.sym(d.key, d.size) for d in self.pose_data}
        pose = Pose(R, p, q, flex_e, data)
        data = ca.vertcat(*data.values()) if data else ca.SX(0, 1)
        probes = [e.probe(pose, values) for e in staged]
        kin = ca.Function("probes", [q, flexion, theta], probes)
        stage_f = [ca.SX.sym(f"{e.name}_force", 3) for e in staged]
        stage_m = [ca.SX.sym(f"{e.name}_moment", 3) for e in staged]
        # staged wrenches arrive in the element's frame: tibial ones are rotated into the femoral
        force = sum((R @ f if e.wrench_frame == "tibial" else f for e, f in zip(staged, stage_f, strict=True)),
                    ca.SX.zeros(3))
        moment = sum((R @ m if e.wrench_frame == "tibial" else m for e, m in zip(staged, stage_m, strict=True)),
                     ca.SX.zeros(3))
        for e in plain:
            f_e, m_e = e.wrench(pose, values)
            force += f_e
            moment += m_e
        # the force acts at the trial's point (the tuberosity by default), shifted by LoadPoint; with the tibial
        # origin elsewhere (TibialOrigin) the joint loads' force (on e1, e2, e3) adds the shift's couple
        shift = self.measurement.load_point_shift(values)
        origin = self.measurement.joint_origin_shift(values)
        e1, e2, e3 = axes
        joint_force = ca.solve(ca.horzcat(e1, e2, e3).T, load[8:11])
        force += load[0:3]
        at = ca.DM(self.knee.tuberosity) * load[14] + load[11:14]  # the trial's point, or the tuberosity
        moment += ca.cross(R @ (at + shift), load[0:3]) + load[3:6]
        moment += ca.cross(R_exp @ (shift + origin), joint_force)  # the experiment's tibial axes
        f_pre, m_pre = preload_wrench(load, R, self.knee.tuberosity)
        residual = held_residual(generalized_forces(q, p, axes, force + f_pre, moment + m_pre) + load[6:11], q, load)
        plain_out = ca.vertcat(*[v for e in plain for v in e.output_values(pose, values)])
        balance = ca.Function("balance", [q, flexion, theta, load, data, *stage_f, *stage_m],
                              [residual, plain_out])

        bias = self.measurement.bias(pose, values, load[LOADED])
        y = coords_to_user(q) + (coords_to_user(bias) if bias is not None else 0)
        self.observation = ca.Function("observation", [q, theta, load, flexion], [y], OBSERVATION_INPUTS, ["y"])

        self.pose = ca.Function("pose", [q, flexion, theta], [R, p], ["q", "flexion", "theta"], ["R", "p"])
        self.staged = staged
        self._probes, self._balance = kin, balance
        return kin, balance, [pr.numel() for pr in probes]

    def _build_residual(self, kin: ca.Function, balance: ca.Function, probe_sizes: list[int]) -> None:
        """:attr:`residual` and :attr:`details` (MX): the probes through each staged element's
        surface function, with its slice of the working sets, into the balance; the pose data
        (:attr:`pose_data`) are the working sets' last part (:attr:`data_slice`)."""
        staged = self.staged
        sizes = [e.ws_width * e.n_working for e in staged]
        self.ws_slices = [slice(a, a + s) for a, s in zip(np.cumsum([0, *sizes[:-1]]), sizes, strict=True)]
        n_data = sum(d.size for d in self.pose_data)
        self.data_slice = slice(int(sum(sizes)), int(sum(sizes)) + n_data)
        self.ws_size = int(sum(sizes)) + n_data
        qm, flexm = ca.MX.sym("q", 5), ca.MX.sym("flexion")
        thetam, loadm = ca.MX.sym("theta", len(self.parameter_names)), ca.MX.sym("load", LOAD_SIZE)
        wsm = ca.MX.sym("ws", self.ws_size)
        pr = kin(qm, flexm, thetam) if staged else []
        pr = [pr] if isinstance(pr, ca.MX) else list(pr)
        fm = [e.surface(probe_sizes[j]).call([pr[j], wsm[self.ws_slices[j]]]) for j, e in enumerate(staged)]
        res, out_plain = balance(qm, flexm, thetam, loadm, wsm[self.data_slice], *[o[0] for o in fm],
                                 *[o[1] for o in fm])
        names_in = ["q", "theta", "load", "flexion", "ws"]
        self.residual = ca.Function("residual", [qm, thetam, loadm, flexm, wsm], [res], names_in, ["r"])
        # outputs for tables, in the order of :attr:`outputs`
        out_staged = {e.name: e.surface(probe_sizes[j], True).call([pr[j], wsm[self.ws_slices[j]]])[2:]
                      for j, e in enumerate(staged)}
        k = 0
        columns = []
        for e in self.elements:
            if isinstance(e, StagedElement):
                columns += out_staged[e.name]
            else:
                n = len(e.outputs())
                columns += [out_plain[k + i] for i in range(n)]
                k += n
        self.details = ca.Function("details", [qm, thetam, loadm, flexm, wsm],
                                   [res, ca.vertcat(*columns) if columns else ca.MX(0, 1)], names_in,
                                   ["r", "outputs"])


    @cached_property
    def exact_residual(self) -> ca.Function:
        """``(q, theta, load, flexion) -> r``: :attr:`residual` with every staged element's wrench
        computed inside the graph from the pose (:meth:`StagedElement.exact_wrench
        <kneenlp.model.elements.StagedElement.exact_wrench>`: for mesh contact the distance field
        itself, :mod:`kneenlp.geometry.graph_field`) instead of from working sets taken outside it.
        The same function at every pose; slower to evaluate, but self-contained (export)."""
        return self._exact_residual("vector")

    @cached_property
    def exact_residual_loop(self) -> ca.Function:
        """:attr:`exact_residual` with the field's spline as one point's function mapped over the
        points (:data:`kneenlp.geometry.graph_field.LAYOUTS`): the same values, C that compiles."""
        return self._exact_residual("loop")

    def residual_given(self, q: np.ndarray, theta: np.ndarray, load: np.ndarray, flexion: float,
                       wrenches: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """The equilibrium residual (5, N and N m) at the pose ``q`` (SI) with the staged elements'
        force and moment given (one pair per element of :attr:`staged`, in its ``wrench_frame``, N and
        N m about the tibial origin): another contact (e.g. the brute force of
        :mod:`kneenlp.testing.reference`) in the model's own balance."""
        data = self.working_data(q, theta, flexion, order=0)[self.data_slice]
        return np.asarray(self._balance_with(q, theta, load, flexion, wrenches, data), float).ravel()

    def _balance_with(self, q, theta, load, flexion, wrenches, data):
        """The balance's residual with the staged elements' wrenches and the pose data given (numeric or MX)."""
        return self._balance(q, flexion, theta, load, data, *[w[0] for w in wrenches], *[w[1] for w in wrenches])[0]

    def _exact_residual(self, layout: Layout) -> ca.Function:
        if self.pose_data:
            raise InputError(f"{self.pose_data[0].what} is solved outside CasADi at every pose, so no self-contained "
                             "graph of the residual (kneenlp export: .nl, CasADi, C) can carry it: export the knee "
                             "with that path straight or over an obstacle (cylinder, ellipsoid)")
        q, flexion = ca.MX.sym("q", 5), ca.MX.sym("flexion")
        theta, load = ca.MX.sym("theta", len(self.parameter_names)), ca.MX.sym("load", LOAD_SIZE)
        pr = self._probes(q, flexion, theta) if self.staged else []
        pr = [pr] if isinstance(pr, ca.MX) else list(pr)
        wrenches = [e.exact_wrench(pr[j], layout) for j, e in enumerate(self.staged)]
        r = self._balance_with(q, theta, load, flexion, wrenches, ca.DM(0, 1))
        return ca.Function("exact_residual", [q, theta, load, flexion], [r], ["q", "theta", "load", "flexion"], ["r"])
