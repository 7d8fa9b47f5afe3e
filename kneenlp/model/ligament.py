"""Ligament line elements; by default with the toe + linear force-strain law of the paper (Eq. 1-3),
any :class:`~kneenlp.model.laws.LigamentLaw` by choice (a knee file's ``law``).

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

Multi-bundle ligaments (OpenSim's Blankevoort1991Ligament bundles, grouped): every bundle has its
own stiffness ``k_i``, reference strain ``eps_r,i`` and linear strain limit; the group's
parameters are a stiffness scale ``<group>.k_scale`` (bundle stiffness ``k_scale k_i``, default 1)
and a reference-strain offset ``<group>.ref_strain_offset`` (bundle reference strain ``eps_r,i +
offset``, default 0): the fit moves the whole group and keeps its internal pattern.  A group
imported from a finite-element model moves as the FE's does (:class:`SlackShift`, the knee file's
``slack_shift``): every bundle's slack length by one length, so that the calibration is the FE
model's own parameters (:func:`bundle_law`, :mod:`kneenlp.io.export_abaqus`).

Attachment shifts: every (non-candidate) ligament also has six parameters, neutral 0, that move
all its femoral attachments (femoral frame) and all its tibial attachments (tibial frame) by a
vector (m inside, mm at the user boundary): ``<lig>.femur_anterior``, ``.femur_proximal``,
``.femur_lateral``, ``.tibia_anterior``, ... (axes X anterior, Y proximal, Z lateral of
:mod:`kneenlp.base.conventions`).  The reference length follows the moved attachments, so the model
with a shift equals a knee file whose attachments are moved by it (a segmentation error); model
adequacy frees them as geometry candidates (:func:`kneenlp.model.effects.attachment_effects`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from kneenlp.base.keywords import keyword_options
from kneenlp.model.bone_wrap import PATH_DATA, BoneWrap
from kneenlp.model.elements import ForceElement, Output, Pose, PoseData
from kneenlp.model.laws import NUMPY, LigamentLaw, ToeLinearLaw
from kneenlp.model.parameters import LIGAMENT_KINDS, Parameter, ligament_parameters
from kneenlp.model.paths import LigamentPath, StraightPath


def force_strain(eps, k, eps_l):
    """Tensile force (N) of Eq. (1) as a CasADi expression of strain ``eps``
    (:class:`~kneenlp.model.laws.ToeLinearLaw`)."""
    return ToeLinearLaw().tension(eps, k, eps_l)


def force_strain_numpy(eps: np.ndarray, k: float, eps_l: float) -> np.ndarray:
    """Eq. (1) on NumPy arrays (the same law), for checking and plotting."""
    return ToeLinearLaw().tension(np.asarray(eps, dtype=float), k, eps_l, NUMPY)


#: Attachment-shift axes, in the order of the frames' X, Y, Z (:mod:`kneenlp.base.conventions`).
SHIFT_AXES: tuple[str, ...] = ("anterior", "proximal", "lateral")
#: Largest attachment shift a fit may give (m).
SHIFT_BOUND = 0.02


def attachment_parameters(ligament: str) -> list[Parameter]:
    """The six attachment-shift parameters of ``ligament`` (m, neutral 0; see module docstring)."""
    return [Parameter(f"{ligament}.{side}_{axis}", "length",
                      f"{ligament} {'femoral' if side == 'femur' else 'tibial'} attachment shift, {axis}",
                      0.0, 0.0, -SHIFT_BOUND, SHIFT_BOUND)
            for side in ("femur", "tibia") for axis in SHIFT_AXES]


def slack_length(reference_length, ref_strain):
    """Slack length ``l0 = l_r / (1 + eps_r)`` (Eq. 2), same unit as ``reference_length``."""
    return reference_length / (1 + ref_strain)


@dataclass(frozen=True)
class SlackShift:
    """A bundle group whose reference-strain offset moves every bundle's slack length by one length,
    as a finite-element model's ligament group does (Abaqus: ``L0 = L / EREF``, each fibre slack at
    its own imaged length ``+ L0 - L``): the group's reference length ``length`` (m, the FE's ``L``)
    at its reference strain ``ref_strain`` (fraction, the FE's ``EREF - 1``)."""

    length: float
    ref_strain: float

    def rest_length(self, offset=0.0):
        """The group's slack length ``L / (1 + ref_strain + offset)`` (m; the FE's ``L0``)."""
        return slack_length(self.length, self.ref_strain + offset)


def bundle_law(b: Bundle, imaged: float, reference, group: tuple, shift: SlackShift | None = None):
    """``(slack length, stiffness, linear strain limit)`` of bundle ``b`` of a group with the
    parameters ``group = (scale, offset)``: stiffness scale and reference-strain offset (numbers or
    CasADi expressions), the one place they act.  ``imaged`` is the bundle's length in the reference pose as the
    knee file gives it (m), ``reference`` the same length after attachment shifts.

    Without ``shift``: slack ``reference / (1 + eps_r + offset)``, stiffness ``scale k``, the
    bundle's own limit (module docstring).  With a :class:`SlackShift` (an Abaqus group, so that
    a calibration writes back into the FE model exactly; :mod:`kneenlp.io.export_abaqus`): every
    slack length moves by the group's ``L0(offset) - L0(0)``, the stiffness per unit length
    ``k / s`` (N/m) is the bundle's times ``scale``, and the toe's length ``2 eps_l s`` scales with
    ``L0`` (the FE's toe is ``2 ET L0``)."""
    scale, offset = group
    if shift is None:
        return slack_length(reference, b.ref_strain + offset), scale * b.stiffness, b.lin_strain
    own = slack_length(imaged, b.ref_strain)
    rest, rest0 = shift.rest_length(offset), shift.rest_length()
    slack = reference - imaged + own + (rest - rest0)
    return slack, scale * b.stiffness * slack / own, b.lin_strain * own * (rest / rest0) / slack


@dataclass(frozen=True)
class Bundle:
    """One line element: femoral attachment (femoral frame) and tibial attachment (tibial frame), m.

    A bundle of a multi-bundle (grouped) ligament carries its own properties: ``stiffness`` (N per
    unit strain), ``ref_strain`` (at the reference pose) and ``lin_strain`` (the paper's linear
    strain limit, half OpenSim's transition strain); ``name`` is its name in the source model."""

    femur: np.ndarray
    tibia: np.ndarray
    name: str = ""
    stiffness: float | None = None
    ref_strain: float | None = None
    lin_strain: float | None = None
    #: how it runs between the attachments (:mod:`kneenlp.model.paths`; straight by default)
    path: LigamentPath = field(default_factory=StraightPath)

    @property
    def reference_length(self) -> float:
        """Length (m) where the tibial and femoral frames coincide (:meth:`Ligament.bundle_length`
        gives it in the ligament's reference pose)."""
        return float(np.linalg.norm(np.asarray(self.femur) - np.asarray(self.tibia)))


@dataclass(frozen=True)
class LigamentOptions:
    """The keyword options of :class:`Ligament` (its docstring), checked in one place (:meth:`of`)."""

    law: LigamentLaw | None = None
    candidate: bool = False
    defaults: dict[str, float] | None = None
    description: str = ""
    reference: tuple[np.ndarray, np.ndarray] | None = None
    shift: SlackShift | None = None



class Ligament(ForceElement):
    """A ligament: one or more bundles (line elements) sharing one law (``law``, default the paper's
    :class:`~kneenlp.model.laws.ToeLinearLaw`), its parameters and a reference strain.  A
    *candidate* ligament (e.g. the posterior capsule named in a knee file) has stiffness 0 in the
    knee's parameter set; adding it as an effect frees its stiffness.

    Keyword options (:class:`LigamentOptions`): ``law``; ``candidate`` (False); ``defaults`` (its
    parameters' values other than the defaults, by kind); ``description``; ``reference`` (the
    reference pose, below); ``shift`` (a :class:`SlackShift`, below).

    Outputs: strain (%, the largest over the bundles) and force (N, the sum over the bundles).
    """

    def __init__(self, name: str, bundles: list[Bundle], **options):
        if not bundles:
            raise ValueError(f"ligament {name} has no bundles")
        opts = keyword_options(LigamentOptions, "Ligament", options)
        law, candidate, defaults, description, reference, shift = (
            opts.law, opts.candidate, opts.defaults, opts.description, opts.reference, opts.shift)
        self.name, self.bundles, self.law = name, list(bundles), law or ToeLinearLaw()
        #: the reference pose (rotation tibial -> femoral, tibial origin in the femoral frame, m)
        #: where reference strains are defined: the knee's imaged pose (identity by default)
        self.reference = (np.eye(3), np.zeros(3)) if reference is None else (
            np.asarray(reference[0], float), np.asarray(reference[1], float))
        self.candidate, self.description = candidate, description
        self._defaults = dict(defaults or {})
        #: a group of bundles with their own properties (parameters: k_scale, ref_strain_offset)
        self.grouped = all(b.stiffness is not None for b in self.bundles)
        #: how the group's reference-strain offset moves its slack lengths (None: each bundle's by
        #: its own strain; a :class:`SlackShift`: all by one length, as an FE group)
        self.shift = shift
        if shift is not None and not self.grouped:
            raise ValueError(f"ligament {name}: a slack shift needs bundles with their own properties")

    def main_parameters(self) -> list[str]:
        """What an identification frees by default: stiffness and reference strain (of the group)."""
        if self.grouped:
            return [f"{self.name}.k_scale", f"{self.name}.ref_strain_offset"]
        return [f"{self.name}.k", f"{self.name}.ref_strain"]

    @property
    def femur(self) -> np.ndarray:
        """Femoral attachment of the first bundle (m)."""
        return self.bundles[0].femur

    @property
    def tibia(self) -> np.ndarray:
        """Tibial attachment of the first bundle (m)."""
        return self.bundles[0].tibia

    @property
    def reference_length(self) -> float:
        """Length (m) of the first bundle in the reference pose."""
        return self.bundle_length(self.bundles[0])

    def tibia_at_reference(self, point) -> np.ndarray:
        """A tibial point (tibial frame) in the femoral frame at the reference pose (m)."""
        R, p = self.reference
        return R @ np.asarray(point, float) + p

    def bundle_length(self, b: Bundle) -> float:
        """Length (m) of bundle ``b`` in the reference pose (along its path)."""
        if isinstance(b.path, StraightPath):
            return float(np.linalg.norm(np.asarray(b.femur) - self.tibia_at_reference(b.tibia)))
        return b.path.length(b.femur, b.tibia, *self.reference)

    def parameters(self) -> list[Parameter]:
        shifts = [] if self.candidate else attachment_parameters(self.name)
        if self.grouped:
            return [Parameter(f"{self.name}.k_scale", "scale", f"{self.name} stiffness scale (every bundle)", 1.0),
                    Parameter(f"{self.name}.ref_strain_offset", "ref_strain",
                              f"{self.name} reference-strain offset (every bundle)", 0.0), *shifts]
        neutral = {"k": 0.0} if self.candidate else None
        defaults = ({"k": 0.0, "lin_strain": 0.03} | self._defaults) if self.candidate else self._defaults
        return [*ligament_parameters(self.name, defaults, neutral), *shifts]

    def direction(self) -> np.ndarray:
        """Unit vector from the tibial to the femoral attachment in the reference pose (the mean
        over the bundles; femoral and tibial frames coincide there).  An attachment shift along it
        moves the point along the line of action, which laxity data barely see: the reference
        strain absorbs the length change."""
        u = np.mean([(np.asarray(b.femur) - self.tibia_at_reference(b.tibia)) / self.bundle_length(b)
                     for b in self.bundles], axis=0)
        return u / np.linalg.norm(u)

    def attachment_names(self, side: str) -> list[str]:
        """The three shift parameters of the ``side`` ("femur" or "tibia") attachments."""
        return [f"{self.name}.{side}_{axis}" for axis in SHIFT_AXES]

    def frees(self) -> list[str]:
        return [f"{self.name}.k"] if self.candidate else super().frees()

    def _shift(self, side: str, values: dict) -> ca.SX | float:
        if self.candidate:
            return 0.0
        return ca.vertcat(*[values[n] for n in self.attachment_names(side)])

    def attachments(self, b: Bundle, values: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """Bundle ``b``'s femoral and tibial attachments (m) moved by the shifts in ``values`` (numbers)."""
        return tuple(np.asarray(x, float) + np.array([values.get(n, 0.0) for n in self.attachment_names(side)])
                     for x, side in ((b.femur, "femur"), (b.tibia, "tibia")))

    def _data_key(self, i: int, at_reference: bool = False) -> str:
        """The key of bundle ``i``'s pose data (:meth:`pose_data`)."""
        return f"{self.name}.bundle{i}.path" + (".reference" if at_reference else "")

    def pose_data(self) -> list[PoseData]:
        """Each bundle over a bone (:class:`~kneenlp.model.bone_wrap.BoneWrap`): its path at the pose
        and in the reference pose (where its reference length is measured, moved with the shifts)."""
        out = []
        for i, b in enumerate(self.bundles):
            if isinstance(b.path, BoneWrap):
                def take(R, p, values, b=b):
                    return b.path.take(*self.attachments(b, values), R, p)

                def take_reference(R, p, values, b=b):  # one pose for all: it moves with the parameters only
                    one = b.path.take(*self.attachments(b, values), self.reference[0][None], self.reference[1][None])
                    return np.repeat(one, len(p), axis=0)

                what = f"ligament {self.name} bundle {b.name or self.name!r}'s path over the {b.path.bone}"
                out += [PoseData(self._data_key(i), b.path.data_size, take, what),
                        PoseData(self._data_key(i, True), b.path.data_size, take_reference, what)]
        return out

    def _bundle_terms(self, pose: Pose, values: dict):
        shift_f, shift_t = self._shift("femur", values), self._shift("tibia", values)
        if self.grouped:
            scale, offset = values[f"{self.name}.k_scale"], values[f"{self.name}.ref_strain_offset"]
        else:
            own = {kind: values[f"{self.name}.{kind}"] for kind in LIGAMENT_KINDS}
        at_reference = Pose(ca.DM(self.reference[0]), ca.DM(self.reference[1]), ca.DM.zeros(5), ca.DM(0))
        for i, b in enumerate(self.bundles):
            femur, tibia = ca.DM(b.femur) + shift_f, ca.DM(b.tibia) + shift_t
            here, there = pose, at_reference
            if isinstance(b.path, BoneWrap):  # its own pose data (pose_data)
                here = dataclasses.replace(pose, data={PATH_DATA: pose.data[self._data_key(i)]})
                there = dataclasses.replace(at_reference, data={PATH_DATA: pose.data[self._data_key(i, True)]})
            reference = b.path.route(femur, tibia, there).length if not self.candidate else self.bundle_length(b)
            route = b.path.route(femur, tibia, here)
            length = route.length
            if self.grouped:
                slack, k, lin = bundle_law(b, self.bundle_length(b), reference, (scale, offset), self.shift)
                strain = length / slack - 1
                tension = self.law.tension(strain, k, lin)
            else:
                strain = length / slack_length(reference, own["ref_strain"]) - 1
                tension = self.law.tension(strain, own["k"], own["lin_strain"])
            yield route, strain, tension

    def wrench(self, pose: Pose, values: dict) -> tuple[ca.SX, ca.SX]:
        force, moment = ca.SX.zeros(3), ca.SX.zeros(3)
        for route, _, tension in self._bundle_terms(pose, values):
            f, m = route.wrench(tension)
            force += f
            moment += m
        return force, moment

    def outputs(self) -> list[Output]:
        return [Output("strain", f"{self.name}_strain_pct", "%", 100.0), Output("force", f"{self.name}_force_N", "N")]

    def output_values(self, pose: Pose, values: dict) -> list[ca.SX]:
        terms = list(self._bundle_terms(pose, values))
        strain = terms[0][1]
        for t in terms[1:]:
            strain = ca.fmax(strain, t[1])
        return [strain, sum((t[2] for t in terms), ca.SX(0))]
