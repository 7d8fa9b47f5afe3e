"""Exact signed distance from points to a triangle mesh (the brute-force reference of contact).

``signed_distance(mesh, points)`` finds, for every point, the closest point on the mesh with a
*certified* candidate search: the ``k`` triangles whose centroids are nearest, plus the few
unusually large triangles; the answer is accepted only when no triangle outside the candidates can
be closer (the ``k``-th centroid distance minus the largest triangle radius is at least the best
distance found), otherwise ``k`` grows fourfold and finally every triangle is searched.  The
point-triangle distances are trimesh's (``trimesh.triangles.closest_point``).  We do not use
``trimesh.proximity.closest_point``: on the Lenhart 2015 femoral meshes it returned a farther
point than the closest one for about one point in six, by up to 39 um
(``docs/research/mesh-contact-representation.md``).

Sign: negative behind the mesh's outward normals (inside the body).  At the closest point the
normal is the face normal, or the barycentric blend of vertex normals when the closest point lies
on an edge or a vertex (robust there).  Lengths are in the mesh's unit (kneenlp: metres).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from trimesh import triangles as _triangles


def vertex_areas(mesh: trimesh.Trimesh) -> np.ndarray:
    """Area lumped to every vertex: a third of each adjacent face (mesh unit squared)."""
    a = np.zeros(len(mesh.vertices))
    np.add.at(a, mesh.faces.ravel(), np.repeat(mesh.area_faces / 3.0, 3))
    return a


def _pseudo_normals(mesh: trimesh.Trimesh, face: np.ndarray, closest: np.ndarray) -> np.ndarray:
    """Normal deciding the sign at ``closest`` on ``face``: the face normal inside the face, the
    barycentric blend of the vertex normals on its edges and vertices."""
    normal = np.array(mesh.face_normals[face], dtype=float)
    bary = _triangles.points_to_barycentric(mesh.triangles[face], closest)
    edge = bary.min(axis=1) < 1e-6
    if np.any(edge):
        b = np.clip(bary[edge], 0, None)
        b /= b.sum(axis=1, keepdims=True)
        blend = np.einsum("ij,ijk->ik", b, mesh.vertex_normals[mesh.faces[face[edge]]])
        normal[edge] = blend / np.linalg.norm(blend, axis=1, keepdims=True)
    return normal


def _closest_of(tris: np.ndarray, q: np.ndarray, cand: np.ndarray):
    """Closest point of each ``q`` (n, 3) among the candidate triangles ``cand`` (n, k)."""
    n, k = cand.shape
    c = _triangles.closest_point(tris[cand.ravel()], np.repeat(q, k, axis=0)).reshape(n, k, 3)
    dist = np.linalg.norm(c - q[:, None, :], axis=2)
    j = dist.argmin(axis=1)
    r = np.arange(n)
    return c[r, j], cand[r, j], dist[r, j]


class MeshDistance:
    """Signed distances to one mesh; the search structures are built once (see module docstring)."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.mesh = mesh
        self.tris = np.asarray(mesh.triangles, dtype=float)
        cen = self.tris.mean(axis=1)
        rad = np.linalg.norm(self.tris - cen[:, None, :], axis=2).max(axis=1)
        self.r_small = float(np.percentile(rad, 99.99))
        self.big = np.flatnonzero(rad > self.r_small)
        self.small = np.flatnonzero(rad <= self.r_small)
        self.tree = cKDTree(cen[self.small])

    def __call__(self, points: np.ndarray, k: int = 24, certify: bool = True,
                 chunk: int = 20000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(d, closest, normal)``: signed distance (N,), closest points (N, 3) and the unit
        gradient of ``d`` (N, 3; the direction from the closest point, or the face normal when the
        point lies on the mesh).  ``certify=False`` keeps the first ``k``-candidate answer (fast;
        exact unless a far larger triangle is closer)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        n = len(pts)
        closest, face, dist = np.empty((n, 3)), np.empty(n, dtype=np.int64), np.empty(n)
        for s in range(0, n, chunk):
            q = pts[s : s + chunk]
            todo = np.arange(len(q))
            kk = min(k, len(self.small))
            while len(todo):
                dk, ik = self.tree.query(q[todo], kk)
                ik, dk = self.small[np.reshape(ik, (len(todo), -1))], np.reshape(dk, (len(todo), -1))
                cand = np.hstack([ik, np.broadcast_to(self.big, (len(todo), len(self.big)))])
                c, f, dd = _closest_of(self.tris, q[todo], cand)
                closest[s + todo], face[s + todo], dist[s + todo] = c, f, dd
                if not certify or kk >= len(self.small):
                    break
                todo = todo[dk[:, -1] - self.r_small < dd]
                kk = min(4 * kk, len(self.small))
        normal = _pseudo_normals(self.mesh, face, closest)
        sign = np.where(np.einsum("ij,ij->i", pts - closest, normal) < 0, -1.0, 1.0)
        d = sign * dist
        grad = normal.copy()
        away = dist > 1e-12
        grad[away] = (pts[away] - closest[away]) / d[away, None]
        return d, closest, grad


def signed_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact signed distance of ``points`` to ``mesh``: ``(d, closest, gradient)`` (see
    :class:`MeshDistance`)."""
    return MeshDistance(mesh)(points)
