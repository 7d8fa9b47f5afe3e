"""The open edges (rim) of a surface mesh: where a cropped or partial surface ends.

A femoral articular surface given as an open mesh (the cartilage's top surface, a cropped implant
component) has edges used by one face only.  Beyond such an edge the signed distance is not a
distance to a surface any more: it is the distance to the edge line, signed by the rim's
pseudo-normal, so a tibial point 4-6 mm past the edge and a little below it counts as
penetrating.  :class:`OpenEdges` finds the rim and measures how far points are from it, so that
contact whose nearest femoral point lies on the rim can be refused (see
:meth:`kneenlp.model.mesh_contact.MeshContact.rim_penetration`).

Lengths are in the mesh's unit (kneenlp: metres).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from kneenlp.geometry.sdf import DistanceField

#: A point is at the open edge when its nearest surface point lies within this many grid spacings
#: of the edge (the spline field rounds the distance there over about a spacing).
RIM_SPACINGS = 1.0
#: Segments looked at per point (nearest by midpoint): rim edges are short and of similar length.
NEAREST_SEGMENTS = 8
#: A one-face edge lies on other edges (a crack, not a rim) when points along it are within this
#: fraction of the longest edge (plus 1e-3 of its own length) of them.
SEALED_TOLERANCE = 1e-6


def nearest_segments(x: np.ndarray, segments: np.ndarray, tree: cKDTree) -> tuple[np.ndarray, np.ndarray]:
    """Distances (N x k) from points ``x`` (N x 3) to the ``k`` segments (n x 2 x 3) whose midpoints
    (``tree``) are nearest, and those segments' indices (N x k)."""
    k = min(NEAREST_SEGMENTS, len(segments))
    _, idx = tree.query(x, k)
    idx = np.reshape(idx, (len(x), k))
    a, b = segments[idx, 0], segments[idx, 1]  # N x k x 3
    ab = b - a
    t = np.clip(np.einsum("nkj,nkj->nk", x[:, None] - a, ab) / np.maximum(np.einsum("nkj,nkj->nk", ab, ab), 1e-300),
                0.0, 1.0)
    return np.linalg.norm(a + t[..., None] * ab - x[:, None], axis=2), idx


def sealed(edges: np.ndarray, rim: np.ndarray) -> np.ndarray:
    """Which one-face edges ``edges[rim]`` (``edges``: every edge of the mesh, n x 2 x 3) are no rim:
    of zero length (a face with a repeated vertex), or lying along other edges (a T-junction, where
    a vertex sits on the edge of the next face, or the sides of a zero-area face: the surface goes
    on across them).  Tested at a quarter, half and three quarters of each edge, against the edges
    whose midpoints are nearest."""
    if not len(rim):
        return np.zeros(0, dtype=bool)
    a, b = edges[rim, 0], edges[rim, 1]
    length = np.linalg.norm(b - a, axis=1)
    tol = SEALED_TOLERANCE * max(float(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1).max()), 1e-300)
    tree = cKDTree(edges.mean(axis=1))
    covered = np.ones(len(rim), dtype=bool)
    for f in (0.25, 0.5, 0.75):
        d, idx = nearest_segments(a + f * (b - a), edges, tree)
        d[idx == rim[:, None]] = np.inf  # not itself
        covered &= d.min(axis=1) <= tol + 1e-3 * length
    return (length <= tol) | covered


class OpenEdges:
    """The edges of ``mesh`` used by one face, moved outward by ``offset`` along the vertex normals
    (the represented surface is ``offset`` outside the mesh, :class:`~kneenlp.geometry.sdf.
    DistanceField`)."""

    def __init__(self, mesh: trimesh.Trimesh, offset: float = 0.0):
        # an edge is the key a * n + b (a < b): a 1-D unique, ~10x faster than unique(axis=0), same order
        n = len(mesh.vertices)
        edges = np.asarray(mesh.edges_sorted, dtype=np.int64)
        keys, counts = np.unique(edges[:, 0] * n + edges[:, 1], return_counts=True)
        pairs = np.column_stack([keys // n, keys % n])
        one_face = np.flatnonzero(counts == 1)
        vertices = np.asarray(mesh.vertices, float)
        rim = pairs[one_face[~sealed(vertices[pairs], one_face)]]
        vertices = vertices + offset * np.asarray(mesh.vertex_normals, float)
        #: rim segments (n x 2 x 3)
        self.segments = vertices[rim]
        self._tree = cKDTree(self.segments.mean(axis=1)) if len(rim) else None
        #: half the longest segment (a point within ``r`` of a segment is within ``r + reach`` of its midpoint)
        lengths = np.linalg.norm(self.segments[:, 1] - self.segments[:, 0], axis=1)
        self.reach = 0.5 * float(lengths.max()) if len(rim) else 0.0

    @property
    def closed(self) -> bool:
        """True when the mesh has no open edge (a watertight surface)."""
        return self._tree is None

    def __len__(self) -> int:
        return len(self.segments)

    def distance(self, points: np.ndarray, upper: float = np.inf) -> np.ndarray:
        """Distance (N,) from every point (N x 3) to the nearest rim segment (inf without a rim);
        with ``upper``, inf for points farther than ``upper`` from every segment (one cheap nearest
        midpoint query passes them over)."""
        x = np.asarray(points, float).reshape(-1, 3)
        out = np.full(len(x), np.inf)
        if self._tree is None or not len(x):
            return out
        if np.isfinite(upper):
            near, _ = self._tree.query(x, 1, distance_upper_bound=upper + self.reach)
            close = np.isfinite(near)
            out[close] = self.distance(x[close])
            return np.where(out <= upper, out, np.inf)
        return nearest_segments(x, self.segments, self._tree)[0].min(axis=1)


def at_open_edge(field: DistanceField, rim: OpenEdges, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d, mask)`` for points (N x 3, the field's frame): the field's signed distance and whether
    the nearest surface point (reached along the field's gradient) lies on the open edge, within
    :data:`RIM_SPACINGS` grid spacings of it.  There ``d`` measures the distance to the edge, not
    to a surface: a negative one is no penetration."""
    x = np.asarray(points, float).reshape(-1, 3)
    d, g = field.evaluate(x, order=1)
    if rim.closed:
        return d, np.zeros(len(x), dtype=bool)
    norm = np.linalg.norm(g, axis=1)
    n = np.divide(g, norm[:, None], out=np.zeros_like(g), where=norm[:, None] > 0)
    reach = RIM_SPACINGS * field.spacing
    return d, (norm > 0) & (rim.distance(x - d[:, None] * n, upper=reach) <= reach)
