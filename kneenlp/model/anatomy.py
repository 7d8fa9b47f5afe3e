"""Cartilage surfaces of the synthetic example knee (``Knee.named("synthetic")``), built with trimesh.

The synthetic knee is a right knee in the ISB femoral frame (X anterior, Y proximal, Z lateral, mm,
origin on the flexion axis midway between the condyle centres).  Its dimensions and their sources
are listed in ``docs/research/anatomy-sources.md``; this module only turns them into meshes:

* femoral cartilage of each condyle: an explicit sphere of the knee file (the condyle's
  flexion-facet circle, Iwaki et al. 2000), centred on the flexion axis; :func:`condyle_mesh`
  tessellates its distal-posterior part for pictures;
* tibial cartilage of each plateau: an elliptical patch of the surface
  ``y = y0 + x^2 / (2 R_sag) + z^2 / (2 R_cor)`` (concave for positive radii) whose lowest point
  touches the condyle in the reference pose.

Run ``python -m kneenlp.model.anatomy DIR`` to (re)write the tibial STL files of the synthetic knee.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from kneenlp.base.atomic import export_mesh_atomic


@dataclass(frozen=True)
class Compartment:
    """Dimensions of one compartment (mm)."""

    name: str
    condyle_z: float  # medio-lateral position of the condyle sphere centre
    condyle_radius: float
    plateau_x: float  # antero-posterior centre of the plateau patch
    plateau_half_ap: float
    plateau_half_ml: float
    radius_sagittal: float  # > 0 concave; use a large value for flat
    radius_coronal: float


DEFAULT_COMPARTMENTS = (
    Compartment("medial", -21.0, 22.0, -2.0, 23.0, 14.0, 90.0, 55.0),
    Compartment("lateral", 21.0, 21.0, -3.0, 20.0, 14.0, 400.0, 70.0),
)


def condyle_mesh(c: Compartment, subdivisions: int = 4) -> trimesh.Trimesh:
    """Femoral cartilage of one condyle: the distal-posterior part of a sphere (mm)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=c.condyle_radius)
    v = sphere.vertices
    keep_v = (v[:, 1] < -0.2 * c.condyle_radius) & (v[:, 0] < 0.7 * c.condyle_radius)
    keep_f = keep_v[sphere.faces].all(axis=1)
    mesh = trimesh.Trimesh(v, sphere.faces[keep_f], process=True)
    mesh.remove_unreferenced_vertices()
    mesh.apply_translation([0.0, 0.0, c.condyle_z])
    return mesh


def plateau_mesh(c: Compartment, spacing: float = 1.0) -> trimesh.Trimesh:
    """Tibial cartilage of one plateau: an elliptical patch of a doubly curved surface (mm).

    The surface's lowest point lies under the condyle centre (``x = 0``) at ``y = -R_condyle``,
    so that condyle and plateau just touch in the reference pose.
    """
    xs = np.arange(-c.plateau_half_ap, c.plateau_half_ap + 1e-9, spacing) + c.plateau_x
    zs = np.arange(-c.plateau_half_ml, c.plateau_half_ml + 1e-9, spacing) + c.condyle_z
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    dx, dz = gx, gz - c.condyle_z
    gy = -c.condyle_radius + dx**2 / (2 * c.radius_sagittal) + dz**2 / (2 * c.radius_coronal)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    nx, nz = gx.shape
    idx = np.arange(nx * nz).reshape(nx, nz)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    cc, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.vstack([np.column_stack([a, d, b]), np.column_stack([b, d, cc])])  # normals +Y
    inside = ((gx - c.plateau_x) / c.plateau_half_ap) ** 2 + (dz / c.plateau_half_ml) ** 2 <= 1.0
    keep_f = inside.ravel()[faces].all(axis=1)
    mesh = trimesh.Trimesh(vertices, faces[keep_f], process=True)
    mesh.remove_unreferenced_vertices()
    return mesh


def write_default_meshes(directory: Path) -> list[Path]:
    """Write the synthetic knee's two tibial cartilage STL files into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for c in DEFAULT_COMPARTMENTS:
        path = directory / f"tibia_{c.name}.stl"
        export_mesh_atomic(plateau_mesh(c), path)
        written.append(path)
    return written


if __name__ == "__main__":  # pragma: no cover - maintenance script
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("kneenlp/resources/knees/synthetic/meshes")
    for p in write_default_meshes(out):
        print(p)
