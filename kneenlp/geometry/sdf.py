"""A smooth signed-distance field of a surface: a narrow band on a grid, as a tricubic B-spline.

The femoral articular surface enters the contact model through its signed distance ``d(x)``
(metres, negative inside the femur).  :class:`DistanceField` stores the exact distance to a mesh
(optionally to its outward offset ``{x : d_mesh(x) = offset}``, e.g. subchondral bone plus the
cartilage thickness, which needs no offset mesh that could fold) at the nodes of a regular grid,
clipped to the band ``-depth <= d <= band``, and interpolates it with a cubic B-spline
(``scipy.ndimage.spline_filter`` coefficients): C2 everywhere, so Newton and exact-Hessian IPOPT
see continuous first and second derivatives.  Its error against the exact distance is measured
when it is built (:attr:`DistanceField.info`) and reported with the knee.

Evaluation is NumPy (:meth:`DistanceField.evaluate`: value, gradient and Hessian at many points
at once); the contact element expands it to second order around each contact point's current
position (:mod:`kneenlp.model.mesh_contact`).  Outside the grid and more than ``band`` outside
the surface the field is the constant ``band`` (no contact).

Build once per surface and keep: :func:`cached_field` stores fields on disk keyed by a hash of the
mesh and the settings (``$KNEENLP_CACHE`` or the user cache directory).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh
from scipy.ndimage import spline_filter
from scipy.spatial import cKDTree

from kneenlp.base.atomic import atomic_target
from kneenlp.base.cache import cache_dir
from kneenlp.geometry.distance import MeshDistance
from kneenlp.geometry.rim import OpenEdges, rim_weights
from kneenlp.geometry.shell import ShellDistance
from kneenlp.geometry.spline_kernels import cell_lower_bound, field_derivatives, field_values

#: Bump when the stored format or the construction changes (old cache entries are then rebuilt).
FORMAT_VERSION = 5


#: Peak memory per grid node while a field is built (bytes): node coordinates, distances, the
#: clipped values, the spline coefficients and scipy's work array.
BYTES_PER_NODE = 80
#: Largest field built (bytes): the issue-24 bound of 2 GB for a knee load, with room for the rest.
MAX_FIELD_BYTES = 1.5e9


#: Samples of a mesh's surface the grid nodes are first sorted out against (more: a subsample).
COARSE_SAMPLES = 40_000


def _subsample_indices(n: int, most: int) -> np.ndarray:
    """At most ``most`` of ``range(n)``, evenly strided (deterministic)."""
    return np.arange(n) if n <= most else np.linspace(0, n - 1, most).round().astype(np.int64)


def _subsample(points: np.ndarray, most: int) -> tuple[np.ndarray, float]:
    """At most ``most`` of ``points`` and the largest distance of any point from them (0 for all)."""
    keep = _subsample_indices(len(points), most)
    if len(keep) == len(points):
        return points, 0.0
    sub = points[keep]
    return sub, float(cKDTree(sub).query(points, 1, workers=-1)[0].max())


@dataclass
class DistanceField:
    """Tricubic B-spline of a clipped signed distance on the grid ``origin + spacing * (i, j, k)``
    (metres, in the frame of the mesh it was built from)."""

    origin: np.ndarray
    spacing: float
    coeffs: np.ndarray  # (nx, ny, nz) B-spline coefficients, m
    band: float  # clip outside the surface, m
    depth: float  # clip inside the surface, m
    info: dict = field(default_factory=dict)
    #: the contact weight of a surface with an open edge (a cropped mesh): B-spline coefficients on
    #: the same grid, the nodes' weights themselves (:func:`~kneenlp.geometry.rim.rim_weights`: 1 on
    #: the surface, 0 beyond its rim), so the weight stays within [0, 1] and is exactly 1 in a cell
    #: whose 64 nodes weigh 1 (more than 2.5 spacings inside the rim); None without an open edge
    weights: np.ndarray | None = None

    @cached_property
    def weight_spline(self) -> DistanceField | None:
        """:attr:`weights` as a spline to evaluate (value 1 outside the grid), or None."""
        if self.weights is None:
            return None
        return DistanceField(self.origin, self.spacing, self.weights, band=1.0, depth=0.0)

    @property
    def spline(self) -> tuple[np.ndarray, np.ndarray, float]:
        """``(coeffs, origin, spacing)``: the spline as the compiled loops read it
        (:mod:`kneenlp.geometry.spline_kernels`)."""
        return self.coeffs, self.origin, self.spacing

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.coeffs.shape)

    @cached_property
    def cell_min(self) -> np.ndarray:
        """A lower bound of the field in each grid cell (m; :func:`~kneenlp.geometry.spline_kernels.cell_lower_bound`,
        at least the smallest coefficient shaping the cell), derived once from :attr:`coeffs`: a point
        in a cell whose bound is not negative cannot penetrate, and is passed over with one look-up."""
        return cell_lower_bound(self.coeffs)

    @cached_property
    def bounds(self) -> np.ndarray:
        """Box (2 x 3, m) in which the field is evaluated (one node inside the outer layer; read only)."""
        lo = self.origin + self.spacing
        return np.array([lo, self.origin + self.spacing * (np.array(self.shape) - 2)])

    # ------------------------------------------------------------------ construction
    @staticmethod
    def grid(box: np.ndarray, spacing: float) -> tuple[np.ndarray, tuple[int, int, int]]:
        """(origin, shape) of the grid representing ``box`` (2 x 3, m) at ``spacing`` (m): nodes
        on multiples of the spacing, padded by the spline's support."""
        lo = np.floor(np.asarray(box[0], float) / spacing - 3) * spacing
        hi = np.ceil(np.asarray(box[1], float) / spacing + 3) * spacing
        return lo, tuple(int(np.ceil((hi[i] - lo[i]) / spacing)) + 1 for i in range(3))

    @classmethod
    def check_memory(cls, box: np.ndarray, spacing: float) -> None:
        """``ValueError`` (saying the finest spacing that fits) if the field over ``box`` at
        ``spacing`` would need more than :data:`MAX_FIELD_BYTES` to build."""
        need = float(np.prod(cls.grid(box, spacing)[1], dtype=float)) * BYTES_PER_NODE
        if need > MAX_FIELD_BYTES:
            finest = spacing * (need / MAX_FIELD_BYTES) ** (1 / 3)
            raise ValueError(f"a distance field at {spacing * 1e3:g} mm over the contact region needs {need / 1e9:.3g} "
                             f"GB (at most {MAX_FIELD_BYTES / 1e9:g} GB): use at least {finest * 1e3:.2g} mm "
                             "(default 0.5 mm)")

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, box: np.ndarray, *, spacing: float = 5e-4, offset: float = 0.0,
                  band: float = 2e-3, depth: float = 3e-3, n_check: int = 4000,
                  rng_seed: int = 0, articular: np.ndarray | None = None) -> DistanceField:
        """Build from a triangle mesh with outward normals (metres).

        ``box`` (2 x 3, m) is the region to represent (padded here by the spline's support);
        ``offset`` (m) moves the represented surface outward (``d = d_mesh - offset``).  Exact
        distances are computed for the nodes that can lie within the band; the others take the
        clip value with the sign of their nearest vertex normal.  The spline rounds the clips within
        about three grid cells, so the field is accurate for ``-(depth - 3 spacing) < d < band - 3
        spacing`` (-1.5 to 0.5 mm by default: penetrations up to 1.5 mm, gaps up to 0.5 mm); it is
        checked there against exact distances at ``n_check`` random points inside ``box``
        (``info['error_rms_um']``, ``info['error_max_um']``).  ``articular`` (bool per face) makes
        a thin closed shell's field the depth below those faces (:class:`~kneenlp.geometry.shell.
        ShellDistance`).
        """
        t0 = time.perf_counter()
        # nodes on multiples of the spacing in the mesh's frame: the same anatomy in the same frame gives
        # the same grid whatever the exact box
        cls.check_memory(box, spacing)
        lo, shape = cls.grid(box, spacing)
        axes = [lo[i] + spacing * np.arange(shape[i]) for i in range(3)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        exact = MeshDistance(mesh) if articular is None else ShellDistance(mesh, articular)
        side = mesh if articular is None else exact.surface  # whose vertex normals tell a far node's side
        # nearest-sample distance bounds the true distance within one facet radius; on a fine mesh the
        # nodes are sorted out against a subsample (its slack: the farthest sample from it), since the
        # tree queries of a million nodes grow with the samples (158 s for a 300k-face femur)
        samples = np.vstack([mesh.vertices, mesh.triangles_center])
        coarse, slack = _subsample(samples, COARSE_SAMPLES)
        facet = float(np.percentile(np.linalg.norm(mesh.triangles - mesh.triangles_center[:, None], axis=2), 99.9))
        reach = offset + max(band, depth) + facet + 2 * spacing
        approx, _ = cKDTree(coarse).query(nodes, 1, distance_upper_bound=reach + slack, workers=-1)
        near = np.isfinite(approx) & (approx >= offset - depth - facet - 2 * spacing)
        d = np.empty(len(nodes))
        far = np.flatnonzero(~near)
        # far nodes (beyond the reach) take the side of the nearest vertex's normal (of a subsample)
        keep = _subsample_indices(len(side.vertices), COARSE_SAMPLES)
        vertices, normals = np.asarray(side.vertices)[keep], np.asarray(side.vertex_normals)[keep]
        _, iv = cKDTree(vertices).query(nodes[far], 1, workers=-1)
        outward = np.einsum("ij,ij->i", nodes[far] - vertices[iv], normals[iv]) >= 0
        d[far] = np.where(outward, band, -depth)
        d[near] = exact(nodes[near], certify=False)[0] - offset
        values = np.clip(d, -depth, band).reshape(shape)
        # float32 coefficients, as stored: a field built now and one read from the cache are identical
        coeffs = spline_filter(values, order=3, mode="mirror").astype(np.float32).astype(np.float64)
        out = cls(lo, float(spacing), coeffs, float(band), float(depth))
        rim = OpenEdges(mesh, offset)
        if not rim.closed:  # a counted point's 64 nodes are near ones: far nodes weigh 0 (beyond a rim the
            weights = np.zeros(len(nodes))  # far nodes' clip takes the side of a vertex normal, a fake inside)
            weights[near] = rim_weights(rim, nodes[near], np.abs(d[near]), spacing)
            out.weights = weights.reshape(shape).astype(np.float32).astype(np.float64)
        t1 = time.perf_counter()
        # accuracy: random points on the represented surface moved along its normal within the band
        rng = np.random.default_rng(rng_seed)
        pts, face = trimesh.sample.sample_surface(side, 4 * n_check, seed=rng_seed)
        inside = np.all((pts >= box[0]) & (pts <= box[1]), axis=1)
        pts, face = pts[inside][:n_check], face[inside][:n_check]
        lo_d, hi_d = -(depth - 3 * spacing), band - 3 * spacing
        test = pts + side.face_normals[face] * (offset + rng.uniform(lo_d, hi_d, (len(pts), 1)))
        d_exact = exact(test)[0] - offset
        keep = (d_exact > lo_d) & (d_exact < hi_d) & np.all((test >= box[0]) & (test <= box[1]), axis=1)
        err = out.evaluate(test[keep])[0] - d_exact[keep]
        out.info = {"nodes": int(np.prod(shape)), "exact_nodes": int(near.sum()), "spacing_mm": spacing * 1e3,
                    "offset_mm": offset * 1e3, "band_mm": band * 1e3, "depth_mm": depth * 1e3,
                    "error_rms_um": float(np.sqrt(np.mean(err**2)) * 1e6) if err.size else float("nan"),
                    "error_max_um": float(np.max(np.abs(err)) * 1e6) if err.size else float("nan"),
                    "checked_points": int(err.size), "build_seconds": t1 - t0,
                    "check_seconds": time.perf_counter() - t1, "megabytes": coeffs.nbytes / 1e6,
                    "rim_edges": len(rim),
                    "shell_articular_faces": int(np.count_nonzero(articular)) if articular is not None else 0,
                    "rim_weighted_nodes": int(np.count_nonzero(out.weights.ravel()[near] < 1))
                    if out.weights is not None else 0}
        return out

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, points: np.ndarray, order: int = 0):
        """Signed distance (N,) at ``points`` (N x 3, m); with ``order`` >= 1 also the gradient
        (N x 3), with ``order`` >= 2 the Hessian (N x 3 x 3), with ``order`` 3 the third
        derivatives (N x 3 x 3 x 3, piecewise constant in a cubic spline).  Returns a tuple of
        ``order + 1`` arrays (just the distance for ``order`` 0 is ``evaluate(x)[0]``).  Points
        outside the grid get ``band`` with zero derivatives."""
        x = np.asarray(points, dtype=float).reshape(-1, 3)
        n = len(x)
        u = (x - self.origin) / self.spacing
        i0 = np.floor(u).astype(np.int64)
        ok = np.all((i0 >= 1) & (i0 <= np.array(self.shape) - 3), axis=1)
        out = [np.full(n, self.band)] + [np.zeros((n,) + (3,) * k) for k in range(1, order + 1)]
        if not np.any(ok):
            return tuple(out)
        m = int(ok.sum())
        if order == 0:  # compiled (kernels); the same spline as scipy's map_coordinates
            values = np.empty(m)
            field_values(self.spline, x[ok], values)
            out[0][ok] = values
            return tuple(out)
        parts = (np.empty(m), np.empty((m, 3)), np.empty((m, 3, 3)), np.empty((m, 3, 3, 3)))
        field_derivatives(self.spline, np.ascontiguousarray(x[ok]), parts)
        for k in range(order + 1):
            out[k][ok] = parts[k]
        return tuple(out)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> None:
        """Write to a compressed ``.npz`` atomically (coefficients as float32: 1e-7 relative)."""
        with atomic_target(path) as tmp, open(tmp, "wb") as fh:
            extra = {} if self.weights is None else {"weights": self.weights.astype(np.float32)}
            np.savez_compressed(fh, origin=self.origin, spacing=self.spacing, coeffs=self.coeffs.astype(np.float32),
                                band=self.band, depth=self.depth, info=json.dumps(self.info), **extra)

    @classmethod
    def load(cls, path: str | Path) -> DistanceField:
        with np.load(path) as z:
            weights = np.asarray(z["weights"], np.float64) if "weights" in z.files else None
            return cls(np.asarray(z["origin"], float), float(z["spacing"]), np.asarray(z["coeffs"], np.float64),
                       float(z["band"]), float(z["depth"]), json.loads(str(z["info"])), weights)


def field_key(mesh: trimesh.Trimesh, box: np.ndarray, articular: np.ndarray | None = None, **settings: float) -> str:
    """Hash of everything a field depends on: vertices, faces, box, the articular faces and settings."""
    h = hashlib.sha256()
    if articular is not None:
        h.update(np.packbits(np.asarray(articular, bool)).tobytes())
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(np.round(np.asarray(box, float), 9).tobytes())
    h.update(json.dumps({**settings, "version": FORMAT_VERSION}, sort_keys=True).encode())
    return h.hexdigest()[:24]


def cached_field(mesh: trimesh.Trimesh, box: np.ndarray, progress=None, articular: np.ndarray | None = None,
                 **settings: float) -> DistanceField:
    """:meth:`DistanceField.from_mesh`, read from the cache when an identical field was built
    before; ``progress`` (callable taking a message) is told when a build starts."""
    key = field_key(mesh, box, articular, **settings)
    where = cache_dir()
    path = where / f"field-{key}.npz" if where else None
    if path is not None and path.is_file():
        try:
            out = DistanceField.load(path)
            out.info["cached"] = str(path)
            return out
        except (OSError, ValueError, KeyError):
            pass  # a damaged entry is rebuilt
    if progress is not None:
        progress("building the femoral distance field (once per surface; cached)")
    out = DistanceField.from_mesh(mesh, box, articular=articular, **settings)
    if path is not None:
        try:
            out.save(path)
        except OSError:
            pass
    return out
