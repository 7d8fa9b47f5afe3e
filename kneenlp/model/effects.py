"""Candidate physical effects: elements and parameter groups that are neutral in the base model.

An *effect* is something the model adequacy check can add (:mod:`kneenlp.adequacy.diagnosis`):

* a candidate force element (:class:`~kneenlp.model.elements.ForceElement` with
  ``candidate = True``): at its neutral parameter values it contributes exactly nothing, so the
  base fit is the extended fit with those parameters fixed.  Built in: bundles named in the knee
  file's ``[candidates.<name>]`` (e.g. ``posterior_capsule``, ``ALL``: :class:`Ligament` elements
  with stiffness 0), :class:`Meniscus`, :class:`FlexionOffset`, :class:`LoadPoint` and :class:`Registration` (all five
  coordinates; :func:`registration_effects` adds one candidate per coordinate); every model also carries
  :class:`TibialOrigin`, :class:`FemoralOrigin` and :class:`TibialAxes`, neutral and fitted only where named (not scored
  by the adequacy check);
* a parameter group of the base model (:func:`parameter_group`): ``lin_strain`` (the linear
  strain limits) and ``contact_modulus``;
* a geometry candidate (:func:`attachment_effects`): the position of one ligament's (or bundle
  group's) femoral or tibial attachments, ``<LIG>_femoral_attachment`` and
  ``<LIG>_tibial_attachment``, three shifts in mm each (anterior, proximal, lateral);
* a bundle group of a multi-bundle knee whose parameters a fit keeps fixed
  (:func:`bundle_group_effects`, ``<GROUP>_bundles``: stiffness scale and strain offset).

Extension point: subclass :class:`~kneenlp.model.elements.ForceElement` (set ``candidate = True``,
give :meth:`parameters` with a ``neutral`` value and :meth:`wrench`), and pass it as
``KneeModel(knee, extra_elements=[...])``; ``docs/architecture.md`` has a worked example.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from kneenlp.base.conventions import COORDINATE_UNITS, COORDINATES
from kneenlp.model.elements import ForceElement, Pose
from kneenlp.model.kinematics import rot_x, rot_z, tibial_pose
from kneenlp.model.parameters import Parameter

#: Axes of :class:`LoadPoint`'s shift, in the order of the tibial frame's X, Y, Z.
LOAD_POINT_AXES = ("anterior", "proximal", "lateral")
#: Default prior widths (sd) of the experiment's registration: a constant offset of each measured
#: coordinate (mm, deg), and the shift of a frame's origin or of the robot's load point (mm):
#: the spread of digitised landmarks and of frame definitions (docs/priors.md).
REGISTRATION_SD_MM = 5.0
REGISTRATION_SD_DEG = 5.0
ORIGIN_SD_MM = 5.0


@dataclass(frozen=True)
class Effect:
    """What adequacy can add: a name, a description and the parameters it frees."""

    name: str
    description: str
    parameters: tuple[str, ...]

    def free_names(self) -> list[str]:
        return list(self.parameters)

    def parameter_named(self, key: str) -> str | None:
        """The parameter ``key`` names: its full name, or a unique ending after a dot or an
        underscore (``k`` of ``posterior_capsule.k``, ``modulus`` of ``contact.modulus``,
        ``anterior`` of ``ACL.femur_anterior``) or beginning before a dot (``ACL`` of ``ACL.lin_strain``);
        ``None`` if none or several match."""
        if key in self.parameters:
            return key
        hits = [n for n in self.parameters if n.endswith(f".{key}") or n.endswith(f"_{key}")]
        hits = hits or [n for n in self.parameters if n.startswith(f"{key}.")]
        return hits[0] if len(hits) == 1 else None


class Meniscus(ForceElement):
    """Springs (N/m) between each condyle centre and its reference position over the plateau,
    acting in the tibial transverse plane (X, Z of the tibial frame): the menisci's resistance to
    condylar translation.  ``meniscus.k`` in N/mm.

    A candidate (neutral 0) unless the knee file declares its menisci (``[menisci] stiffness``,
    N/mm): then it is part of the base model with that default stiffness."""

    name = "meniscus"
    description = "menisci: resistance to condylar translation over the plateau"

    def __init__(self, centres: list[np.ndarray], stiffness: float | None = None,
                 rest: list[np.ndarray] | None = None):
        self.centres = [np.asarray(c, float) for c in centres]  # femoral frame, m
        #: where each centre sits over the plateau with the springs relaxed (tibial frame, m): at
        #: the knee's reference pose (the centres themselves where that pose is the identity)
        self.rest = [np.asarray(c, float) for c in (rest if rest is not None else centres)]
        self.stiffness = stiffness  # N/m, None: a candidate
        self.candidate = stiffness is None

    def parameters(self) -> list[Parameter]:
        if self.candidate:
            return [Parameter("meniscus.k", "spring", "meniscal spring stiffness per compartment", 0.0, 0.0)]
        return [Parameter("meniscus.k", "spring", "meniscal spring stiffness per compartment", self.stiffness)]

    def wrench(self, pose: Pose, values: dict) -> tuple[ca.SX, ca.SX]:
        k = values["meniscus.k"]
        force, moment = ca.SX.zeros(3), ca.SX.zeros(3)
        mask = ca.DM([1.0, 0.0, 1.0])
        for ref, rest in zip(self.centres, self.rest, strict=True):
            c = pose.to_tibial(ref)
            f_t = k * mask * (c - ca.DM(rest))  # on the tibia, tibial frame
            force += pose.R @ f_t
            moment += pose.R @ ca.cross(c, f_t)
        return force, moment


class FlexionOffset(ForceElement):
    """The knee was flexed differently from the prescribed angle: ``flexion_offset.delta`` (deg)."""

    name = "flexion_offset"
    description = "the knee was flexed differently from the prescribed angle"
    candidate = True

    def parameters(self) -> list[Parameter]:
        return [Parameter("flexion_offset.delta", "angle", "true minus prescribed flexion", 0.0, 0.0)]

    def flexion_offset(self, values: dict) -> ca.SX:
        return values["flexion_offset.delta"]


class Registration(ForceElement):
    """A constant bias of the measured coordinates (a registration offset of the tracking frames):
    ``registration.<coordinate>`` in mm or deg."""

    name = "registration"
    description = "a constant registration offset of the measured coordinates"
    candidate = True

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"registration.{c}", "angle" if u == "deg" else "length",
                          f"constant bias of the measured {c.replace('_', ' ')}", 0.0, 0.0,
                          prior=("normal", np.deg2rad(REGISTRATION_SD_DEG) if u == "deg" else REGISTRATION_SD_MM / 1e3))
                for c, u in zip(COORDINATES, COORDINATE_UNITS, strict=True)]

    def measurement_bias(self, pose, values: dict) -> ca.SX:
        return ca.vertcat(*[values[f"registration.{c}"] for c in COORDINATES])


class TibialOrigin(ForceElement):
    """The experiment reads its translations at a tibial point other than the model's tibial
    origin, moved by ``tibial_origin.<anterior|proximal|lateral>`` (mm, tibial frame X, Y, Z): a
    robot's tibial frame registered a few millimetres off the knee's.  Its Grood-Suntay
    translations are the model's plus ``[e1 e2 e3]^-1 R s``; with ``R = Rz(-flexion) B`` and the
    axes ``Rz(-flexion)`` times flexion-free vectors (:func:`~kneenlp.model.kinematics.tibial_pose`),
    this depends on the varus and internal rotations alone.  Unlike a constant registration it
    moves with the tibia: a point ``a`` mm anterior of the origin moves ``a`` mm laterally per
    radian of external rotation.  A robot applies its joint loads at the same origin (the
    Grood-Suntay origin of kinematics and kinetics), so the joint loads' force acts there too
    (:meth:`joint_origin_offset`); :class:`LoadPoint` shifts it further."""

    name = "tibial_origin"
    description = "the experiment reads its translations at another tibial point"
    #: not scored by ``diagnose`` (near small rotations it is the constant registration of the three
    #: translations, which the adequacy check already tests); fitted where named, e.g. ``calibrate``'s
    #: ``also_free`` (S192803, docs/real-experiment.md)
    candidate = False

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"tibial_origin.{a}", "length", f"{a} shift of the tibial point the translations are read at",
                          0.0, 0.0, prior=("normal", ORIGIN_SD_MM / 1e3)) for a in LOAD_POINT_AXES]

    def joint_origin_offset(self, values: dict) -> ca.SX:
        return ca.vertcat(*[values[f"tibial_origin.{a}"] for a in LOAD_POINT_AXES])

    def measurement_bias(self, pose, values: dict) -> ca.SX:
        q = pose.q
        shift = self.joint_origin_offset(values)
        R, _, _ = tibial_pose(0.0, q)  # any flexion gives the same (docstring)
        w = R @ shift
        # at zero flexion the axes are e1 = Z, e2 = X, e3 = (0, cos v, sin v): [e1 e2 e3] d = w solved
        # by hand (no symbolic solve in the exported graphs)
        proximal = w[1] / ca.cos(q[0])
        return ca.vertcat(0.0, 0.0, w[2] - ca.sin(q[0]) * proximal, w[0], proximal)


class FemoralOrigin(ForceElement):
    """The experiment's femoral origin is elsewhere than the model's: moved by
    ``femoral_origin.<anterior|proximal|lateral>`` (mm, femoral frame X, Y, Z).  Its Grood-Suntay
    translations are those of the tibial origin from that point, the model's minus
    ``[e1 e2 e3]^-1 s``; as the tibial axis ``e3`` turns with the flexion, so does the bias: a point
    1 mm posterior of the model's origin adds 1 mm to the anterior translation in extension and to
    the proximal translation at 90 deg.  With :class:`TibialOrigin` and the constant rotations of
    :class:`Registration` it places the experiment's frames on the model's, up to the directions
    of the axes.  The joint loads act at the tibial origin and do not move."""

    name = "femoral_origin"
    description = "the experiment reads its translations from another femoral point"
    #: fitted where named, like :class:`TibialOrigin` (S192803, docs/real-experiment.md)
    candidate = False

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"femoral_origin.{a}", "length", f"{a} shift of the femoral point the translations are "
                          "read from", 0.0, 0.0, prior=("normal", ORIGIN_SD_MM / 1e3)) for a in LOAD_POINT_AXES]

    def measurement_bias(self, pose, values: dict) -> ca.SX:
        s = ca.vertcat(*[values[f"femoral_origin.{a}"] for a in LOAD_POINT_AXES])
        sf, cf, v = ca.sin(pose.flexion), ca.cos(pose.flexion), pose.q[0]
        # -s = lateral e1 + anterior e2 + proximal e3 with e1 = Z, e2 = (cos f, -sin f, 0) and
        # e3 = (cos v sin f, cos v cos f, sin v) (tibial_pose), solved by hand
        proximal = -(s[0] * sf + s[1] * cf) / ca.cos(v)
        anterior = -(s[0] * cf - s[1] * sf)
        return ca.vertcat(0.0, 0.0, -s[2] - ca.sin(v) * proximal, anterior, proximal)


class TibialAxes(ForceElement):
    """The experiment's tibial axes are the model's turned by ``tibial_axes.varus`` (about the
    tibial anterior axis X) and ``tibial_axes.flexion`` (about the tibial lateral axis Z), deg: at
    zero internal rotation the experiment reads that much more varus and flexion.  (A turn about
    the long axis is the constant internal-rotation registration.)  A robot prescribes the flexion
    and applies its joint loads in its own axes, so the model's coordinates become the
    experiment's: the flexion is prescribed about the experiment's axes, the joint loads act along
    them, and the tibia turns with ``R_model = R(q) C^T``, ``C = Rz(-flexion) Rx(varus)``
    (:meth:`~kneenlp.model.elements.ForceElement.tibial_axes`).  Unlike the constant
    registration, the turn couples the readings: with internal rotation ``i`` a varus turn ``a``
    reads ``a cos i`` of varus and ``a sin i`` of flexion, so the model is held at another flexion
    under internal-external loads."""

    name = "tibial_axes"
    description = "the experiment's tibial axes are turned from the model's"
    #: fitted where named, like :class:`TibialOrigin` (S192803, docs/real-experiment.md);
    #: not scored by ``diagnose``: near small internal rotations the varus turn reads as the constant
    #: varus registration (``a cos i``), which the adequacy check already tests
    candidate = False

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"tibial_axes.{a}", "angle", f"{a} turn of the experiment's tibial axes from the model's",
                          0.0, 0.0) for a in ("varus", "flexion")]

    def tibial_axes(self, values: dict) -> ca.SX:
        return rot_z(-values["tibial_axes.flexion"]) @ rot_x(values["tibial_axes.varus"])


class LoadPoint(ForceElement):
    """The applied force acts elsewhere than the model assumes: its point moved by
    ``load_point.<anterior|proximal|lateral>`` (mm, tibial frame X, Y, Z) from the tuberosity
    (femoral or joint axes) or from the tibial origin (a robot's joint loads).  A robot whose
    load-reference point is registered a few millimetres off the knee's tibial origin applies an
    extra moment, the force times the offset: 200 N of drawer 8 mm off the origin is 1.6 N m of
    internal-external moment."""

    name = "load_point"
    description = "the applied force acts elsewhere than the model's load point"
    candidate = True

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"load_point.{a}", "length", f"{a} shift of the point the applied force acts at", 0.0, 0.0,
                          prior=("normal", ORIGIN_SD_MM / 1e3)) for a in LOAD_POINT_AXES]

    def load_point_offset(self, values: dict) -> ca.SX:
        return ca.vertcat(*[values[f"load_point.{a}"] for a in LOAD_POINT_AXES])


def registration_effects() -> list[Effect]:
    """One candidate per measured coordinate: a registration bias of that coordinate alone
    (``registration_<coordinate>``, 1 degree of freedom).  With only the 5-coordinate
    ``registration`` a bias of one coordinate was penalised for 4 parameters it does not need, and
    3-parameter attachment shifts mimicked it (benchmarks/bench_adequacy.py)."""
    return [parameter_group(f"registration_{c}", [f"registration.{c}"],
                            f"a constant registration offset of the measured {c.replace('_', ' ')} alone")
            for c in COORDINATES]


def parameter_group(name: str, names: list[str], description: str) -> Effect:
    """An effect that frees existing base-model parameters (e.g. the linear strain limits)."""
    return Effect(name, description, tuple(names))


def builtin_elements(centres: list[np.ndarray], meniscus: bool = True,
                     rest: list[np.ndarray] | None = None) -> list[ForceElement]:
    """The candidate elements every knee model carries (neutral until freed); ``meniscus=False``
    for a knee whose menisci are part of its base model; ``rest``: the condyle centres' rest
    positions over the plateaus (:class:`Meniscus`)."""
    return [*([Meniscus(centres, rest=rest)] if meniscus else []), FlexionOffset(), Registration(), LoadPoint(),
            TibialOrigin(), FemoralOrigin(), TibialAxes()]


def builtin_groups(ligaments: list[str]) -> list[Effect]:
    """Effects that free base-model parameters: the linear strain limits of the (single-law)
    ``ligaments`` and the contact modulus."""
    groups = [parameter_group("lin_strain", [f"{lig}.lin_strain" for lig in ligaments],
                              "the linear strain limits of the ligaments differ from 3 %")] if ligaments else []
    return [*groups, parameter_group("contact_modulus", ["contact.modulus"], "the cartilage pressure modulus differs")]


def bundle_group_effects(groups: list[str]) -> list[Effect]:
    """One candidate per bundle group of a multi-bundle knee: the group's stiffness scale and
    reference-strain offset (``<group>.k_scale``, ``<group>.ref_strain_offset``).  A candidate
    only where a fit keeps them at the model's values (e.g. a group left out of ``--free``)."""
    return [parameter_group(f"{g}_bundles", [f"{g}.k_scale", f"{g}.ref_strain_offset"],
                            f"the {g} bundles are stiffer or slacker than the model's") for g in groups]


def attachment_effects(ligaments: list[str]) -> list[Effect]:
    """One geometry candidate per ligament (or bundle group) and side: its attachments moved by
    a vector (``<lig>.femur_anterior`` ..., mm; :mod:`kneenlp.model.ligament`)."""
    from kneenlp.model.ligament import SHIFT_AXES

    out = []
    for lig in ligaments:
        for side, word in (("femur", "femoral"), ("tibia", "tibial")):
            out.append(Effect(f"{lig}_{word}_attachment", f"the {lig} {word} attachment is elsewhere",
                              tuple(f"{lig}.{side}_{axis}" for axis in SHIFT_AXES)))
    return out
