"""A brute-force shortest path over a triangle mesh: the oracle of :mod:`kneenlp.geometry.taut_path`.

Between two points outside a closed mesh, the shortest path that touches it along a convex patch
runs straight to a tangent point, along the surface's geodesic to a second tangent point and
straight on.  :func:`shortest_over_mesh` takes the mesh near the path, subdivided to ``edge``
(the same polyhedron, finer vertices), and searches the pairs of its vertices near where the path
meets and leaves the surface, each visible from its end (the segment crosses no face): heat-method
distances (potpourri3d) rank every pair, and the exact polyhedral geodesic (potpourri3d's
edge-flip solver, Sharp & Crane 2020) of the best is then improved vertex by vertex over the
neighbouring pairs until none is shorter.  It shares nothing with the taut path's solver but the
mesh: no distance field, no nodes, no Newton.  Lengths in the mesh's unit.
"""

from __future__ import annotations

import numpy as np
import trimesh


def _visible(mesh: trimesh.Trimesh, origin: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Whether the segment from ``origin`` to each target vertex crosses no face short of it
    (Moller-Trumbore on every face; faces touching the target vertex do not count)."""
    tri = np.asarray(mesh.triangles)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = np.ones(len(targets), bool)
    for i, target in enumerate(targets):
        d = target - origin
        h = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, h)
        ok = np.abs(det) > 1e-30
        inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
        sv = origin - v0
        u = inv * np.einsum("ij,ij->i", sv, h)
        q = np.cross(sv, e1)
        v = inv * (q @ d)
        t = inv * np.einsum("ij,ij->i", e2, q)
        hit = ok & (u > 1e-9) & (v > 1e-9) & (u + v < 1 - 1e-9) & (t > 1e-9) & (t < 1 - 1e-7)
        out[i] = not hit.any()
    return out


def shortest_over_mesh(mesh: trimesh.Trimesh, start: np.ndarray, end: np.ndarray, near_start: np.ndarray,
                       near_end: np.ndarray, reach: float, edge: float, crop: float) -> float:
    """The shortest path's length from ``start`` to ``end`` over ``mesh`` (module docstring): tangent
    vertices within ``reach`` of ``near_start`` and ``near_end``, the mesh within ``crop`` of them
    subdivided to ``edge``."""
    import potpourri3d as pp3d

    start, end = np.asarray(start, float), np.asarray(end, float)
    centre = (np.asarray(near_start) + np.asarray(near_end)) / 2
    radius = np.linalg.norm(np.asarray(near_start) - centre) + crop
    keep = np.linalg.norm(mesh.triangles_center - centre, axis=1) < radius
    patch = mesh.submesh([np.flatnonzero(keep)], append=True)
    vertices, faces = trimesh.remesh.subdivide_to_size(patch.vertices, patch.faces, max_edge=edge)
    fine = trimesh.Trimesh(vertices, faces, process=True)
    V, F = np.asarray(fine.vertices), np.asarray(fine.faces)
    a = np.flatnonzero(np.linalg.norm(V - near_start, axis=1) < reach)
    b = np.flatnonzero(np.linalg.norm(V - near_end, axis=1) < reach)
    a, b = a[_visible(fine, start, V[a])], b[_visible(fine, end, V[b])]
    if not len(a) or not len(b):
        raise ValueError("no tangent vertex visible from an end")
    heat = pp3d.MeshHeatMethodDistanceSolver(V, F)
    free_a, free_b = np.linalg.norm(V[a] - start, axis=1), np.linalg.norm(V[b] - end, axis=1)
    approx = np.array([heat.compute_distance(int(i))[b] for i in a])  # |a| x |b|
    total = free_a[:, None] + approx + free_b[None, :]
    i, j = np.unravel_index(np.argmin(total), total.shape)
    flips = pp3d.EdgeFlipGeodesicSolver(V, F)
    neighbours = fine.vertex_neighbors
    visible_a, visible_b = set(a.tolist()), set(b.tolist())

    def exact(p: int, q: int) -> float:
        path = flips.find_geodesic_path(p, q)
        return (float(np.linalg.norm(V[p] - start)) + float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
                + float(np.linalg.norm(V[q] - end)))

    best, p, q = exact(a[i], b[j]), int(a[i]), int(b[j])
    improved = True
    while improved:
        improved = False
        moves = [(n, q) for n in neighbours[p] if n in visible_a] + [(p, n) for n in neighbours[q] if n in visible_b]
        for pp, qq in moves:
            length = exact(pp, qq)
            if length < best - 1e-15:
                best, p, q, improved = length, pp, qq, True
                break
    return best
