"""The articular surfaces of a knee file: tibial compartments and the femoral surface.

The ``[contact]`` table of a knee file (lengths in the file's unit) names::

    [contact]
    femur = "femur.stl"          # femoral articular surface, both condyles in one mesh ...
    femur_offset = 2.0           # ... or the bone under it, the articular surface this far outside
    tibia = "tibia.stl"          # tibial cartilage of both plateaus: split automatically ...
    [contact.medial]             # ... or one table per compartment
    tibia = "tibia_medial.stl"
    femur = "femur_medial.stl"   # optional: femoral meshes of all compartments form one surface
    sphere_center = [0, 0, -21]  # an explicit analytic sphere instead of the femoral mesh
    sphere_radius = 22.0

plus ``gate`` (width of the contact gate), ``grid_spacing`` (of the femoral distance field) and,
for explicit spheres, ``working_set`` (points per compartment and trial, 0: every point).  A
sphere is only ever used where the file asks for one; a femoral mesh is always represented as
itself (:mod:`kneenlp.model.mesh_contact`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh

from kneenlp.base.errors import InputError
from kneenlp.geometry.axes import CondyleSplit, FlexionAxis, split_plateaus, sweep, touchable_box
from kneenlp.geometry.distance import vertex_areas
from kneenlp.geometry.rim import OpenEdges
from kneenlp.geometry.sdf import DistanceField, cached_field

log = logging.getLogger("kneenlp")

#: Flexions (deg) over which the tibia is swept to find the femoral surface it can touch.
TOUCHABLE_FLEXION_DEG = (-5.0, 100.0)
#: Gap (m) within which a swept tibial point counts as reaching the femoral surface (the knee
#: report's check of open edges, :meth:`FemoralSurface.open_edge_reached`).
RIM_GAP = 0.5e-3


@dataclass(frozen=True)
class Compartment:
    """One tibiofemoral compartment (SI): its tibial cartilage and the femoral condyle above it.

    ``centre`` is the condyle centre in the femoral frame (the explicit sphere's centre, else the
    centre of the cylinder fitted to the condyle); ``sphere_radius`` is set only for a compartment
    whose femoral surface the knee file gives as an explicit sphere around ``centre``."""

    name: str
    tibia_mesh: trimesh.Trimesh  # tibial frame, m (:func:`sampled_plateau` of the file's mesh)
    points: np.ndarray  # tibial sample points (N x 3, tibial frame, m): the mesh vertices
    areas: np.ndarray  # area lumped to each point (N,), m^2
    centre: np.ndarray
    sphere_radius: float | None = None
    #: the compartment's pressure law (:class:`~kneenlp.model.laws.PressureLaw`; None: the paper's)
    law: object = None

    @property
    def sphere(self) -> bool:
        return self.sphere_radius is not None


@dataclass
class FemoralSurface:
    """The femoral articular surface: ``mesh`` (femoral frame, m) moved outward by ``offset`` (m;
    the cartilage thickness when the mesh is the subchondral bone), represented by a distance
    field with ``spacing`` (m) over ``box`` (the part the tibia can touch, 2 x 3, m)."""

    mesh: trimesh.Trimesh
    offset: float
    spacing: float
    box: np.ndarray
    sources: list[str] = field(default_factory=list)
    #: for a thin closed shell (a segmented cartilage), its articular faces (bool per face): the field
    #: is the depth below them (:mod:`kneenlp.geometry.shell`); None for a bone or an open surface
    articular: np.ndarray | None = None

    @cached_property
    def field(self) -> DistanceField:
        """The distance field, built once per surface and kept in the on-disk cache."""
        return cached_field(self.mesh, self.box, progress=log.info, articular=self.articular, spacing=self.spacing,
                            offset=self.offset)

    @cached_property
    def rim(self) -> OpenEdges:
        """The open edges of the represented surface (none for a watertight mesh)."""
        return OpenEdges(self.mesh, self.offset)

    def open_edge_reached(self, swept: np.ndarray) -> int:
        """How many of the ``swept`` tibial points (femoral frame, m) lie within :data:`RIM_GAP` of
        the surface (either side) beyond its open edge (the field's rim weight below a half, which
        it is at the edge; 0 for a watertight mesh)."""
        weight = self.field.weight_spline
        if weight is None:
            return 0
        lo, hi = self.field.bounds
        x = swept[np.all((swept >= lo) & (swept <= hi), axis=1)]
        x = x[np.abs(self.field.evaluate(x)[0]) < RIM_GAP]  # compiled, no derivatives
        return int(np.count_nonzero(weight.evaluate(x)[0] < 0.5))

    def describe(self) -> str:
        what = (f"{' + '.join(self.sources) or 'mesh'} ({len(self.mesh.faces)} faces)"
                + (f", articular surface {self.offset * 1e3:g} mm outside it" if self.offset else "")
                + (f", a closed cartilage shell {2e3 * abs(self.mesh.volume) / self.mesh.area:.1f} mm thick on "
                   f"average: depth is measured below its articular side ({int(self.articular.sum())} faces not "
                   "facing the flexion axis)" if self.articular is not None else ""))
        lo, hi = self.box * 1e3
        return (f"femoral surface: {what}; distance field on a {self.spacing * 1e3:g} mm grid over "
                f"[{lo[0]:.0f}, {hi[0]:.0f}] x [{lo[1]:.0f}, {hi[1]:.0f}] x [{lo[2]:.0f}, {hi[2]:.0f}] mm "
                "(the region the tibia can touch between -5 and 100 deg flexion)")


def field_summary(fld: DistanceField) -> str:
    """How well the field represents the exact surface (from its build check)."""
    i = fld.info
    cached = " (read from the cache)" if "cached" in i else ""
    return (f"distance-field error against exact distances in the touchable region: RMS "
            f"{i.get('error_rms_um', float('nan')):.1f} um, max {i.get('error_max_um', float('nan')):.1f} um "
            f"({i.get('checked_points', 0)} points within the band){cached}")


def split_tibia(mesh: trimesh.Trimesh, lateral: np.ndarray) -> tuple[dict[str, trimesh.Trimesh], dict, str]:
    """Split a tibial cartilage mesh holding both plateaus (:func:`split_plateaus`): the medial and
    lateral sub-meshes, their vertex indices in ``mesh`` and how the split was made."""
    parts, how = split_plateaus(mesh, lateral)
    meshes = {}
    for name, idx in parts.items():
        keep = np.zeros(len(mesh.vertices), dtype=bool)
        keep[idx] = True
        faces = np.flatnonzero(keep[mesh.faces].all(axis=1))
        meshes[name] = mesh.submesh([faces], append=True)
    return meshes, parts, how


#: Largest median edge (m) of a tibial cartilage mesh whose vertices sample contact as they are, and
#: the longest edge (m) of one refined.  Contact acts at the vertices, and the force of a vertex
#: starts within the gate (0.01 mm): on a coarse plateau the contact sum changes by steps as vertices
#: enter the patch one by one, so the equilibria of a load ramp (and a fit's objective) ripple and
#: Newton stalls between them (S192803, median edge 1.8 mm: the objective along a stiffness changed
#: by up to 0.4 % between values 0.5 % apart; refined to 1 mm edges it is smooth and monotone).  The
#: shipped default, synthetic and implant knees (0.77, 1.01, 0.91 mm) are sampled as they are.
COARSE_EDGE = 1.25e-3
SAMPLE_EDGE = 1e-3


def sampled_plateau(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` (m) itself, or where its median edge exceeds :data:`COARSE_EDGE`, its triangles split
    in their planes until no edge exceeds :data:`SAMPLE_EDGE` (the same surface, the same area)."""
    if float(np.median(mesh.edges_unique_length)) <= COARSE_EDGE:
        return mesh
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=SAMPLE_EDGE)
    return trimesh.Trimesh(vertices, faces, process=True)


def tibial_samples(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Sample points (the vertices, m) and their lumped areas (m^2) of tibial cartilage (a mesh
    already :func:`sampled_plateau`)."""
    return np.asarray(mesh.vertices, dtype=float), vertex_areas(mesh)


def swept_tibia(tibia_points: np.ndarray, axis: FlexionAxis | None, reference_flexion_deg: float = 0.0) -> np.ndarray:
    """The tibial points (femoral frame, at the reference pose of flexion ``reference_flexion_deg``)
    flexed about the fitted flexion axis, or about the frame's Z axis through the origin without
    one, over :data:`TOUCHABLE_FLEXION_DEG` (:func:`~kneenlp.geometry.axes.sweep`)."""
    point = axis.point if axis is not None else np.zeros(3)
    direction = axis.direction if axis is not None else np.array([0.0, 0.0, 1.0])
    lo, hi = TOUCHABLE_FLEXION_DEG
    return sweep(tibia_points, point, direction, (lo - reference_flexion_deg, hi - reference_flexion_deg))


def femoral_box(femur: trimesh.Trimesh, tibia_points: np.ndarray, axis: FlexionAxis | None,
                reference_flexion_deg: float = 0.0) -> np.ndarray:
    """The region of the femoral surface the tibia can touch (femoral frame):
    :func:`~kneenlp.geometry.axes.touchable_box` of the :func:`swept_tibia` points."""
    return touchable_box(femur.vertices, swept_tibia(tibia_points, axis, reference_flexion_deg))


@dataclass
class Geometry:
    """What the contact section of a knee file became, with the sentences that report it."""

    compartments: dict[str, Compartment]
    femur: FemoralSurface | None
    axis: FlexionAxis | None
    split: CondyleSplit | None
    notes: list[str]


def mesh_path(base: Path, value: object, source: str, fld: str) -> Path:
    if not isinstance(value, str) or not value:
        raise InputError(f"expected a mesh file name, got {value!r}", source=source, field=fld)
    return base / value
