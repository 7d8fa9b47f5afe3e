# PROTOTYPE (issue 13), not part of the package and not imported by it: the measured femoral-surface
# representation of docs/research/mesh-contact-representation.md, kept for integration as a
# kneenlp.model contact element (see docs/progress.md).
"""Smooth femoral-surface representation for elastic-foundation knee contact.

Self-contained (numpy, scipy, trimesh, casadi, standard library only).  Units: SI throughout
(metres, newtons, pascals; K in N/m^3).

Contents
--------
* :func:`articular_surface_from_bone` -- femoral articular surface = subchondral bone offset
  outward by a cartilage thickness along smoothed vertex normals.
* :func:`split_condyles` -- automatic medial/lateral split at the intercondylar notch.
* :func:`fit_flexion_axis` -- axis through the centres of cylinders fitted to the two condyles.
* :func:`mesh_signed_distance` -- exact (certified) point-to-triangle-mesh signed distance.
* :func:`reference_contact` -- brute-force contact oracle on the mesh (test utility).
* :class:`FemoralSurface` -- narrow-band signed distance field stored as a tensor-product cubic
  B-spline, evaluated by ``casadi.Function.bspline`` (C2 in space, exact AD derivatives of any
  order), with :meth:`FemoralSurface.contact_wrench` returning a vectorised CasADi Function
  ``(R, p, K) -> (force, moment)``.

Conventions
-----------
* Signed distance ``d(x)``: < 0 inside the femur (below the articular surface), > 0 outside.
  For an open surface the sign is that of ``(x - c) . n_c`` where ``c`` is the closest point
  and ``n_c`` the (pseudo-)normal there, so the mesh normals must point out of the femur
  (towards the tibia).  This is the case for the Lenhart meshes.
* Penetration of a tibial point: ``pen = -d``.  Pressure ``p = K g(pen)`` with the C2 gate
  ``g(s) = s^3/delta^2 - s^4/(2 delta^3)`` on ``[0, delta]``, ``s - delta/2`` beyond, 0 below 0.
* Force on the tibia ``sum p_i A_i n_i`` along the outward femoral normal ``n = grad d``,
  expressed in the femoral frame; moment about the tibial origin ``p``.
* Tibial frame in the femoral frame: ``x_fem = R x_tib + p``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
import scipy.optimize
import scipy.sparse as sp
from scipy.ndimage import map_coordinates, spline_filter
from scipy.spatial import cKDTree
import trimesh
from trimesh import triangles as _tri

K_DEFAULT = 1e10  # N/m^3
DELTA_DEFAULT = 1e-5  # m, gate width of the smooth max(d, 0)


# ----------------------------------------------------------------------------------------------
# pressure law
# ----------------------------------------------------------------------------------------------
def smooth_gate(pen: Any, delta: float = DELTA_DEFAULT) -> Any:
    """C2-smooth max(pen, 0) [m -> m]; works for numpy arrays and CasADi SX/MX/DM (elementwise).

    ``g = s^3/delta^2 - s^4/(2 delta^3) + max(pen - delta, 0)`` with ``s = clip(pen, 0, delta)``,
    which equals the piecewise definition exactly and is exactly 0 for ``pen <= 0``.
    """
    if isinstance(pen, (ca.SX, ca.MX, ca.DM)):
        s = ca.fmin(ca.fmax(pen, 0), delta)
        return s**3 / delta**2 - s**4 / (2 * delta**3) + ca.fmax(pen - delta, 0)
    pen = np.asarray(pen, dtype=float)
    s = np.clip(pen, 0.0, delta)
    return s**3 / delta**2 - s**4 / (2 * delta**3) + np.maximum(pen - delta, 0.0)


# ----------------------------------------------------------------------------------------------
# mesh utilities
# ----------------------------------------------------------------------------------------------
def _vertex_adjacency(mesh: trimesh.Trimesh) -> sp.csr_matrix:
    e = mesh.edges_unique
    n = len(mesh.vertices)
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return (a + a.T).tocsr()


def smoothed_vertex_normals(mesh: trimesh.Trimesh, iterations: int = 10) -> np.ndarray:
    """Vertex normals (unit, outward) averaged ``iterations`` times over the 1-ring (Laplacian)."""
    n = np.array(mesh.vertex_normals, dtype=float)
    if iterations <= 0:
        return n
    a = _vertex_adjacency(mesh)
    a = a + sp.identity(a.shape[0], format="csr")
    deg = np.asarray(a.sum(axis=1)).ravel()
    w = sp.diags(1.0 / deg) @ a
    for _ in range(iterations):
        n = w @ n
        n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n


def articular_surface_from_bone(
    bone: trimesh.Trimesh,
    thickness: float = 2e-3,
    normal_smoothing_iterations: int = 10,
    subdivisions: int = 1,
    keep: np.ndarray | None = None,
) -> trimesh.Trimesh:
    """Femoral articular (cartilage) surface derived from the subchondral bone surface [m].

    Method: every bone vertex is moved outward by ``thickness`` along its vertex normal after
    ``normal_smoothing_iterations`` passes of 1-ring averaging of the normals (uniform-thickness
    cartilage; smoothing keeps the offset from folding in the concave notch / MRI staircase).
    Then ``subdivisions`` Loop subdivisions are applied (each quarters the facet size, so the
    faceting error of the surface drops ~4x; this also smooths MRI noise slightly).
    ``keep`` (bool mask over bone faces) optionally restricts the result to a region.

    The bone normals must point out of the bone (towards the joint).  Diagnostics are stored in
    ``result.metadata['articular']``: achieved offset (exact distance of the offset vertices to
    the bone: min/mean/max, m), number of flipped faces, thickness, method.
    """
    bone = bone.copy()
    if keep is not None:
        bone.update_faces(np.asarray(keep, dtype=bool))
        bone.remove_unreferenced_vertices()
    n = smoothed_vertex_normals(bone, normal_smoothing_iterations)
    v = bone.vertices + thickness * n
    off = trimesh.Trimesh(v, bone.faces.copy(), process=False)
    flipped = int(np.sum(np.einsum("ij,ij->i", off.face_normals, bone.face_normals) < 0))
    dist = mesh_signed_distance(bone, v)[0]
    for _ in range(subdivisions):
        vv, ff = trimesh.remesh.subdivide_loop(off.vertices, off.faces, iterations=1)
        off = trimesh.Trimesh(vv, ff, process=False)
    off.metadata["articular"] = dict(
        method="offset along %d-times 1-ring-smoothed vertex normals, %d Loop subdivision(s)"
        % (normal_smoothing_iterations, subdivisions),
        thickness=float(thickness),
        achieved_offset_min=float(dist.min()),
        achieved_offset_mean=float(dist.mean()),
        achieved_offset_max=float(dist.max()),
        flipped_faces=flipped,
    )
    return off


def _triangle_pseudo_normals(mesh: trimesh.Trimesh, face: np.ndarray, cp: np.ndarray) -> np.ndarray:
    """Normal used for the sign at closest point ``cp`` on ``face``: the face normal in the face
    interior, the barycentric blend of vertex normals on edges/vertices (robust sign there)."""
    fn = mesh.face_normals[face]
    bary = _tri.points_to_barycentric(mesh.triangles[face], cp)
    onb = bary.min(axis=1) < 1e-6
    if np.any(onb):
        b = np.clip(bary[onb], 0, None)
        b /= b.sum(axis=1, keepdims=True)
        vn = mesh.vertex_normals[mesh.faces[face[onb]]]  # (m,3,3)
        blend = np.einsum("ij,ijk->ik", b, vn)
        fn = fn.copy()
        fn[onb] = blend / np.linalg.norm(blend, axis=1, keepdims=True)
    return fn


def _closest_candidates(tris: np.ndarray, q: np.ndarray, cand: np.ndarray):
    """Closest point of each q (n,3) among candidate triangle ids cand (n,k)."""
    n, k = cand.shape
    c = _tri.closest_point(tris[cand.ravel()], np.repeat(q, k, axis=0)).reshape(n, k, 3)
    dd = np.linalg.norm(c - q[:, None, :], axis=2)
    j = dd.argmin(axis=1)
    r = np.arange(n)
    return c[r, j], cand[r, j], dd[r, j]


def mesh_signed_distance(
    mesh: trimesh.Trimesh, points: np.ndarray, k: int = 24, chunk: int = 20_000,
    certify: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact signed distance from ``points`` (N,3) [m] to the triangle mesh.

    Returns ``(d, closest, face, grad)``: signed distance (N,) [m] (< 0 inside / behind the
    outward normals), closest points (N,3), face index (N,), unit gradient of d (N,3) (=
    ``(x-c)/d``, or the face normal when |d| < 1e-12).

    Candidates: the ``k`` triangles with nearest centroids plus the few "big" triangles
    (centroid-vertex radius above the 99.99th percentile, e.g. subdivision artefacts at the
    rim).  With ``certify=True`` the answer is *proven* exact: a point is accepted when the
    k-th candidate centroid distance minus the largest small-triangle radius is at least the
    best distance found; otherwise k is multiplied by 4 (up to 4 times) and finally all
    triangles are searched (brute force).  NB: ``trimesh.proximity.closest_point`` (trimesh
    5.2) is *not* exact on these meshes (it missed closer faces by up to ~40 um in our tests),
    so it is not used here.  With ``certify=False`` the first k-candidate answer is returned
    (fast; used for grid nodes and validated against the certified answer).
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    tris = mesh.triangles
    cen = tris.mean(axis=1)
    rad = np.linalg.norm(tris - cen[:, None, :], axis=2).max(axis=1)
    r_small = float(np.percentile(rad, 99.99))
    big = np.nonzero(rad > r_small)[0]
    small = np.nonzero(rad <= r_small)[0]
    tree = cKDTree(cen[small])
    N = len(pts)
    cp = np.empty((N, 3))
    fid = np.empty(N, dtype=np.int64)
    dist = np.empty(N)
    for s in range(0, N, chunk):
        q = pts[s : s + chunk]
        todo = np.arange(len(q))
        kk = min(k, len(small))
        for attempt in range(5):
            dk, ik = tree.query(q[todo], kk)
            ik = small[ik.reshape(len(todo), -1)]
            dk = dk.reshape(len(todo), -1)
            cand = np.hstack([ik, np.broadcast_to(big, (len(todo), len(big)))])
            c, f, dd = _closest_candidates(tris, q[todo], cand)
            cp[s + todo], fid[s + todo], dist[s + todo] = c, f, dd
            if not certify or kk >= len(small):
                break
            ok = dk[:, -1] - r_small >= dd
            todo = todo[~ok]
            if len(todo) == 0:
                break
            kk = min(4 * kk, len(small))
        else:
            for t in todo:  # brute force over all triangles
                c, f, dd = _closest_candidates(tris, q[t : t + 1], np.arange(len(tris))[None, :])
                cp[s + t], fid[s + t], dist[s + t] = c[0], f[0], dd[0]
    nrm = _triangle_pseudo_normals(mesh, fid, cp)
    sgn = np.where(np.einsum("ij,ij->i", pts - cp, nrm) < 0, -1.0, 1.0)
    d = sgn * dist
    with np.errstate(invalid="ignore", divide="ignore"):
        grad = (pts - cp) / d[:, None]
    tiny = np.abs(d) < 1e-12
    grad[tiny] = mesh.face_normals[fid[tiny]]
    return d, cp, fid, grad


def trimesh_signed_distance(
    mesh: trimesh.Trimesh, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Same outputs as :func:`mesh_signed_distance` but with the closest points from
    ``trimesh.proximity.closest_point`` (kept for comparison only: not always exact)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    cp, dist, fid = trimesh.proximity.closest_point(mesh, pts)
    nrm = _triangle_pseudo_normals(mesh, fid, cp)
    sgn = np.where(np.einsum("ij,ij->i", pts - cp, nrm) < 0, -1.0, 1.0)
    d = sgn * dist
    with np.errstate(invalid="ignore", divide="ignore"):
        grad = (pts - cp) / d[:, None]
    small = np.abs(d) < 1e-12
    grad[small] = mesh.face_normals[fid[small]]
    return d, cp, fid, grad


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix for a right-handed rotation by ``angle`` [rad] about unit ``axis``."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def flexion_pose(axis_point: np.ndarray, axis_dir: np.ndarray, flexion: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Tibial pose (R, p) in the femoral frame for a pure flexion ``flexion`` [rad] about the
    axis (point [m], unit direction medial->lateral of a right knee = +z), from the identity
    pose.  As in OpenSim's knee_r (rotation about z with coefficient -1): R = rot(axis, -flex)."""
    R = axis_rotation(axis_dir, -flexion)
    return R, np.asarray(axis_point, float) - R @ np.asarray(axis_point, float)


def swept_box(points: np.ndarray, axis_point: np.ndarray, axis_dir: np.ndarray,
              flexion_range: tuple[float, float] = (np.radians(-10), np.radians(120)),
              margin: float = 4e-3, n: int = 27) -> tuple[np.ndarray, np.ndarray]:
    """Box [m, femoral frame] covering the tibial points (N,3) [m] swept by flexion about the
    flexion axis over ``flexion_range`` [rad], padded by ``margin`` (covers the laxity-test
    translations/rotations around that path)."""
    P = []
    for th in np.linspace(*flexion_range, n):
        R, p = flexion_pose(axis_point, axis_dir, th)
        P.append(np.asarray(points) @ R.T + p)
    P = np.vstack(P)
    return P.min(axis=0) - margin, P.max(axis=0) + margin


def contact_region_box(
    femur: trimesh.Trimesh, tibia_points: np.ndarray, axis_point: np.ndarray,
    axis_dir: np.ndarray, flexion_range: tuple[float, float] = (np.radians(-10), np.radians(120)),
    reach: float = 5e-3, margin: float = 3e-3, n: int = 66,
) -> tuple[np.ndarray, np.ndarray]:
    """Box [m, femoral frame] around the part of the femoral surface that the tibia can touch:
    femoral vertices within ``reach`` of the tibial points (N,3) [m] swept by flexion about the
    flexion axis over ``flexion_range`` [rad] (``n`` steps), bounding box padded by ``margin``.
    ``reach`` stands for the laxity translations/rotations around the flexion path."""
    tree = cKDTree(femur.vertices)
    hit = np.zeros(len(femur.vertices), bool)
    for th in np.linspace(*flexion_range, n):
        R, p = flexion_pose(axis_point, axis_dir, th)
        for lst in tree.query_ball_point(np.asarray(tibia_points) @ R.T + p, reach):
            hit[lst] = True
    v = femur.vertices[hit]
    return v.min(axis=0) - margin, v.max(axis=0) + margin


def vertex_areas(mesh: trimesh.Trimesh) -> np.ndarray:
    """Lumped vertex areas [m^2]: one third of the area of every adjacent face."""
    a = np.zeros(len(mesh.vertices))
    np.add.at(a, mesh.faces.ravel(), np.repeat(mesh.area_faces / 3.0, 3))
    return a


# ----------------------------------------------------------------------------------------------
# condyle split and flexion axis
# ----------------------------------------------------------------------------------------------
def _components(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    from scipy.sparse.csgraph import connected_components

    nc, lab = connected_components(_vertex_adjacency(mesh), directed=False)
    return [np.nonzero(lab == i)[0] for i in range(nc)]


def split_condyles(
    femur: trimesh.Trimesh,
    tibia: trimesh.Trimesh | None = None,
    lateral_axis: np.ndarray = np.array([0.0, 0.0, 1.0]),
    up_axis: np.ndarray = np.array([0.0, 1.0, 0.0]),
    plane_normal: np.ndarray | None = None,
    nbins: int = 60,
) -> dict[str, Any]:
    """Split a femoral surface holding both condyles into medial and lateral meshes.

    The split plane is perpendicular to ``plane_normal`` (default: the direction from the medial
    to the lateral tibial compartment centroid, made perpendicular to ``up_axis``; if no tibia is
    given: ``lateral_axis``; pass the flexion axis here for the paper's convention) and passes
    through the intercondylar notch, found as the highest (most proximal along ``up_axis``)
    of the per-bin distal-most points of the distally facing femoral vertices, searched between
    the two tibial compartment centroids (or the central 60 % of the femur width).

    ``lateral_axis`` only decides which side is lateral (for a right knee in OpenSim frames +z).
    Returns dict(medial, lateral (Trimesh), plane_point, plane_normal (unit, medial->lateral),
    notch_offset (m along the normal from the search midpoint), tibia_centroids).
    """
    lat = np.asarray(lateral_axis, float) / np.linalg.norm(lateral_axis)
    up = np.asarray(up_axis, float) / np.linalg.norm(up_axis)
    cents = None
    if tibia is not None:
        comps = _components(tibia)
        if len(comps) >= 2:
            comps = sorted(comps, key=len)[-2:]
            cents = [tibia.vertices[c].mean(axis=0) for c in comps]
        else:  # 2-means along the lateral axis
            s = tibia.vertices @ lat
            thr = np.median(s)
            for _ in range(20):
                thr = 0.5 * (s[s < thr].mean() + s[s >= thr].mean())
            cents = [tibia.vertices[s < thr].mean(axis=0), tibia.vertices[s >= thr].mean(axis=0)]
    if plane_normal is not None:
        nrm = np.asarray(plane_normal, float).copy()
    elif cents is not None:
        nrm = cents[1] - cents[0]
        nrm = nrm - (nrm @ up) * up
    else:
        nrm = lat.copy()
    nrm /= np.linalg.norm(nrm)
    if nrm @ lat < 0:
        nrm = -nrm
    if cents is not None and (cents[1] - cents[0]) @ nrm < 0:
        cents = cents[::-1]
    v = femur.vertices
    s = v @ nrm
    if cents is not None:
        lo, hi = sorted([cents[0] @ nrm, cents[1] @ nrm])
    else:
        a, b = np.percentile(s, [0, 100])
        lo, hi = a + 0.2 * (b - a), b - 0.2 * (b - a)
    distal = femur.vertex_normals @ (-up) > 0.5
    h = v @ up
    edges = np.linspace(lo, hi, nbins + 1)
    idx = np.digitize(s, edges) - 1
    lowest = np.full(nbins, np.nan)
    for i in range(nbins):
        m = distal & (idx == i)
        if np.any(m):
            lowest[i] = h[m].min()
    # light smoothing of the profile, ignoring empty bins
    prof = np.where(np.isnan(lowest), -np.inf, lowest)
    prof_s = np.convolve(np.where(np.isinf(prof), np.nanmin(lowest), prof), np.ones(3) / 3, "same")
    prof_s[np.isinf(prof)] = -np.inf
    inner = slice(2, nbins - 2)
    i_notch = np.argmax(prof_s[inner]) + 2
    s_notch = 0.5 * (edges[i_notch] + edges[i_notch + 1])
    mid = 0.5 * (lo + hi)
    centre = v.mean(axis=0)
    point = centre + (s_notch - centre @ nrm) * nrm
    side = (femur.triangles_center - point) @ nrm
    med = femur.submesh([np.nonzero(side < 0)[0]], append=True)
    latm = femur.submesh([np.nonzero(side >= 0)[0]], append=True)
    return dict(
        medial=med,
        lateral=latm,
        plane_point=point,
        plane_normal=nrm,
        notch_offset=float(s_notch - mid),
        tibia_centroids=cents,
        profile=(0.5 * (edges[:-1] + edges[1:]), lowest),
    )


def _fit_cylinder(pts: np.ndarray, axis0: np.ndarray) -> dict[str, Any]:
    """Least-squares cylinder (geometric distance) starting from a circle fit in the plane
    perpendicular to ``axis0``.  Returns axis direction, a point on the axis (the projection of
    the points' centroid), radius, RMS and max |residual| [m]."""
    a0 = axis0 / np.linalg.norm(axis0)
    u = np.cross(a0, [1.0, 0, 0] if abs(a0[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    w = np.cross(a0, u)
    c0 = pts.mean(axis=0)
    P = np.c_[(pts - c0) @ u, (pts - c0) @ w]
    # Kasa algebraic circle fit
    A = np.c_[2 * P, np.ones(len(P))]
    sol = np.linalg.lstsq(A, (P**2).sum(axis=1), rcond=None)[0]
    cu, cw = sol[:2]
    r0 = np.sqrt(sol[2] + cu**2 + cw**2)

    def axis_of(t):
        a = a0 + t[0] * u + t[1] * w
        return a / np.linalg.norm(a)

    def res(t):
        a = axis_of(t)
        q = c0 + t[2] * u + t[3] * w
        dvec = pts - q
        perp = dvec - np.outer(dvec @ a, a)
        return np.linalg.norm(perp, axis=1) - t[4]

    t = scipy.optimize.least_squares(res, [0, 0, cu, cw, r0], method="lm").x
    a = axis_of(t)
    q = c0 + t[2] * u + t[3] * w
    q = q + ((c0 - q) @ a) * a
    r = res(t)
    return dict(axis=a, centre=q, radius=float(abs(t[4])), rms=float(np.sqrt(np.mean(r**2))),
                max_abs=float(np.abs(r).max()), n_points=int(len(pts)))


def condyle_fit_region(
    mesh: trimesh.Trimesh,
    axis: np.ndarray = np.array([0.0, 0.0, 1.0]),
    up_axis: np.ndarray = np.array([0.0, 1.0, 0.0]),
    anterior_axis: np.ndarray = np.array([1.0, 0.0, 0.0]),
    sector_deg: tuple[float, float] = (30.0, 120.0),
    max_axial_normal: float = 0.5,
) -> np.ndarray:
    """Vertex indices of the distal-posterior articular part of one condyle: vertices whose
    normal, projected on the sagittal plane, points between ``sector_deg[0]`` and
    ``sector_deg[1]`` degrees measured from distal (-up, 0 deg) towards posterior
    (-anterior, 90 deg), and whose normal component along ``axis`` is below ``max_axial_normal``
    (excludes the condyle side walls)."""
    n = mesh.vertex_normals
    ang = np.degrees(np.arctan2(n @ (-np.asarray(anterior_axis)), n @ (-np.asarray(up_axis))))
    ok = (ang >= sector_deg[0]) & (ang <= sector_deg[1]) & (np.abs(n @ axis) < max_axial_normal)
    return np.nonzero(ok)[0]


def fit_flexion_axis(
    medial: trimesh.Trimesh,
    lateral: trimesh.Trimesh,
    axis_guess: np.ndarray = np.array([0.0, 0.0, 1.0]),
    up_axis: np.ndarray = np.array([0.0, 1.0, 0.0]),
    anterior_axis: np.ndarray = np.array([1.0, 0.0, 0.0]),
    sector_deg: tuple[float, float] = (30.0, 120.0),
) -> dict[str, Any]:
    """Flexion axis = line through the centres of cylinders fitted to the distal-posterior
    articular surfaces of the medial and lateral condyles (see :func:`condyle_fit_region`).

    Each cylinder centre is the point of its fitted axis nearest to the centroid of its fitted
    points.  Returns dict(point (m, midpoint of the two centres), direction (unit, medial ->
    lateral), medial / lateral (per-cylinder fit: axis, centre, radius, rms, max_abs,
    n_points), rms (pooled RMS of both fits, m), angle_between_cylinder_axes_deg).
    """
    fits = {}
    for name, m in (("medial", medial), ("lateral", lateral)):
        idx = condyle_fit_region(m, axis_guess, up_axis, anterior_axis, sector_deg)
        fits[name] = _fit_cylinder(m.vertices[idx], axis_guess)
    c_m, c_l = fits["medial"]["centre"], fits["lateral"]["centre"]
    d = c_l - c_m
    d /= np.linalg.norm(d)
    nm, nl = fits["medial"]["n_points"], fits["lateral"]["n_points"]
    rms = np.sqrt((fits["medial"]["rms"] ** 2 * nm + fits["lateral"]["rms"] ** 2 * nl) / (nm + nl))
    cosang = abs(fits["medial"]["axis"] @ fits["lateral"]["axis"])
    return dict(point=0.5 * (c_m + c_l), direction=d, medial=fits["medial"],
                lateral=fits["lateral"], rms=float(rms),
                angle_between_cylinder_axes_deg=float(np.degrees(np.arccos(min(1.0, cosang)))))


# ----------------------------------------------------------------------------------------------
# brute-force oracle
# ----------------------------------------------------------------------------------------------
def reference_contact(
    femur_mesh: trimesh.Trimesh,
    tibia_points: np.ndarray,
    tibia_areas: np.ndarray,
    R: np.ndarray,
    p: np.ndarray,
    K: float = K_DEFAULT,
    delta: float = DELTA_DEFAULT,
    offset: float = 0.0,
) -> dict[str, Any]:
    """Brute-force elastic-foundation contact on the triangle mesh (the test oracle).

    Tibial points (N,3) [m, tibial frame] with lumped areas (N,) [m^2] are mapped into the
    femoral frame ``x = R x_tib + p``; exact signed distances to ``femur_mesh``
    (:func:`mesh_signed_distance` with ``certify=True``: proven exact, unlike
    ``trimesh.proximity.closest_point`` which can miss the closest face); pressure ``K g(-d)`` [Pa]; force on the tibia along the
    exact SDF gradient (outward femoral normal).  ``offset`` [m]: contact against the exact
    offset surface ``d_mesh = offset`` (e.g. bone + cartilage thickness).  Returns dict(force (3,) N, moment (3,) N m
    about the tibial origin, cop (3,) m = pressure*area-weighted mean contact point (femoral
    frame, NaN if no contact), pressure (N,) Pa, depth (N,) m = -d, n_contact, max_depth).
    """
    P = np.asarray(tibia_points, float) @ np.asarray(R, float).T + np.asarray(p, float)
    d, _, _, grad = mesh_signed_distance(femur_mesh, P, certify=True)
    d = d - offset
    pen = -d
    pres = K * smooth_gate(pen, delta)
    w = pres * np.asarray(tibia_areas, float)
    f = grad * w[:, None]
    force = f.sum(axis=0)
    moment = np.cross(P - p, f).sum(axis=0)
    cop = (P * w[:, None]).sum(axis=0) / w.sum() if w.sum() > 0 else np.full(3, np.nan)
    return dict(force=force, moment=moment, cop=cop, pressure=pres, depth=pen,
                n_contact=int((pres > 0).sum()), max_depth=float(pen.max()))


# ----------------------------------------------------------------------------------------------
# the smooth representation
# ----------------------------------------------------------------------------------------------
@dataclass
class FemoralSurface:
    """Narrow-band signed distance field of a femoral surface as a cubic tensor B-spline.

    Stored quantity ``e(x) = band - clip(d(x), -depth, band)`` (>= 0), so that
    ``e = 0`` -- hence no contact -- far outside the femur *and* everywhere outside the grid
    (the B-spline is exactly 0 beyond its knots).  ``d = band - e`` inside the band.
    Optional extra channels (``normal_mode='fitted'``) hold the exact SDF gradient sampled at
    the grid nodes, splined the same way (then the contact normal needs only first derivatives
    of the spline, which makes Jacobians/Hessians cheaper than differentiating ``e``).

    Grid nodes ``origin + spacing * (i, j, k)``, shape ``shape``; all lengths in metres.
    """

    origin: np.ndarray
    spacing: float
    shape: tuple[int, int, int]
    coeffs: np.ndarray  # (nx, ny, nz, m) B-spline coefficients
    band: float
    depth: float
    normal_mode: str
    info: dict[str, Any] = field(default_factory=dict)
    _fn: dict[str, ca.Function] = field(default_factory=dict, repr=False)

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_mesh(
        cls,
        mesh: trimesh.Trimesh,
        spacing: float = 5e-4,
        band: float = 2e-3,
        depth: float = 3e-3,
        box: tuple[np.ndarray, np.ndarray] | None = None,
        normal_mode: str = "fitted",
        offset: float = 0.0,
        k_candidates: int = 24,
        n_validate: int = 2000,
    ) -> "FemoralSurface":
        """Build from a triangle mesh (outward normals, metres).

        ``offset`` > 0 represents the exact outward offset surface ``{x: d_mesh(x) = offset}``
        with signed distance ``d = d_mesh - offset`` (exact outside the mesh): pass the
        subchondral bone and the cartilage thickness to get the articular surface without
        building (and possibly folding) an offset mesh.  Recommended for MRI bone meshes.

        ``box`` = (lo, hi) corners of the region to represent (default: mesh bounds); it is
        padded so that the outer 3 node layers are beyond ``band`` outside.  Exact distances
        are computed only for nodes within the band (+ one facet size + 2 spacings) with the fast
        k-candidate search (``k_candidates``), checked against the certified search on
        ``n_validate`` random nodes (``info['validate_max_err']``); other nodes get the clipped value with the sign of
        their nearest vertex normal.
        ``normal_mode``: 'fitted' (4 channels, recommended) or 'ad' (1 channel, normals by AD).
        """
        t0 = time.perf_counter()
        if box is None:
            lo, hi = mesh.bounds
        else:
            lo, hi = (np.asarray(b, float) for b in box)
        pad = band + 3 * spacing
        lo = lo - pad
        hi = hi + pad
        shape = tuple(int(np.ceil((hi[i] - lo[i]) / spacing)) + 1 for i in range(3))
        axes = [lo[i] + spacing * np.arange(shape[i]) for i in range(3)]
        G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        # near nodes: bounded nearest-sample query on dense samples (vertices + face centres)
        samples = np.vstack([mesh.vertices, mesh.triangles_center])
        facet = float(np.percentile(
            np.linalg.norm(mesh.triangles - mesh.triangles_center[:, None], axis=2).max(axis=1), 99.9))
        r_near = offset + max(band, depth) + facet + 2 * spacing
        da, _ = cKDTree(samples).query(G, 1, distance_upper_bound=r_near)
        near = np.isfinite(da)
        # far nodes: sign of the nearest vertex normal (bounded query; beyond 25 mm: outside)
        far = np.nonzero(~near)[0]
        df, iff = cKDTree(mesh.vertices).query(G[far], 1, distance_upper_bound=25e-3)
        ok = np.isfinite(df)
        sgn_far = np.ones(len(far))
        sgn_far[ok] = np.where(np.einsum("ij,ij->i", G[far[ok]] - mesh.vertices[iff[ok]],
                                         mesh.vertex_normals[iff[ok]]) < 0, -1.0, 1.0)
        d = np.empty(len(G))
        d[far] = np.where(sgn_far > 0, band, -depth)
        grad = np.zeros((len(G), 3))
        grad[far[ok]] = mesh.vertex_normals[iff[ok]]
        t1 = time.perf_counter()
        dn, _, _, gn = mesh_signed_distance(mesh, G[near], k=k_candidates, certify=False)
        d[near] = dn - offset
        grad[near] = gn
        t2 = time.perf_counter()
        # validate the fast exact distances on a random subset of the near nodes
        rng = np.random.default_rng(0)
        sub = rng.choice(np.nonzero(near)[0], size=min(n_validate, int(near.sum())), replace=False)
        dv = mesh_signed_distance(mesh, G[sub], certify=True)[0] if len(sub) else np.zeros(0)
        val_err = float(np.abs(dv - offset - d[sub]).max()) if len(sub) else 0.0
        e = band - np.clip(d, -depth, band)
        chans = [e]
        if normal_mode == "fitted":
            chans += [grad[:, 0], grad[:, 1], grad[:, 2]]
        elif normal_mode != "ad":
            raise ValueError("normal_mode must be 'fitted' or 'ad'")
        data = np.stack([c.reshape(shape) for c in chans], axis=-1)
        coeffs = np.empty_like(data)
        for c in range(data.shape[-1]):
            coeffs[..., c] = spline_filter(data[..., c], order=3, mode="nearest")
        t3 = time.perf_counter()
        info = dict(
            n_nodes=int(np.prod(shape)), n_exact=int(near.sum()), validate_max_err=val_err,
            n_validate=int(len(sub)),
            t_approx=t1 - t0, t_exact=t2 - t1, t_prefilter=t3 - t2, t_build=t3 - t0,
            coeff_bytes=int(coeffs.nbytes), mesh_faces=int(len(mesh.faces)), offset=offset,
        )
        return cls(origin=lo, spacing=spacing, shape=shape, coeffs=coeffs, band=band,
                   depth=depth, normal_mode=normal_mode, info=info)

    # -- persistence ---------------------------------------------------------------------------
    def save(self, path: str) -> None:
        """Save to a compressed .npz (coefficients, grid, band, depth, mode)."""
        np.savez_compressed(path, origin=self.origin, spacing=self.spacing,
                            shape=np.array(self.shape), coeffs=self.coeffs, band=self.band,
                            depth=self.depth, normal_mode=self.normal_mode)

    @classmethod
    def load(cls, path: str) -> "FemoralSurface":
        """Load what :meth:`save` wrote."""
        z = np.load(path)
        return cls(origin=z["origin"], spacing=float(z["spacing"]),
                   shape=tuple(int(v) for v in z["shape"]), coeffs=z["coeffs"],
                   band=float(z["band"]), depth=float(z["depth"]),
                   normal_mode=str(z["normal_mode"]))

    # -- numpy evaluation (same spline, for working sets / diagnostics) ------------------------
    def _index_coords(self, X: np.ndarray) -> np.ndarray:
        return ((np.asarray(X, float).reshape(-1, 3) - self.origin) / self.spacing).T

    def eval_np(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance d (N,) [m] and outward normal (N,3) of the spline at femoral-frame
        points X (N,3) [m], numpy/scipy (matches the CasADi spline inside the grid; outside
        the grid it returns d = band)."""
        ic = self._index_coords(X)
        e = map_coordinates(self.coeffs[..., 0], ic, order=3, prefilter=False, mode="constant")
        if self.normal_mode == "fitted":
            g = np.stack([map_coordinates(self.coeffs[..., c], ic, order=3, prefilter=False,
                                          mode="constant") for c in (1, 2, 3)], axis=1)
        else:
            h = 1e-6
            g = np.stack([-(map_coordinates(self.coeffs[..., 0], self._index_coords(
                X + h * np.eye(3)[c]), order=3, prefilter=False, mode="constant") - e) / h
                for c in range(3)], axis=1)
        g /= np.sqrt((g**2).sum(axis=1, keepdims=True) + 1e-6)
        return self.band - e, g

    # -- CasADi --------------------------------------------------------------------------------
    def spline_function(self) -> ca.Function:
        """``casadi.Function`` x (3,) [m, femoral frame] -> channel values (m,) of the spline:
        ``[e]`` or ``[e, gx, gy, gz]`` (``d = band - e``; g = fitted grad d)."""
        if "spline" not in self._fn:
            nx, ny, nz, m = self.coeffs.shape
            knots = [(self.origin[i] + self.spacing * (np.arange(self.shape[i] + 4) - 2)).tolist()
                     for i in range(3)]
            flat = self.coeffs.transpose(2, 1, 0, 3).ravel()  # m fastest, then x, y, z
            self._fn["spline"] = ca.Function.bspline("femur_sdf", knots, flat.tolist(),
                                                     [3, 3, 3], m, {})
        return self._fn["spline"]

    def signed_distance_function(self) -> ca.Function:
        """``casadi.Function`` sdf(x (3,)) -> (d [m], n (3,) unit outward normal)."""
        x = ca.MX.sym("x", 3)
        E = self.spline_function()(x)
        d = self.band - E[0]
        g = E[1:4] if self.normal_mode == "fitted" else -ca.gradient(E[0], x)
        n = g / ca.sqrt(ca.sumsqr(g) + 1e-6)
        return ca.Function("sdf", [x], [d, n], ["x"], ["d", "n"])

    def _wrench_expr(self, R: ca.MX, p: ca.MX, K: ca.MX, points: np.ndarray, areas: np.ndarray,
                     delta: float):
        P = ca.DM(np.asarray(points, float).T)  # 3 x N
        A = ca.DM(np.asarray(areas, float).reshape(1, -1))  # 1 x N
        N = P.shape[1]
        X = ca.mtimes(R, P) + ca.repmat(p, 1, N)  # femoral frame, 3 x N
        F = self.spline_function().map(N)
        if self.normal_mode == "fitted":
            E = F(X)
            e, g = E[0, :], E[1:4, :]
        else:  # normal = grad d by reverse AD through the mapped spline (one adjoint sweep)
            Xs = ca.MX.sym("X", 3, N)
            es = F(Xs)[0, :]
            gs = -ca.reshape(ca.jtimes(es, Xs, ca.DM.ones(1, N), True), 3, N)
            e, g = ca.Function("field", [Xs], [es, gs])(X)
        n = g / ca.repmat(ca.sqrt(ca.sum1(g * g) + 1e-6), 3, 1)
        w = K * smooth_gate(e - self.band, delta) * A  # 1 x N, pressure*area [N]
        f = n * ca.repmat(w, 3, 1)
        r = X - ca.repmat(p, 1, N)
        force = ca.sum2(f)
        mom = ca.vertcat(
            ca.sum2(r[1, :] * f[2, :] - r[2, :] * f[1, :]),
            ca.sum2(r[2, :] * f[0, :] - r[0, :] * f[2, :]),
            ca.sum2(r[0, :] * f[1, :] - r[1, :] * f[0, :]),
        )
        W = ca.sum2(w)
        cop = ca.sum2(X * ca.repmat(w, 3, 1)) / (W + 1e-300)
        return force, mom, cop, W, e

    def contact_wrench(self, points: np.ndarray, areas: np.ndarray,
                       delta: float = DELTA_DEFAULT, with_cop: bool = False) -> ca.Function:
        """``casadi.Function`` ``contact_wrench(R (3x3), p (3), K) -> (force (3), moment (3))``.

        ``points`` (N,3) tibial sample points [m, tibial frame], ``areas`` (N,) [m^2] are baked
        in as constants (pass a working set to make it cheaper).  ``R, p``: tibial frame in the
        femoral frame; K [N/m^3].  Force on the tibia [N] and moment about the tibial origin
        [N m], both in the femoral frame.  With ``with_cop`` two more outputs: ``cop`` (3) [m,
        femoral frame; pressure*area-weighted mean of the contact points, 0 if no contact] and
        ``load`` = sum p_i A_i [N].  Exactly zero (no NaN) for points outside the grid.
        """
        R = ca.MX.sym("R", 3, 3)
        p = ca.MX.sym("p", 3)
        K = ca.MX.sym("K")
        force, mom, cop, W, _ = self._wrench_expr(R, p, K, points, areas, delta)
        outs, names = [force, mom], ["force", "moment"]
        if with_cop:
            outs += [cop, W]
            names += ["cop", "load"]
        return ca.Function("contact_wrench", [R, p, K], outs, ["R", "p", "K"], names)

    # -- working set ---------------------------------------------------------------------------
    def working_set(self, points: np.ndarray, R: np.ndarray, p: np.ndarray,
                    margin: float = 1e-3) -> np.ndarray:
        """Indices of tibial points (N,3) [m, tibial frame] whose spline signed distance at
        pose (R, p) is below ``margin`` [m] (i.e. can touch if the pose changes by < margin)."""
        X = np.asarray(points, float) @ np.asarray(R).T + np.asarray(p)
        d, _ = self.eval_np(X)
        return np.nonzero(d < margin)[0]

    def check_excluded(self, points: np.ndarray, included: np.ndarray, R: np.ndarray,
                       p: np.ndarray) -> float:
        """Largest penetration depth [m] (= -min d) of the tibial points NOT in ``included`` at
        pose (R, p); <= 0 means the working set is still valid (no excluded point touches)."""
        mask = np.ones(len(points), bool)
        mask[np.asarray(included, int)] = False
        if not mask.any():
            return -np.inf
        X = np.asarray(points, float)[mask] @ np.asarray(R).T + np.asarray(p)
        d, _ = self.eval_np(X)
        return float(-d.min())
