"""Exact signed distance from points to a triangle mesh (the brute-force reference of contact).

``signed_distance(mesh, points)`` finds, for every point, the closest point on the mesh with a
*certified* candidate search: the ``k`` triangles whose centroids are nearest, plus the few
unusually large triangles; the answer is accepted only when no triangle outside the candidates can
be closer (the ``k``-th centroid distance minus the largest triangle radius is at least the best
distance found), otherwise ``k`` grows fourfold and finally every triangle is searched.  The
point-triangle distances are trimesh's (``trimesh.triangles.closest_point``), computed in units of
the mesh's median edge length: that routine compares barycentric quantities with an absolute
tolerance (1e-13) meant for unit-sized triangles, and on sub-millimetre triangles given in metres
it returns wrong closest points for more than half of the points (by up to 0.33 mm on the Lenhart
femur; found while building the implant knee).

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


def _pseudo_normals(mesh: trimesh.Trimesh, tris: np.ndarray, face: np.ndarray, closest: np.ndarray) -> np.ndarray:
    """Normal deciding the sign at ``closest`` on ``face`` (of triangles ``tris``, the mesh's in any
    unit): the face normal inside the face, the barycentric blend of the vertex normals on its
    edges and vertices."""
    normal = np.array(mesh.face_normals[face], dtype=float)
    bary = _triangles.points_to_barycentric(tris[face], closest)
    edge = bary.min(axis=1) < 1e-6
    if np.any(edge):
        b = np.clip(bary[edge], 0, None)
        b /= b.sum(axis=1, keepdims=True)
        blend = np.einsum("ij,ijk->ik", b, mesh.vertex_normals[mesh.faces[face[edge]]])
        length = np.linalg.norm(blend, axis=1)
        ok = length > 1e-12  # opposed vertex normals (a fold) blend to nothing: keep the face normal there
        rows = np.flatnonzero(edge)[ok]
        normal[rows] = blend[ok] / length[ok, None]
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
        #: lengths are handled in units of the median edge (see module docstring)
        self.unit = float(np.median(mesh.edges_unique_length)) or 1.0
        self.tris = np.asarray(mesh.triangles, dtype=float) / self.unit
        cen = self.tris.mean(axis=1)
        rad = np.linalg.norm(self.tris - cen[:, None, :], axis=2).max(axis=1)
        self.r_small = float(np.percentile(rad, 99.99))
        self.big = np.flatnonzero(rad > self.r_small)
        self.small = np.flatnonzero(rad <= self.r_small)
        self.tree = cKDTree(cen[self.small])
        self.vertex_tree = cKDTree(np.asarray(mesh.vertices) / self.unit)
        self.r_max = float(rad.max())

    def lower_bound(self, points: np.ndarray) -> np.ndarray:
        """A lower bound of the unsigned distance (cheap): nearest vertex minus the largest
        triangle circumradius (used to skip points that cannot be near the surface)."""
        pts = np.asarray(points, float).reshape(-1, 3) / self.unit
        return (self.vertex_tree.query(pts)[0] - self.r_max) * self.unit

    def __call__(self, points: np.ndarray, k: int = 24, certify: bool = True,
                 chunk: int = 20000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(d, closest, normal)``: signed distance (N,), closest points (N, 3) and the unit
        gradient of ``d`` (N, 3; the direction from the closest point, or the face normal when the
        point lies on the mesh).  ``certify=False`` keeps the first ``k``-candidate answer (fast;
        exact unless a far larger triangle is closer)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3) / self.unit
        n = len(pts)
        closest, face, dist = np.empty((n, 3)), np.empty(n, dtype=np.int64), np.empty(n)
        for s in range(0, n, chunk):
            q = pts[s : s + chunk]
            todo = np.arange(len(q))
            kk = min(k, len(self.small))
            while len(todo):
                dk, ik = self.tree.query(q[todo], kk, workers=-1)
                ik, dk = self.small[np.reshape(ik, (len(todo), -1))], np.reshape(dk, (len(todo), -1))
                cand = np.hstack([ik, np.broadcast_to(self.big, (len(todo), len(self.big)))])
                c, f, dd = _closest_of(self.tris, q[todo], cand)
                closest[s + todo], face[s + todo], dist[s + todo] = c, f, dd
                if not certify or kk >= len(self.small):
                    break
                todo = todo[dk[:, -1] - self.r_small < dd]
                kk = min(4 * kk, len(self.small))
        normal = _pseudo_normals(self.mesh, self.tris, face, closest)
        sign = np.where(np.einsum("ij,ij->i", pts - closest, normal) < 0, -1.0, 1.0)
        d = sign * dist
        grad = normal.copy()
        away = dist > 1e-9
        grad[away] = (pts[away] - closest[away]) / d[away, None]
        return d * self.unit, closest * self.unit, grad


def signed_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact signed distance of ``points`` to ``mesh``: ``(d, closest, gradient)`` (see
    :class:`MeshDistance`)."""
    return MeshDistance(mesh)(points)


def winding_number(mesh: trimesh.Trimesh, points: np.ndarray, chunk: int = 500_000) -> np.ndarray:
    """Generalised winding number (N,) of ``mesh`` around ``points`` (N x 3, the mesh's unit): the
    solid angle the surface subtends, over 4 pi (van Oosterom and Strackee 1983).  1 inside and 0
    outside a closed mesh with outward normals; an open mesh (a cropped bone, a cartilage sheet)
    jumps by 1 across its surface and is fractional elsewhere, so ``> 0.5`` still tells a point the
    surface encloses (below a cropped bone's articular surface: 97 % of points 5 mm deep on the
    default knee's subchondral bone) but not one it merely faces (an intercondylar notch, a point
    under a cartilage sheet).  Work: N x faces triangle evaluations, ``chunk`` at a time."""
    tris = np.asarray(mesh.triangles, dtype=float)
    x = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.zeros(len(x))
    per = max(1, chunk // max(len(x), 1))
    for s in range(0, len(tris), per):
        t = tris[None, s:s + per] - x[:, None, None, :]  # N x f x 3 x 3
        a, b, c = t[..., 0, :], t[..., 1, :], t[..., 2, :]
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        det = np.einsum("...j,...j->...", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("...j,...j->...", a, b) * lc + np.einsum("...j,...j->...", b, c) * la
               + np.einsum("...j,...j->...", c, a) * lb)
        out += 2.0 * np.arctan2(det, den).sum(axis=1)
    return out / (4.0 * np.pi)
