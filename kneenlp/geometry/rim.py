"""The open edges (rim) of a surface mesh: where a cropped or partial surface ends.

A femoral articular surface given as an open mesh (the cartilage's top surface, a cropped implant
component) has edges used by one face only.  Beyond such an edge the signed distance is not a
distance to a surface any more: it is the distance to the edge line, signed by the rim's
pseudo-normal, so a tibial point 4-6 mm past the edge and a little below it would count as
penetrating.  The surface ends where the mesh ends: :class:`OpenEdges` finds the rim and measures
how far points are from it, and :func:`rim_weights` gives the grid nodes of the distance field a
weight that multiplies the contact pressure (:attr:`kneenlp.geometry.sdf.DistanceField.weights`):
1 on the surface, falling to 0 across the rim within a grid spacing, 0 beyond it.

Lengths are in the mesh's unit (kneenlp: metres).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

#: Nodes within this many grid spacings of the rim take their weight from their lateral position
#: (:func:`rim_weights`); farther ones are on the surface (1) or beyond the rim (0).
WEIGHT_REACH = 3.0
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
        rim_keys = one_face[~sealed(vertices[pairs], one_face)]
        rim = pairs[rim_keys]
        vertices = vertices + offset * np.asarray(mesh.vertex_normals, float)
        #: rim segments (n x 2 x 3)
        self.segments = vertices[rim]
        #: per segment, the unit direction in the surface, across the segment, into its face (n x 3)
        self.inward = self._inward(mesh, vertices, n, keys[rim_keys])
        self._tree = cKDTree(self.segments.mean(axis=1)) if len(rim) else None
        #: half the longest segment (a point within ``r`` of a segment is within ``r + reach`` of its midpoint)
        lengths = np.linalg.norm(self.segments[:, 1] - self.segments[:, 0], axis=1)
        self.reach = 0.5 * float(lengths.max()) if len(rim) else 0.0

    def _inward(self, mesh: trimesh.Trimesh, vertices: np.ndarray, n: int, keys: np.ndarray) -> np.ndarray:
        """The unit vectors across each rim segment into its one face (the face's third vertex
        less its part along the segment)."""
        if not len(keys):
            return np.zeros((0, 3))
        sorted_edges = np.asarray(mesh.edges_sorted, dtype=np.int64)
        order = np.argsort(sorted_edges[:, 0] * n + sorted_edges[:, 1], kind="stable")
        row = order[np.searchsorted((sorted_edges[:, 0] * n + sorted_edges[:, 1])[order], keys)]
        faces = np.asarray(mesh.faces, dtype=np.int64)[np.asarray(mesh.edges_face)[row]]
        a, b = self.segments[:, 0], self.segments[:, 1]
        third = vertices[faces.sum(axis=1) - sorted_edges[row].sum(axis=1)]  # the face's vertex off the edge
        t = (b - a) / np.maximum(np.linalg.norm(b - a, axis=1), 1e-300)[:, None]
        u = third - a
        u -= np.einsum("ij,ij->i", u, t)[:, None] * t
        return u / np.maximum(np.linalg.norm(u, axis=1), 1e-300)[:, None]

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
        return self.nearest(x)[0]

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (N,) from every point (N x 3) to its nearest rim segment, and that segment's
        index (N,); the mesh must have a rim."""
        d, idx = nearest_segments(np.asarray(points, float).reshape(-1, 3), self.segments, self._tree)
        best = np.argmin(d, axis=1)
        rows = np.arange(len(d))
        return d[rows, best], idx[rows, best]


def rim_weights(rim: OpenEdges, nodes: np.ndarray, unsigned: np.ndarray, spacing: float) -> np.ndarray:
    """Contact weight (N,) of grid ``nodes`` (N x 3) whose distance to the represented surface is
    ``unsigned`` (N,), for a grid of ``spacing``: the nodes within :data:`WEIGHT_REACH` spacings of
    the rim take ``clip(1/2 + lam / spacing, 0, 1)``, ``lam`` their position across the nearest rim
    segment (positive into the surface, :attr:`OpenEdges.inward`), so the weight falls from 1 to 0
    over the spacing centred on the rim; the others are 1 where their nearest surface point is inside
    the surface, 0 where it is on the rim (the node is then as far from the rim as from the surface)."""
    x = np.asarray(nodes, float).reshape(-1, 3)
    w = np.ones(len(x))
    if rim.closed or not len(x):
        return w
    reach = WEIGHT_REACH * spacing
    for start in range(0, len(x), 200_000):  # bounded memory: k segments a node
        part = slice(start, start + 200_000)
        e, seg = rim.nearest(x[part])
        a, b = rim.segments[seg, 0], rim.segments[seg, 1]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", x[part] - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1)
        lam = np.einsum("ij,ij->i", x[part] - (a + t[:, None] * ab), rim.inward[seg])
        near = e <= reach
        out = np.where(e - unsigned[part] <= 0.25 * spacing, 0.0, 1.0)
        out[near] = np.clip(0.5 + lam[near] / spacing, 0.0, 1.0)
        w[part] = out
    return w
