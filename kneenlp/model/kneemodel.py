"""The CasADi model of a knee: ONE equilibrium residual function used by every solver.

``KneeModel(knee).residual`` is the function ``(q, theta, load, flexion) -> r``:

* ``q`` (5): free coordinates ``[varus, internal, lateral, anterior, proximal]`` (rad, m),
* ``theta`` (n): all model parameters in :attr:`KneeModel.parameter_names` order (SI),
* ``load`` (6): ``[Fx, Fy, Fz, Mx, My, Mz]`` in the femoral frame; the force acts at the tibial
  tuberosity, the moment is pure (N, N m),
* ``flexion`` (1): prescribed flexion (rad),
* ``r`` (5): generalised forces of ligaments + contact + load for the five free coordinates
  (N m for the rotations, N for the translations); equilibrium is ``r = 0``.  The flexion moment
  is reacted and does not appear.

The forward rootfinder, the simultaneous identification NLP and the nested objective all call
this same function.  It is built once per knee with the parameters as symbols, so changing a
parameter value never rebuilds it.  Structure (for speed of derivatives): an SX kinematics
function gives each condyle centre in the tibial frame, the mapped per-point contact functions of
:mod:`kneenlp.model.contact` give the contact wrenches, and an SX balance function adds ligaments and
loads and projects everything onto the generalised coordinates.
"""

from __future__ import annotations

from functools import cached_property

import casadi as ca
import numpy as np

from kneenlp.model.contact import compartment_function
from kneenlp.model.kinematics import generalized_forces, tibial_pose
from kneenlp.model.knee import Knee
from kneenlp.model.ligament import force_strain, slack_length
from kneenlp.model.parameters import (
    LIGAMENT_KINDS,
    MODULUS_INFO,
    ParameterInfo,
    ligament_parameter_info,
)


class KneeModel:
    """Symbolic equilibrium model of a :class:`~kneenlp.model.knee.Knee` (built once, reused)."""

    def __init__(self, knee: Knee, extra_effects: list | None = None):
        from kneenlp.model.effects import builtin_effects

        self.knee = knee
        self.ligament_names = list(knee.ligaments)
        self.compartment_names = list(knee.compartments)
        self.effects = [*knee.candidates, *builtin_effects(self.ligament_names), *(extra_effects or [])]
        self.parameter_info: list[ParameterInfo] = [
            ligament_parameter_info(lig, kind) for lig in self.ligament_names for kind in LIGAMENT_KINDS
        ] + [MODULUS_INFO]
        self.n_base = len(self.parameter_info)
        for e in self.effects:
            for ep in e.parameters:
                self.parameter_info.append(ParameterInfo(ep.name, ep.unit, ep.to_user, ep.description, ep.lower,
                                                         ep.upper, ep.scale, ep.neutral))
        self.parameter_names = [p.name for p in self.parameter_info]
        if len(set(self.parameter_names)) != len(self.parameter_names):
            raise ValueError(f"duplicate parameter names: {self.parameter_names}")
        self._build()

    # ------------------------------------------------------------------ construction
    def _build(self) -> None:
        knee = self.knee
        n_lig = len(self.ligament_names)
        n_comp = len(self.compartment_names)
        q = ca.SX.sym("q", 5)
        flexion = ca.SX.sym("flexion")
        R, p, axes = tibial_pose(flexion, q)
        centres = [R.T @ (ca.DM(c.sphere_center) - p) for c in knee.compartments.values()]
        kin = ca.Function("kinematics", [q, flexion], [ca.horzcat(*centres)], ["q", "flexion"], ["centres"])

        theta = ca.SX.sym("theta", len(self.parameter_names))
        values = {n: theta[i] for i, n in enumerate(self.parameter_names)}
        offset = sum((e.flexion_offset(values) for e in self.effects), ca.SX(0))
        bias = sum((e.measurement_bias(values) for e in self.effects), ca.SX.zeros(5))
        flex_eff = ca.Function("flexion_effective", [flexion, theta], [flexion + offset])
        self.measurement_bias = ca.Function("measurement_bias", [theta], [bias], ["theta"], ["bias"])
        load = ca.SX.sym("load", 6)
        fc = ca.SX.sym("contact_force", 3, n_comp)  # tibial frame
        mc = ca.SX.sym("contact_moment", 3, n_comp)  # tibial frame, about the tibial origin
        force = R @ ca.sum2(fc)
        moment = R @ ca.sum2(mc)
        strains, tensions = [], []
        for i, lig in enumerate(knee.ligaments.values()):
            k, eps_r, eps_l = theta[3 * i], theta[3 * i + 1], theta[3 * i + 2]
            arm = R @ ca.DM(lig.tibia)
            u = ca.DM(lig.femur) - (p + arm)
            length = ca.norm_2(u)
            eps = length / slack_length(lig.reference_length, eps_r) - 1
            tension = force_strain(eps, k, eps_l)
            f_vec = tension * u / length
            force += f_vec
            moment += ca.cross(arm, f_vec)
            strains.append(eps)
            tensions.append(tension)
        from kneenlp.model.effects import PoseContext

        ctx = PoseContext(R, p, q, ca.horzcat(*centres),
                          np.column_stack([c.sphere_center for c in knee.compartments.values()]))
        for e in self.effects:
            f_e, m_e = e.wrench(ctx, values)
            force += f_e
            moment += m_e
        arm = R @ ca.DM(knee.tuberosity)
        force += load[0:3]
        moment += ca.cross(arm, load[0:3]) + load[3:6]
        residual = generalized_forces(q, p, axes, force, moment)
        contact_fem = R @ fc  # contact forces in the femoral frame, per compartment
        balance = ca.Function(
            "balance",
            [q, flexion, theta, load, fc, mc],
            [residual, ca.vertcat(*strains), ca.vertcat(*tensions), contact_fem],
            ["q", "flexion", "theta", "load", "contact_force", "contact_moment"],
            ["residual", "strain", "tension", "contact_force_femoral"],
        )

        contact_fns = [
            compartment_function(c.name, c.points, c.areas, knee.gate) for c in knee.compartments.values()
        ]
        radii = [c.sphere_radius for c in knee.compartments.values()]
        i_mod = self.parameter_names.index("contact.modulus")

        qm = ca.MX.sym("q", 5)
        flexm = ca.MX.sym("flexion")
        thetam = ca.MX.sym("theta", len(self.parameter_names))
        loadm = ca.MX.sym("load", 6)
        flex_e = flex_eff(flexm, thetam)
        cen = kin(qm, flex_e)
        fcs, mcs = [], []
        for j, fn in enumerate(contact_fns):
            f_j, m_j = fn(cen[:, j], thetam[i_mod], radii[j])
            fcs.append(f_j)
            mcs.append(m_j)
        res, eps, ten, cf = balance(qm, flex_e, thetam, loadm, ca.horzcat(*fcs), ca.horzcat(*mcs))
        names_in = ["q", "theta", "load", "flexion"]
        self.residual = ca.Function("residual", [qm, thetam, loadm, flexm], [res], names_in, ["r"])
        depth = ca.vertcat(*[radii[j] - self._min_distance(contact_fns[j], cen[:, j], j) for j in range(n_comp)])
        self.details = ca.Function(
            "details",
            [qm, thetam, loadm, flexm],
            [res, eps, ten, cf, depth],
            names_in,
            ["r", "strain", "tension", "contact_force", "max_penetration"],
        )
        self._n_lig = n_lig

    def _min_distance(self, _fn: ca.Function, centre: ca.MX, j: int) -> ca.MX:
        """Smallest distance (m) from the condyle centre to a tibial sample point (for reports)."""
        pts = ca.DM(self.knee.compartments[self.compartment_names[j]].points.T)
        diff = pts - ca.repmat(centre, 1, pts.shape[1])
        return ca.sqrt(ca.mmin(ca.sum1(diff * diff)))

    # ------------------------------------------------------------------ helpers
    def theta(self, values: dict[str, float] | None = None) -> np.ndarray:
        """Full parameter vector (SI): the knee's parameter set, effect parameters at neutral,
        ``values`` (by name) overriding."""
        values = dict(values or {})
        for n in values:
            if n not in self.parameter_names:
                from kneenlp.errors import unknown_name

                raise unknown_name("parameter", n, self.parameter_names)
        out = []
        for info in self.parameter_info:
            if info.name in values:
                out.append(float(values[info.name]))
            elif info.neutral is not None:
                out.append(info.neutral)
            else:
                out.append(self.knee.parameters[info.name])
        return np.array(out, dtype=float)

    def bias_user(self, theta: np.ndarray) -> np.ndarray:
        """Measurement bias (mm, deg) that the effects add to the model's coordinates."""
        from kneenlp.conventions import TO_USER

        return np.asarray(self.measurement_bias(theta)).ravel() * TO_USER

    def effect(self, name: str):
        """The candidate effect called ``name``."""
        for e in self.effects:
            if e.name == name:
                return e
        from kneenlp.errors import unknown_name

        raise unknown_name("effect", name, [e.name for e in self.effects])

    def index(self, name: str) -> int:
        """Position of parameter ``name`` in ``theta``."""
        from kneenlp.errors import unknown_name

        try:
            return self.parameter_names.index(name)
        except ValueError:
            raise unknown_name("parameter", name, self.parameter_names) from None

    @cached_property
    def residual_jacobian(self) -> ca.Function:
        """``(q, theta, load, flexion) -> dr/dq`` (5 x 5)."""
        return self.residual.factory("residual_jac", ["q", "theta", "load", "flexion"], ["jac:r:q"])
