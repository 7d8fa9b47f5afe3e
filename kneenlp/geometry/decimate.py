"""Meshes finer than the contact model can use are decimated when a knee is read.

A knee's contact is resolved at the tibial mesh's vertices (its contact points) and through the
femoral distance field, a cubic spline on a grid of ``grid_spacing`` (0.5 mm by default); the
shipped meshes have 8,600-22,300 faces with edges of 0.4-0.9 mm.  A segmentation can give millions
of faces (a 2-million-face femur ran for 300 s in 4.5 GB before it was stopped), nearly all of them
finer than the contact resolves.  A mesh of more than :data:`MAX_MESH_FACES` faces is therefore
decimated (quadric error metric edge collapses, ``fast-simplification``) to the face count of
equilateral triangles with edges of the contact resolution, the grid spacing
(:func:`resolution_faces`), at most :data:`MAX_MESH_FACES`; the knee report says so.  The most
careful collapses come first (``agg = 0``, which stops where the surface would move: 0.2 um on
average on the subdivided default femur), coarser ones only if those leave more than
:data:`SECOND_PASS` times the target.  A binary STL that large is read by a lean reader
(:func:`read_binary_stl`).  A mesh file of more than :data:`MAX_READ_FACES` faces (or, in another
format than binary STL, of more than :data:`MAX_TEXT_MESH_BYTES`) is refused unread: reading and
decimating it would pass the 2 GB bound of a knee load.  The measured effect on contact force and
the time and memory of a load: ``benchmarks/bench_decimation.py`` (docs/inputs.md).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

#: Faces above which a mesh is decimated when read (the shipped meshes have at most 46,500).
MAX_MESH_FACES = 200_000
#: Faces above which a mesh file is refused unread (binary STL: 50 bytes a face, 125 MB): reading
#: and decimating a mesh takes about 700 bytes a face (1.7 GB peak for 2.2 million faces).
MAX_READ_FACES = 2_500_000
#: A first, careful decimation leaving more than this many times the target faces is followed by a
#: second, coarser one to the target.
SECOND_PASS = 2.0
#: Largest mesh file read in another format than binary STL (ASCII STL: about 250 bytes a face).
MAX_TEXT_MESH_BYTES = 100e6
#: Area (in units of the resolution squared) of an equilateral triangle with edges of it.
_EQUILATERAL = math.sqrt(3.0) / 4.0


def read_binary_stl(path: Path, faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64, the file's unit) and faces (int64) of a binary STL of ``faces`` triangles,
    bitwise identical corners merged into one vertex: a lean reader for large files (trimesh's
    takes 1.9 GB for 2 million faces, this one 0.5 GB)."""
    with path.open("rb") as f:
        f.seek(84)
        raw = np.fromfile(f, dtype=np.uint8, count=50 * faces).reshape(faces, 50)
    corners = np.ascontiguousarray(raw[:, 12:48]).view("<f4").reshape(-1, 3)  # 3 corners a face
    del raw
    bits = corners.view(np.uint32)
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))
    sorted_bits = bits[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(sorted_bits[1:] != sorted_bits[:-1], axis=1)
    del sorted_bits
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = np.cumsum(first) - 1
    return corners[order[first]].astype(np.float64), inverse.reshape(-1, 3)


def resolution_faces(mesh: trimesh.Trimesh, resolution: float) -> int:
    """Faces of ``mesh``'s surface in equilateral triangles of edge ``resolution`` (mesh unit)."""
    area = float(mesh.metadata.get("area", mesh.area))  # as read (read_mesh keeps it)
    return math.ceil(area / (_EQUILATERAL * resolution**2))


def decimate(mesh: trimesh.Trimesh, resolution: float) -> tuple[trimesh.Trimesh, str | None]:
    """``mesh`` itself and None when its file had at most :data:`MAX_MESH_FACES` faces
    (``mesh.metadata["faces_read"]``, else its own count), else the mesh decimated to
    ``min(MAX_MESH_FACES, resolution_faces(mesh, resolution))`` faces (``resolution``: the contact
    resolution, mesh unit) and a sentence saying so.  Open edges are kept in place."""
    read = int(mesh.metadata.get("faces_read", len(mesh.faces)))
    if read <= MAX_MESH_FACES:
        return mesh, None
    target = max(1000, min(MAX_MESH_FACES, resolution_faces(mesh, resolution)))
    out = mesh
    if len(mesh.faces) > target:
        from fast_simplification import simplify

        # the most careful collapses first (agg 0 stops where the surface would move: on a smooth mesh
        # within 0.2 um on average, 10 um at most), then, if that left too many faces, coarser ones
        vertices, faces = simplify(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
                                   target_count=target, agg=0.0)
        if len(faces) > SECOND_PASS * target:
            vertices, faces = simplify(vertices, faces, target_count=target, agg=1.0)
        out = trimesh.Trimesh(vertices, faces, process=True)
        out.update_faces(out.nondegenerate_faces())  # collapses can leave slivers of zero area
        out.remove_unreferenced_vertices()
    edges = float(np.mean(out.edges_unique_length))
    return out, (f"{read:,} faces decimated to {len(out.faces):,} (mean edge {edges * 1e3:.2f} mm; contact "
                 f"resolution {resolution * 1e3:g} mm; a mesh of more than {MAX_MESH_FACES:,} faces is reduced so)")
