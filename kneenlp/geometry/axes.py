"""Anatomy from surfaces: compartments, condyles, the flexion axis and the region that can touch.

What a knee MRI gives is surfaces, so the frames are built from them as in the laxity-noise paper
(after Dzialo et al.): the flexion axis is the line through the centres of cylinders fitted to the
distal-posterior articular surfaces of the medial and lateral femoral condyles, and the knee
centre is the midpoint of those centres.  All functions take and return metres and unit vectors
in the frame of the given points; ``up``, ``anterior`` and ``lateral`` are approximate directions
of that frame (proximal, anterior, lateral), refined by the fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def vertex_components(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """Vertex indices of each connected component, largest first."""
    e = np.asarray(mesh.edges_unique)
    n = len(mesh.vertices)
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, label = connected_components(adj, directed=False)
    comps = [np.flatnonzero(label == i) for i in np.unique(label)]
    return sorted(comps, key=len, reverse=True)


def split_plateaus(mesh: trimesh.Trimesh, lateral: np.ndarray) -> tuple[dict[str, np.ndarray], str]:
    """Split tibial cartilage holding both plateaus into medial and lateral vertex sets.

    Two connected components of comparable size are the two plateaus; otherwise the vertices are
    split in two by 2-means along ``lateral``.  Returns the vertex indices by compartment and a
    sentence saying how the split was made."""
    lat = _unit(lateral)
    comps = vertex_components(mesh)
    v = np.asarray(mesh.vertices)
    if len(comps) >= 2 and len(comps[1]) > 0.2 * len(comps[0]):
        a, b = comps[0], comps[1]
        rest = sum(len(c) for c in comps[2:])
        if v[a].mean(axis=0) @ lat > v[b].mean(axis=0) @ lat:
            a, b = b, a
        how = (f"two connected components ({len(a)} medial, {len(b)} lateral vertices"
               + (f"; {rest} vertices in {len(comps) - 2} small pieces left out)" if rest else ")"))
        return {"medial": a, "lateral": b}, how
    s = v @ lat
    cut = float(np.median(s))
    for _ in range(50):
        new = 0.5 * (s[s < cut].mean() + s[s >= cut].mean())
        if abs(new - cut) < 1e-9:
            break
        cut = new
    a, b = np.flatnonzero(s < cut), np.flatnonzero(s >= cut)
    how = f"2-means along the lateral axis at {cut * 1e3:.1f} mm ({len(a)} / {len(b)} vertices)"
    return {"medial": a, "lateral": b}, how


@dataclass(frozen=True)
class CondyleSplit:
    """Plane separating the medial from the lateral femoral condyle (through the notch)."""

    point: np.ndarray  # m
    normal: np.ndarray  # unit, medial -> lateral

    def lateral_side(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points) - self.point) @ self.normal >= 0

    def describe(self) -> str:
        return (f"plane through the notch at ({', '.join(f'{c * 1e3:.1f}' for c in self.point)}) mm, "
                f"normal ({', '.join(f'{c:.3f}' for c in self.normal)})")


def split_condyles(femur: trimesh.Trimesh, medial_centre: np.ndarray, lateral_centre: np.ndarray,
                   up: np.ndarray, bins: int = 60) -> CondyleSplit:
    """The plane between the femoral condyles: perpendicular to the line joining the two tibial
    plateau centres (made perpendicular to ``up``), through the intercondylar notch, i.e. where the
    most distal femoral point facing distally is highest, searched between the two plateau centres."""
    up = _unit(up)
    normal = np.asarray(lateral_centre, float) - np.asarray(medial_centre, float)
    normal = _unit(normal - (normal @ up) * up)
    v = np.asarray(femur.vertices)
    s, h = v @ normal, v @ up
    lo, hi = sorted([np.asarray(medial_centre) @ normal, np.asarray(lateral_centre) @ normal])
    distal = np.asarray(femur.vertex_normals) @ (-up) > 0.5
    edges = np.linspace(lo, hi, bins + 1)
    idx = np.digitize(s, edges) - 1
    lowest = np.full(bins, -np.inf)
    for i in range(bins):
        m = distal & (idx == i)
        if np.any(m):
            lowest[i] = h[m].min()
    filled = np.where(np.isinf(lowest), np.min(lowest[np.isfinite(lowest)]), lowest)
    smooth = np.convolve(filled, np.ones(3) / 3, "same")
    smooth[np.isinf(lowest)] = -np.inf
    i = int(np.argmax(smooth[2:-2])) + 2
    s_notch = 0.5 * (edges[i] + edges[i + 1])
    centre = v.mean(axis=0)
    return CondyleSplit(centre + (s_notch - centre @ normal) * normal, normal)


@dataclass(frozen=True)
class CylinderFit:
    axis: np.ndarray  # unit
    centre: np.ndarray  # point of the axis nearest to the fitted points' centroid, m
    radius: float  # m
    rms: float  # m
    points: int


def fit_cylinder(points: np.ndarray, axis_guess: np.ndarray) -> CylinderFit:
    """Least-squares cylinder (geometric distances), started from a circle fit in the plane
    perpendicular to ``axis_guess``."""
    pts = np.asarray(points, dtype=float)
    a0 = _unit(axis_guess)
    u = _unit(np.cross(a0, [1.0, 0, 0] if abs(a0[0]) < 0.9 else [0, 1.0, 0]))
    w = np.cross(a0, u)
    c0 = pts.mean(axis=0)
    plane = np.c_[(pts - c0) @ u, (pts - c0) @ w]
    sol = np.linalg.lstsq(np.c_[2 * plane, np.ones(len(plane))], (plane**2).sum(axis=1), rcond=None)[0]
    r0 = np.sqrt(sol[2] + sol[0] ** 2 + sol[1] ** 2)

    def axis_of(t):
        return _unit(a0 + t[0] * u + t[1] * w)

    def residual(t):
        a = axis_of(t)
        d = pts - (c0 + t[2] * u + t[3] * w)
        return np.linalg.norm(d - np.outer(d @ a, a), axis=1) - t[4]

    t = scipy.optimize.least_squares(residual, [0, 0, sol[0], sol[1], r0], method="lm").x
    a = axis_of(t)
    q = c0 + t[2] * u + t[3] * w
    q = q + ((c0 - q) @ a) * a
    r = residual(t)
    return CylinderFit(a, q, float(abs(t[4])), float(np.sqrt(np.mean(r**2))), len(pts))


def condyle_region(normals: np.ndarray, axes: tuple[np.ndarray, np.ndarray, np.ndarray],
                   sector_deg: tuple[float, float] = (30.0, 120.0), max_axial: float = 0.5) -> np.ndarray:
    """Mask of the distal-posterior articular part of a condyle: sagittal normal direction between
    ``sector_deg`` measured from distal (0 deg) towards posterior (90 deg), side walls excluded
    (``|n . lateral| < max_axial``); ``axes = (up, anterior, lateral)``, the femur's directions."""
    up, anterior, lateral = axes
    n = np.asarray(normals)
    ang = np.degrees(np.arctan2(n @ (-_unit(anterior)), n @ (-_unit(up))))
    return (ang >= sector_deg[0]) & (ang <= sector_deg[1]) & (np.abs(n @ _unit(lateral)) < max_axial)


@dataclass(frozen=True)
class FlexionAxis:
    """The flexion axis through the cylinder centres of the two condyles."""

    point: np.ndarray  # knee centre: midpoint of the two cylinder centres, m
    direction: np.ndarray  # unit, medial -> lateral
    medial: CylinderFit
    lateral: CylinderFit

    def mapped(self, rotation: np.ndarray, origin: np.ndarray) -> FlexionAxis:
        """The same fits in another frame, ``x' = rotation @ (x - origin)``."""

        def cyl(c: CylinderFit) -> CylinderFit:
            return CylinderFit(rotation @ c.axis, rotation @ (c.centre - origin), c.radius, c.rms, c.points)

        return FlexionAxis(rotation @ (self.point - origin), rotation @ self.direction, cyl(self.medial),
                           cyl(self.lateral))

    def describe(self, offset: float = 0.0) -> str:
        m, lt = self.medial, self.lateral
        return (f"cylinders: medial radius {(m.radius + offset) * 1e3:.1f} mm (RMS {m.rms * 1e3:.2f} mm, "
                f"{m.points} points), lateral radius {(lt.radius + offset) * 1e3:.1f} mm (RMS "
                f"{lt.rms * 1e3:.2f} mm, {lt.points} points); centres "
                f"{np.linalg.norm(lt.centre - m.centre) * 1e3:.1f} mm apart")


def fit_flexion_axis(femur: trimesh.Trimesh, split: CondyleSplit, up: np.ndarray, anterior: np.ndarray,
                     lateral: np.ndarray) -> FlexionAxis:
    """Cylinders fitted to the distal-posterior surface of each condyle (:func:`condyle_region`);
    the flexion axis joins their centres.  ``femur`` may be the articular surface or the bone
    under it (an offset surface has the same axes)."""
    v, n = np.asarray(femur.vertices), np.asarray(femur.vertex_normals)
    region = condyle_region(n, (up, anterior, lateral))
    side = split.lateral_side(v)
    fits = [fit_cylinder(v[region & (side == lat)], lateral) for lat in (False, True)]
    direction = _unit(fits[1].centre - fits[0].centre)
    return FlexionAxis(0.5 * (fits[0].centre + fits[1].centre), direction, fits[0], fits[1])


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Right-handed rotation by ``angle`` (rad) about unit ``axis``."""
    a = _unit(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def sweep(points: np.ndarray, axis_point: np.ndarray, axis_direction: np.ndarray,
          flexion_deg: tuple[float, float] = (-5.0, 100.0), steps: int = 43) -> np.ndarray:
    """``points`` (N x 3) flexed about the axis through ``axis_point`` along ``axis_direction`` at
    ``steps`` flexions over ``flexion_deg`` (stacked, steps * N x 3; flexion is a negative rotation
    about the lateral axis)."""
    c = np.asarray(axis_point, float)
    return np.vstack([(np.asarray(points) - c) @ rotation_about(axis_direction, -th).T + c
                      for th in np.radians(np.linspace(*flexion_deg, steps))])


def touchable_box(femur_vertices: np.ndarray, swept: np.ndarray, reach: float = 8e-3,
                  margin: float = 3e-3) -> np.ndarray:
    """Box (2 x 3, m) around the femoral surface the tibia can touch: femoral vertices within
    ``reach`` of the ``swept`` tibial points (:func:`sweep`; ``reach`` stands for the laxity
    translations and rotations around that path), padded by ``margin``."""
    # one vectorised query: every femoral vertex within reach of any swept tibial point
    # (an unbalanced tree builds ~8x faster here and answers the same query exactly)
    tree = cKDTree(swept, balanced_tree=False, compact_nodes=False)
    dist, _ = tree.query(np.asarray(femur_vertices), distance_upper_bound=reach, workers=-1)
    hit = np.isfinite(dist)
    if not np.any(hit):
        raise ValueError("no femoral surface within reach of the tibia between the given flexions")
    v = np.asarray(femur_vertices)[hit]
    return np.array([v.min(axis=0) - margin, v.max(axis=0) + margin])
