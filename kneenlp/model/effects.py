"""Candidate physical effects: model extensions that reduce exactly to the base model when neutral.

Each effect adds named parameters (with display units, neutral value, bounds and NLP scale) and
contributes one or more of: a wrench on the tibia (force and moment about the tibial origin, in
the femoral frame), a flexion offset, and a bias of the *measured* coordinates.  At the neutral
values every contribution is exactly zero, so the base fit is the extended fit with the effect's
parameters fixed at neutral.

Built-in effects (the library the adequacy check ranks):

* ``bundle`` (from the knee file's ``[candidates.<name>]``, e.g. ``posterior_capsule`` with a
  medial and a lateral sheet, ``ALL`` the anterolateral ligament): line elements with the
  ligament law; parameters ``<name>.k`` (neutral 0) and ``<name>.ref_strain``;
* ``meniscus``: a spring between each condyle centre and its reference position over the plateau
  (the menisci's resistance to condylar translation); ``meniscus.k`` in N/mm, neutral 0;
* ``flexion_offset``: the true flexion differs from the prescribed one; ``flexion_offset.delta`` in
  deg, neutral 0;
* ``registration``: a constant bias of the measured coordinates (a registration offset of the
  tracking frames); ``registration.<coordinate>`` in mm or deg, neutral 0;
* parameter groups of the base model: ``lin_strain`` (the four linear strain limits) and
  ``contact_modulus``.

Extension point: subclass :class:`Effect`, implement :meth:`Effect.wrench` (and/or
``flexion_offset``/``measurement_bias``) with CasADi expressions, and list it in
``KneeModel(knee, extra_effects=[...])``; see ``docs/adequacy.md`` for a complete example.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from kneenlp.conventions import COORDINATE_UNITS, COORDINATES, TO_USER
from kneenlp.model.ligament import force_strain, slack_length


@dataclass(frozen=True)
class EffectParameter:
    """A parameter of an effect (values SI; ``to_user`` converts to the display unit)."""

    name: str
    unit: str
    to_user: float
    neutral: float
    lower: float
    upper: float
    scale: float
    description: str = ""


@dataclass
class PoseContext:
    """Symbols an effect may use: rotation ``R`` (tibial -> femoral), tibial origin ``p`` (m),
    free coordinates ``q``, condyle centres in the tibial frame (3 x n_compartments, m)."""

    R: ca.SX
    p: ca.SX
    q: ca.SX
    centres: ca.SX
    reference_centres: np.ndarray


@dataclass
class Effect:
    """Base class: no contribution.  ``parameters`` lists the effect's own parameters;
    ``frees`` are the parameters freed when the effect is added (default: ``parameters``)."""

    name: str
    description: str = ""
    parameters: list[EffectParameter] = field(default_factory=list)
    frees: list[str] | None = None

    def free_names(self) -> list[str]:
        return list(self.frees) if self.frees is not None else [p.name for p in self.parameters]

    def wrench(self, ctx: PoseContext, values: dict[str, ca.SX]):
        """Force (N) and moment about the tibial origin (N m) on the tibia, femoral frame."""
        return ca.DM.zeros(3), ca.DM.zeros(3)

    def flexion_offset(self, values: dict[str, ca.SX]):
        return 0

    def measurement_bias(self, values: dict[str, ca.SX]):
        """Added to the model's coordinates before comparison with measurements (SI)."""
        return ca.DM.zeros(5)


@dataclass
class BundleEffect(Effect):
    """Extra line elements (m, femoral / tibial frames) sharing stiffness and reference strain."""

    femur: list[np.ndarray] = field(default_factory=list)
    tibia: list[np.ndarray] = field(default_factory=list)
    lin_strain: float = 0.03

    def wrench(self, ctx, values):
        k, eps_r = values[f"{self.name}.k"], values[f"{self.name}.ref_strain"]
        force, moment = ca.DM.zeros(3), ca.DM.zeros(3)
        for a_f, a_t in zip(self.femur, self.tibia, strict=True):
            arm = ctx.R @ ca.DM(a_t)
            u = ca.DM(a_f) - (ctx.p + arm)
            length = ca.norm_2(u)
            eps = length / slack_length(float(np.linalg.norm(a_f - a_t)), eps_r) - 1
            f = force_strain(eps, k, self.lin_strain) * u / length
            force += f
            moment += ca.cross(arm, f)
        return force, moment


def bundle(name: str, femur, tibia, ref_strain: float, description: str = "") -> BundleEffect:
    """A bundle effect with parameters ``<name>.k`` (neutral 0) and ``<name>.ref_strain``."""
    params = [
        EffectParameter(f"{name}.k", "N", 1.0, 0.0, 0.0, 1e5, 1e4, f"{name} stiffness, N per unit strain"),
        EffectParameter(f"{name}.ref_strain", "%", 100.0, ref_strain, -0.3, 0.3, 1e-2,
                        f"{name} reference strain"),
    ]
    return BundleEffect(name, description, params, [f"{name}.k"], [np.asarray(f, float) for f in femur],
                        [np.asarray(t, float) for t in tibia])


class MeniscusEffect(Effect):
    """Springs (N/m) between each condyle centre and its reference position over the plateau,
    acting in the tibial transverse plane (X, Z of the tibial frame)."""

    def __init__(self):
        super().__init__("meniscus", "menisci: resistance to condylar translation over the plateau",
                         [EffectParameter("meniscus.k", "N/mm", 1e-3, 0.0, 0.0, 1e7, 1e5,
                                          "meniscal spring stiffness per compartment")])

    def wrench(self, ctx, values):
        k = values["meniscus.k"]
        force, moment = ca.DM.zeros(3), ca.DM.zeros(3)
        mask = ca.DM([1.0, 0.0, 1.0])
        for j in range(ctx.centres.shape[1]):
            c = ctx.centres[:, j]
            f_t = k * mask * (c - ca.DM(ctx.reference_centres[:, j]))  # on the tibia, tibial frame
            force += ctx.R @ f_t
            moment += ctx.R @ ca.cross(c, f_t)
        return force, moment


class FlexionOffsetEffect(Effect):
    def __init__(self):
        super().__init__("flexion_offset", "the knee was flexed differently from the prescribed angle",
                         [EffectParameter("flexion_offset.delta", "deg", 180 / np.pi, 0.0, -0.2, 0.2, 1e-2,
                                          "true minus prescribed flexion")])

    def flexion_offset(self, values):
        return values["flexion_offset.delta"]


class RegistrationEffect(Effect):
    def __init__(self):
        params = [EffectParameter(f"registration.{c}", u, float(f), 0.0, -(0.2 if u == "deg" else 0.01),
                                  0.2 if u == "deg" else 0.01, 1e-2 if u == "deg" else 1e-3,
                                  f"constant bias of the measured {c.replace('_', ' ')}")
                  for c, u, f in zip(COORDINATES, COORDINATE_UNITS, TO_USER, strict=True)]
        super().__init__("registration", "a constant registration offset of the measured coordinates", params)

    def measurement_bias(self, values):
        return ca.vertcat(*[values[f"registration.{c}"] for c in COORDINATES])


def parameter_group(name: str, names: list[str], description: str) -> Effect:
    """An effect that frees existing base-model parameters (e.g. the linear strain limits)."""
    return Effect(name, description, [], names)


def builtin_effects(ligaments: list[str]) -> list[Effect]:
    return [MeniscusEffect(), FlexionOffsetEffect(), RegistrationEffect(),
            parameter_group("lin_strain", [f"{lig}.lin_strain" for lig in ligaments],
                            "the linear strain limits of the ligaments differ from 3 %"),
            parameter_group("contact_modulus", ["contact.modulus"], "the cartilage pressure modulus differs")]
