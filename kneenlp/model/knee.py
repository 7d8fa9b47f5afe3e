"""A knee: geometry (articular surfaces, ligament attachments, frames) plus a default parameter set.

A knee is described by a TOML file (e.g. ``kneenlp/resources/knees/default/knee.toml``, the
Lenhart 2015 knee) that names its cartilage meshes (STL/PLY/OBJ, read with trimesh), ligament
attachments, landmarks and contact settings (:mod:`kneenlp.model.articular`), in millimetres
(``units = "mm"``) or metres (``units = "m"``, as OpenSim files are), either already in the
femoral frame (``coordinates = "femoral"``, the default) or in scanner coordinates
(``coordinates = "scan"``), which are mapped into the femoral frame by the method ``frame``
(:mod:`kneenlp.model.frames`: cylinder fits to the condyles, or ISB landmarks).  Tibial points
are given in the tibial frame, which coincides with the femoral frame in the reference pose (the
pose of the scan).  :meth:`Knee.load` validates the file and converts everything to SI.  A left
knee (``side = "left"``) is mirrored into a right knee (Z -> -Z), which keeps the anatomical
meaning of every coordinate.

Knees shipped with the package are loaded by name: ``Knee.named("synthetic")``; the default is
the real Lenhart 2015 knee (:func:`available_knees`).  :meth:`Knee.report` says how the surfaces
and frames were built: the tibial split, the condyle split, the flexion-axis fit and the distance
field's measured error.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kneenlp.base.errors import InputError
from kneenlp.geometry.axes import FlexionAxis
from kneenlp.model.articular import (
    RIM_GAP,
    TOUCHABLE_FLEXION_DEG,
    Compartment,
    FemoralSurface,
    field_summary,
    swept_tibia,
)
from kneenlp.model.elements import ForceElement
from kneenlp.model.kinematics import reference_transform
from kneenlp.model.knee_file import KneeFile, check_parameter_set, default_knee_file, knee_file, resolve_knee
from kneenlp.model.laws import DEFAULT_PRESSURE_LAW
from kneenlp.model.ligament import Ligament
from kneenlp.model.mesh_contact import RIM_SHARE
from kneenlp.model.parameters import ParameterSet
from kneenlp.model.structures import structure_tables


@dataclass
class Knee:
    """Geometry of a (right) knee and its default mechanical parameters (SI)."""

    name: str
    ligaments: dict[str, Ligament]
    compartments: dict[str, Compartment]
    tuberosity: np.ndarray  # tibial frame, m
    parameters: ParameterSet
    gate: float = 1e-5  # m
    working_set: int = 0  # sphere contact: points per compartment and trial (0: every point)
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    source: str | None = None
    description: str = ""
    candidates: list[Ligament] = field(default_factory=list)  # [candidates.*]: bundles with stiffness 0
    femur: FemoralSurface | None = None  # the femoral surface of the mesh compartments
    axis: FlexionAxis | None = None  # fitted flexion axis (femoral frame)
    #: the built-in structures the knee file declares (:mod:`kneenlp.model.structures`): each
    #: table's value (SI) by table name, e.g. ``{"menisci": 5000.0}`` (N/m)
    structures: dict[str, object] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)  # how the file became this knee
    #: the pose in which the geometry was imaged ([reference_pose]): flexion (rad) and the five
    #: coordinates (rad, m); reference strains refer to it, solvers start from it
    reference_pose: tuple[float, np.ndarray] = (0.0, np.zeros(5))
    side: str = "right"  # the side of the knee file (the model is always a right knee)

    @property
    def reference_transform(self) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (tibial -> femoral) and tibial origin (femoral frame, m) at the reference pose."""
        return reference_transform(*self.reference_pose)

    @classmethod
    def default(cls) -> Knee:
        """The embedded default knee (the Lenhart 2015 knee, Table 1 properties)."""
        return cls.load(default_knee_file())

    @classmethod
    def named(cls, name: str) -> Knee:
        """A knee shipped with the package, by name (:func:`available_knees`)."""
        return cls.load(knee_file(name))

    @classmethod
    def load(cls, path: str | Path, parameters: str | Path | ParameterSet | None = None) -> Knee:
        """Read and validate a knee TOML, a knee directory holding ``knee.toml`` (as the importers
        write it), or the name of a shipped knee; see module docstring."""
        return cls(**KneeFile(resolve_knee(path)).fields(parameters))

    @property
    def ligament_names(self) -> list[str]:
        return list(self.ligaments)

    def elements(self) -> list[ForceElement]:
        """The knee's force elements: its ligaments, the built-in structures (the contact of each
        compartment, and those its file declares: :mod:`kneenlp.model.structures`) and the candidate
        bundles of its file (neutral: stiffness 0)."""
        structures = [e for t in structure_tables() if t.read is None or t.name in self.structures
                      for e in t.declared(self, self.structures.get(t.name))]
        return [*self.ligaments.values(), *structures, *self.candidates]

    def structure_candidates(self) -> list[ForceElement]:
        """The neutral candidates of the built-in structures its file does not declare (model
        adequacy may free them; :mod:`kneenlp.model.structures`)."""
        return [e for t in structure_tables() if t.read is not None and t.name not in self.structures
                for e in t.candidates(self)]

    def condyle_centres(self) -> list[np.ndarray]:
        """Centre of each femoral condyle (femoral frame, m): where the meniscus springs act."""
        return [c.centre for c in self.compartments.values()]

    def condyle_rest(self) -> list[np.ndarray]:
        """Each condyle centre in the tibial frame at the reference pose (m): the meniscus springs'
        rest positions."""
        R, p = self.reference_transform
        return [R.T @ (c - p) for c in self.condyle_centres()]

    def with_parameters(self, parameters: ParameterSet | str | Path) -> Knee:
        """The same geometry with another parameter set."""
        params = parameters if isinstance(parameters, ParameterSet) else ParameterSet.load(parameters)
        return dataclasses.replace(self, parameters=check_parameter_set(params, self.ligaments, self.source))

    def report(self) -> str:
        """How the knee file became this model: frames, splits, fits and surface representations
        (builds the femoral distance field if it is not built yet)."""
        lines = [f"knee {self.name!r} ({self.source or 'in memory'})", *self.notes]
        lines += [t.describe(self.structures[t.name]) for t in structure_tables()
                  if t.describe is not None and t.name in self.structures]
        for c in self.compartments.values():
            what = (f"explicit sphere, radius {c.sphere_radius * 1e3:.1f} mm, centre "
                    f"({', '.join(f'{v * 1e3:.1f}' for v in c.centre)}) mm" if c.sphere else "femoral mesh surface")
            law = getattr(c.law, "name", DEFAULT_PRESSURE_LAW)
            lines.append(f"{c.name}: {len(c.points)} tibial points ({c.areas.sum() * 1e6:.0f} mm^2) against the "
                         f"{what}; pressure law {law}")
        if self.femur is not None:
            lines += [self.femur.describe(), field_summary(self.femur.field), self.open_edge_note()]
        return "\n".join(lines)

    @property
    def flexion_range_deg(self) -> tuple[float, float] | None:
        """Flexions (deg) the knee's femoral surface is represented for (the distance field covers
        the region the tibia touches over :data:`~kneenlp.model.articular.TOUCHABLE_FLEXION_DEG`);
        None for a knee without a femoral mesh (explicit spheres hold at any flexion)."""
        return TOUCHABLE_FLEXION_DEG if self.femur is not None else None

    def check_flexions(self, trials, source: str | None = None) -> None:
        """Every trial's flexion inside :attr:`flexion_range_deg`: beyond it the tibia touches femoral
        surface the model does not represent (a diagnose at 115 deg would run minutes and fail)."""
        span = self.flexion_range_deg
        if span is None:
            return
        for t in trials:
            if not span[0] <= t.flexion_deg <= span[1]:
                raise InputError(f"trial {t.id!r} at {t.flexion_deg:g} deg flexion: knee {self.name!r} represents its "
                                 f"femoral surface between {span[0]:g} and {span[1]:g} deg only (the distance field "
                                 "covers the region the tibia touches there)", source=source, field="flexion")

    def open_edge_note(self) -> str:
        """Whether the femoral mesh is open where the tibia reaches: the tibial cartilage swept over
        the touchable flexions at the reference pose, points within
        :data:`~kneenlp.model.articular.RIM_GAP` of the surface at its open edge counted."""
        rim = self.femur.rim
        if rim.closed:
            return "femoral mesh: closed (no open edge)"
        R, p = self.reference_transform
        pts = np.vstack([c.points for c in self.compartments.values() if not c.sphere]) @ R.T + p
        n = self.femur.open_edge_reached(swept_tibia(pts, self.axis, np.degrees(self.reference_pose[0])))
        if not n:
            return (f"femoral mesh: open ({len(rim)} edges), but not where the tibia reaches between "
                    f"{TOUCHABLE_FLEXION_DEG[0]:g} and {TOUCHABLE_FLEXION_DEG[1]:g} deg flexion")
        return (f"femoral mesh: open where the tibia reaches ({len(rim)} edges): {n} swept tibial points come within "
                f"{RIM_GAP * 1e3:g} mm of the surface beyond its open edge between {TOUCHABLE_FLEXION_DEG[0]:g} and "
                f"{TOUCHABLE_FLEXION_DEG[1]:g} deg flexion; the surface ends at the edge (the contact weight falls to "
                f"0 across it within a grid spacing), and a trial is noted where more than "
                f"{RIM_SHARE * 100:g} % of a compartment's contact force would come from beyond it")
