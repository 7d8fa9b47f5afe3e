"""How a lab measured the knee: the experiment's frames, registration, flexion and load point.

The knee's physics is :mod:`kneenlp.model` (force elements: ligaments, contact, menisci).  What a
robot or a tracking system adds on top is the experiment's, and lives here, as
:class:`ExperimentPart` s collected in one :class:`Measurement`:

* :class:`FlexionOffset`: the knee was flexed differently from the prescribed angle;
* :class:`Registration`: a constant bias of each measured coordinate (mm, deg);
* :class:`TibialOrigin`, :class:`FemoralOrigin`: the experiment reads its translations at other
  points of the tibia and the femur than the model's origins (a robot also applies its joint loads
  at its tibial origin);
* :class:`TibialAxes`: the experiment's tibial axes are turned from the model's;
* :class:`LoadPoint`: the applied force acts elsewhere than its nominal point;
* :class:`NeutralZone`: a dead band of the apparatus in the loaded direction.

Every part is neutral at its default (zero) values: the experiment is then the model's own frames,
bit for bit.  :class:`~kneenlp.experiment.kneemodel.KneeModel` combines the knee and its
:class:`Measurement` into ONE residual and ONE observation function.  Parts marked ``candidate``
are scored by model adequacy (:mod:`kneenlp.adequacy`); the others are fitted where named (a
calibration's ``also_free``).

Conventions: SI inside (m, rad), CasADi SX; ``values`` maps every model parameter to its symbol;
the file and report units are mm and deg (:mod:`kneenlp.model.parameters`).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from kneenlp.base.conventions import COORDINATE_UNITS, COORDINATES
from kneenlp.model.effects import Effect, parameter_group
from kneenlp.model.elements import Part, Pose
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
#: Default prior widths (sd) of a dead band's half-width in the loaded direction (mm, deg): the
#: play of a fixture or strap and the soft tissue between it and the bone (docs/priors.md).
NEUTRAL_ZONE_SD_MM = 2.0
NEUTRAL_ZONE_SD_DEG = 2.0
#: The coordinates a load drives (:data:`~kneenlp.experiment.protocol.LOADED_COORDINATE`): the
#: dead band's; the proximal translation carries the preload in every trial and has none.
NEUTRAL_ZONE_COORDINATES = COORDINATES[:4]


class ExperimentPart(Part):
    """A part of the experiment's description.  Base class: every hook neutral."""

    name = "experiment_part"

    def flexion_offset(self, values: dict[str, ca.SX]) -> ca.SX | float:
        """True minus prescribed flexion (rad)."""
        return 0.0

    def measurement_bias(self, pose: Pose, values: dict[str, ca.SX]) -> ca.SX | None:
        """Added to the model's five coordinates ``pose.q`` before comparison with measurements
        (rad, m); it may depend on the pose, flexion included."""
        return None

    def loaded_bias(self, loaded: ca.SX, values: dict[str, ca.SX]) -> ca.SX | None:
        """Added to the five measured coordinates (rad, m) of a trial whose dominant load drives the
        coordinate ``loaded`` marks (5: the load's sign there, else 0; :data:`~kneenlp.base.conventions.LOADED`)."""
        return None

    def load_point_offset(self, values: dict[str, ca.SX]) -> ca.SX | None:
        """Shift (tibial frame, m) of the point where the applied force acts, from its nominal point
        (the tuberosity for femoral or joint axes, the tibial origin for a robot's joint loads)."""
        return None

    def tibial_axes(self, values: dict[str, ca.SX]) -> ca.SX | None:
        """The experiment's tibial axes (columns) in the model's tibial frame, a rotation ``C``:
        the coordinates ``q`` and the prescribed flexion are those of the experiment's axes, and
        the tibia (its points, its meshes) turns with ``R_model = R(q) C^T``.  ``None``: the model's."""
        return None

    def joint_origin_offset(self, values: dict[str, ca.SX]) -> ca.SX | None:
        """Shift (tibial frame, m) of the experiment's tibial origin from the model's: where a
        robot reads its translations *and* applies its joint loads (the Grood-Suntay origin of
        both kinematics and kinetics).  The joint loads' force acts there too."""
        return None


class FlexionOffset(ExperimentPart):
    """The knee was flexed differently from the prescribed angle: ``flexion_offset.delta`` (deg)."""

    name = "flexion_offset"
    description = "the knee was flexed differently from the prescribed angle"
    candidate = True

    def parameters(self) -> list[Parameter]:
        return [Parameter("flexion_offset.delta", "angle", "true minus prescribed flexion", 0.0, 0.0)]

    def flexion_offset(self, values: dict) -> ca.SX:
        return values["flexion_offset.delta"]


class Registration(ExperimentPart):
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


class TibialOrigin(ExperimentPart):
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


class FemoralOrigin(ExperimentPart):
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


class TibialAxes(ExperimentPart):
    """The experiment's tibial axes are the model's turned by ``tibial_axes.varus`` (about the
    tibial anterior axis X) and ``tibial_axes.flexion`` (about the tibial lateral axis Z), deg: at
    zero internal rotation the experiment reads that much more varus and flexion.  (A turn about
    the long axis is the constant internal-rotation registration.)  A robot prescribes the flexion
    and applies its joint loads in its own axes, so the model's coordinates become the
    experiment's: the flexion is prescribed about the experiment's axes, the joint loads act along
    them, and the tibia turns with ``R_model = R(q) C^T``, ``C = Rz(-flexion) Rx(varus)``
    (:meth:`ExperimentPart.tibial_axes`).  Unlike the constant
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


class LoadPoint(ExperimentPart):
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


class NeutralZone(ExperimentPart):
    """A dead band of the apparatus in the loaded direction: under a load that drives a coordinate
    (the trial's dominant load, :attr:`~kneenlp.experiment.protocol.Trial.loaded`), the measured
    coordinate reads the knee's plus ``neutral_zone.<coordinate>`` (mm or deg, at least 0) in the
    load's sense: the play a strap, a fixture's pins or the soft tissue between them and the bone
    take up before the knee is loaded.  Unloaded trials and the other coordinates read the knee's.
    It differs from a constant registration in its sign, which follows the load: it widens every
    laxity (anterior minus posterior translation) by twice the half-width and leaves the unloaded
    pose alone.  (The hysteresis of an unloaded pose, which depends on the previous load, would need
    the trials' order, which the data files do not keep.)"""

    name = "neutral_zone"
    description = "a dead band of the apparatus in the loaded direction"
    candidate = True

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"neutral_zone.{c}", "angle" if u == "deg" else "length",
                          f"half-width of the dead band of the {c.replace('_', ' ')} in the loaded direction", 0.0,
                          0.0, lower=0.0, prior=("normal", np.deg2rad(NEUTRAL_ZONE_SD_DEG) if u == "deg" else
                                                 NEUTRAL_ZONE_SD_MM / 1e3))
                for c, u in zip(NEUTRAL_ZONE_COORDINATES, COORDINATE_UNITS, strict=False)]

    def loaded_bias(self, loaded: ca.SX, values: dict) -> ca.SX:
        return ca.vertcat(*[loaded[i] * values[f"neutral_zone.{c}"] for i, c in enumerate(NEUTRAL_ZONE_COORDINATES)],
                          0.0)


def _summed(vectors: list[ca.SX | None]) -> ca.SX:
    """The sum of the given 3-vectors (``None``: absent), zero if none."""
    return sum((v for v in vectors if v is not None), ca.SX.zeros(3))


@dataclass(frozen=True)
class Measurement:
    """The experiment's description: its parts, summed into what the knee model needs (SI)."""

    parts: tuple[ExperimentPart, ...]

    @classmethod
    def standard(cls) -> Measurement:
        """The parts every knee model carries, neutral until fitted: flexion offset, registration,
        load point, tibial and femoral origins, tibial axes, neutral zone (in this order: the
        parameter order)."""
        return cls((FlexionOffset(), Registration(), LoadPoint(), TibialOrigin(), FemoralOrigin(), TibialAxes(),
                    NeutralZone()))

    def with_parts(self, extra: list[ExperimentPart]) -> Measurement:
        """This description with ``extra`` parts after its own."""
        return Measurement((*self.parts, *extra))

    def flexion(self, flexion: ca.SX, values: dict[str, ca.SX]) -> ca.SX:
        """The knee's true flexion (rad) at the prescribed ``flexion``."""
        return flexion + sum((p.flexion_offset(values) for p in self.parts), ca.SX(0))

    def turn(self, values: dict[str, ca.SX]) -> ca.SX | None:
        """The experiment's tibial axes in the model's tibial frame (a rotation), ``None`` when no
        part turns them."""
        turns = [C for p in self.parts if (C := p.tibial_axes(values)) is not None]
        if not turns:
            return None
        turn = ca.SX.eye(3)
        for C in turns:
            turn = C @ turn
        return turn

    def load_point_shift(self, values: dict[str, ca.SX]) -> ca.SX:
        """Shift (tibial frame, m) of the applied force's point from its nominal point."""
        return _summed([p.load_point_offset(values) for p in self.parts])

    def joint_origin_shift(self, values: dict[str, ca.SX]) -> ca.SX:
        """Shift (tibial frame, m) of the experiment's tibial origin from the model's."""
        return _summed([p.joint_origin_offset(values) for p in self.parts])

    def bias(self, pose: Pose, values: dict[str, ca.SX], loaded: ca.SX) -> ca.SX | None:
        """Bias (rad, m) of the five measured coordinates at ``pose`` of a trial loaded as ``loaded``
        marks (:meth:`ExperimentPart.loaded_bias`), ``None`` when no part has one."""
        biases = [b for p in self.parts for b in (p.measurement_bias(pose, values), p.loaded_bias(loaded, values))
                  if b is not None]
        return sum(biases, ca.SX.zeros(5)) if biases else None


def registration_effects() -> list[Effect]:
    """One candidate per measured coordinate: a registration bias of that coordinate alone
    (``registration_<coordinate>``, 1 degree of freedom).  With only the 5-coordinate
    ``registration`` a bias of one coordinate was penalised for 4 parameters it does not need, and
    3-parameter attachment shifts mimicked it (benchmarks/bench_adequacy.py)."""
    return [parameter_group(f"registration_{c}", [f"registration.{c}"],
                            f"a constant registration offset of the measured {c.replace('_', ' ')} alone")
            for c in COORDINATES]
