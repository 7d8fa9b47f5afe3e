"""Geometry under the contact model: exact mesh distances, the distance field, axes and frames."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from kneenlp.geometry.axes import fit_cylinder, rotation_about
from kneenlp.geometry.distance import MeshDistance
from kneenlp.geometry.sdf import DistanceField
from kneenlp.model.articular import Compartment
from kneenlp.model.laws import ElasticFoundation, PowerFoundation


def box_sdf(points: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Closed-form signed distance of an axis-aligned box centred at the origin."""
    q = np.abs(points) - half
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(np.max(q, axis=1), 0)
    return outside + inside


@pytest.fixture(scope="module")
def box():
    """A 20 x 12 x 16 mm box in metres, with sub-millimetre faces (the scale of segmented knees)."""
    half = np.array([10e-3, 6e-3, 8e-3])
    mesh = trimesh.creation.box(extents=2 * half)
    for _ in range(5):
        mesh = mesh.subdivide()
    return mesh, half


def test_mesh_distance_is_exact_against_the_closed_form(box):
    mesh, half = box
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1.3 * half, 1.3 * half, (3000, 3))
    d, _, grad = MeshDistance(mesh)(pts)
    assert np.max(np.abs(d - box_sdf(pts, half))) < 1e-12
    assert np.allclose(np.linalg.norm(grad, axis=1), 1.0)
    # the same mesh in millimetres gives the same distances (the routine is unit-free)
    d_mm = MeshDistance(trimesh.Trimesh(mesh.vertices * 1e3, mesh.faces))(pts * 1e3)[0]
    assert np.max(np.abs(d_mm * 1e-3 - d)) < 1e-12


def test_distance_field_matches_the_exact_distance_in_its_band(box):
    mesh, half = box
    fld = DistanceField.from_mesh(mesh, np.array([-half - 3e-3, half + 3e-3]), spacing=0.5e-3)
    assert fld.info["checked_points"] > 1000
    rng = np.random.default_rng(1)
    # within the accurate band (-1.5 to 0.5 mm) of the middle of the top face, away from the edges
    # and corners, which the field rounds within a few grid cells
    pts = rng.uniform([-5e-3, half[1] - 1.5e-3, -4e-3], [5e-3, half[1] + 0.5e-3, 4e-3], (500, 3))
    d, g, h, t3 = fld.evaluate(pts, order=3)
    assert np.max(np.abs(d - box_sdf(pts, half))) < 1e-6
    assert np.allclose(g, [0.0, 1.0, 0.0], atol=1e-2)  # |grad d| = 1 within the clips' rounding
    # derivatives are those of the same spline (central differences)
    e = 1e-7
    for a in range(3):
        step = e * np.eye(3)[a]
        dp, gp, hp = fld.evaluate(pts + step, order=2)
        dm, gm, hm = fld.evaluate(pts - step, order=2)
        assert np.allclose((dp - dm) / (2 * e), g[:, a], atol=1e-6)
        assert np.allclose((gp - gm) / (2 * e), h[:, a, :], atol=1e-3 * np.abs(h).max() + 1e-6)
        # the third derivative is constant within a grid cell: compare where both sides share a cell
        same = np.all(np.floor((pts + step - fld.origin) / fld.spacing) == np.floor((pts - step - fld.origin)
                                                                                    / fld.spacing), axis=1)
        assert np.allclose(((hp - hm) / (2 * e))[same], t3[same, a], atol=1e-3 * np.abs(t3).max() + 1e-3)


def test_cylinder_fit_recovers_a_known_cylinder():
    rng = np.random.default_rng(2)
    axis = rotation_about([1.0, 0.0, 0.0], 0.05) @ [0.0, 0.0, 1.0]
    centre, radius = np.array([-3e-3, 1e-3, 0.0]), 19e-3
    u = np.cross(axis, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    t = rng.uniform(0.5, 2.5, 800)
    z = rng.uniform(-10e-3, 10e-3, 800)
    pts = centre + np.outer(z, axis) + radius * (np.outer(np.cos(t), u) + np.outer(np.sin(t), w))
    fit = fit_cylinder(pts + rng.normal(0, 1e-6, pts.shape), [0.0, 0.0, 1.0])
    assert abs(fit.radius - radius) < 1e-6 and fit.rms < 2e-6
    assert abs(abs(fit.axis @ axis) - 1) < 1e-8
    assert np.linalg.norm(np.cross(fit.centre - centre, axis)) < 1e-6


def test_compiled_kernels_equal_the_numpy_references(box):
    """kneenlp.geometry.kernels and spline_kernels (numba) against DistanceField.evaluate and
    mesh_contact.wrench_expansion (NumPy), and the field's values against scipy's own B-spline interpolation."""
    from scipy.ndimage import map_coordinates

    from kneenlp.geometry import kernels, spline_kernels
    from kneenlp.model.mesh_contact import wrench_expansion

    mesh, half = box
    fld = DistanceField.from_mesh(mesh, np.array([-half - 3e-3, half + 3e-3]), spacing=0.5e-3)
    rng = np.random.default_rng(3)
    pts = rng.uniform([-6e-3, half[1] - 0.8e-3, -5e-3], [6e-3, half[1] + 0.1e-3, 5e-3], (300, 3))
    scipy_values = map_coordinates(fld.coeffs, ((pts - fld.origin) / fld.spacing).T, order=3, prefilter=False)
    assert np.allclose(fld.evaluate(pts)[0], scipy_values, rtol=0, atol=1e-15)
    n = len(pts)
    d, g, h, t3 = np.empty(n), np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3, 3, 3))
    spline_kernels.field_derivatives(fld.spline, pts, (d, g, h, t3))
    for got, ref in zip((d, g, h, t3), fld.evaluate(pts, order=3), strict=True):
        assert np.allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    r = pts - [0.0, -0.02, 0.0]  # arms from a tibial origin below the plateau
    areas = rng.uniform(0.2e-6, 0.6e-6, n)
    law = ElasticFoundation()
    one, zero = np.ones(n), np.zeros((n, 3, 3))
    for got, ref in zip(kernels.wrench_expansion((d, g, h, t3), (r, areas), (one, zero[:, 0], zero),
                                                 (law.kernel, 1e-5), 2),
                        wrench_expansion((d, g, h, t3), (r, areas), 1e-5), strict=True):
        assert np.allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def test_cell_minimum_is_the_smallest_coefficient_of_each_cell():
    """Brute force: every cell's 64 coefficients (lower node i: coefficients i-1 .. i+2 per axis)."""
    from kneenlp.geometry.spline_kernels import cell_minimum

    c = np.random.default_rng(0).normal(size=(7, 6, 8))
    got = cell_minimum(c)
    for i, j, k in np.ndindex(*c.shape):
        block = c[max(i - 1, 0):i + 3, max(j - 1, 0):j + 3, max(k - 1, 0):k + 3]
        assert got[i, j, k] == block.min()  # at the border: the part of the block inside the grid


def test_cell_lower_bound_bounds_the_spline_in_every_cell_and_passes_over_more_than_the_smallest_coefficient():
    """Oracle: the spline evaluated at 20 000 random points of a distance field's grid is never below
    its cell's bound, and the bound is above the smallest coefficient in most cells near the surface."""
    from kneenlp.geometry.spline_kernels import cell_lower_bound, cell_minimum

    x, y, z = np.meshgrid(*[np.arange(12) * 1e-3] * 3, indexing="ij")
    coeffs = np.sqrt((x - 5.5e-3) ** 2 + (y - 5e-3) ** 2 + (z - 6e-3) ** 2) - 3e-3  # a sphere's distance
    fld = DistanceField(np.zeros(3), 1e-3, coeffs, band=1.0, depth=1.0)
    bound, smallest = cell_lower_bound(coeffs), cell_minimum(coeffs)
    lo, hi = fld.bounds
    pts = lo + (hi - lo) * np.random.default_rng(1).random((20000, 3))
    cell = np.floor(pts / 1e-3).astype(int)
    values = fld.evaluate(pts)[0]
    assert np.all(values >= bound[cell[:, 0], cell[:, 1], cell[:, 2]] - 1e-15)
    near = (values > 0) & (values < 2e-3)
    tighter = bound[cell[near, 0], cell[near, 1], cell[near, 2]] > smallest[cell[near, 0], cell[near, 1], cell[near, 2]]
    assert np.all(bound >= smallest) and tighter.mean() > 0.5


def test_a_pressure_law_given_as_a_compiled_function_equals_the_built_in_family():
    """A user's law as a compiled function (the pass compiled for it in the process) gives what the
    built-in power family's exponent gives (the pass loaded from the machine's cache)."""
    from numba import njit

    from kneenlp.geometry import kernels
    from kneenlp.geometry.ramp import gate_derivatives

    @njit
    def user_power(s, width):  # d_r (g / d_r)^1.5, written out as a user would
        g, g1, g2 = gate_derivatives(s, width)
        if g <= 0.0:
            return 0.0, 0.0, 0.0
        r = np.sqrt(g / kernels.REFERENCE_DEPTH)
        return g * r, 1.5 * r * g1, 0.75 * g1 * g1 / (kernels.REFERENCE_DEPTH * r) + 1.5 * r * g2

    for s in (-1e-6, 0.0, 3e-6, 1e-5, 2e-4, 1e-3, 2.5e-3):
        assert np.allclose(kernels.pressure_at(user_power, s, 1e-5), kernels.pressure_at(1.5, s, 1e-5),
                           rtol=1e-13, atol=0.0)
        assert kernels.pressure_at(1.0, s, 1e-5) == pytest.approx(gate_derivatives(s, 1e-5), rel=0, abs=0)


@pytest.mark.slow
def test_the_contact_pass_of_a_built_in_law_is_compiled_once_per_machine(tmp_path):
    """A second process loads the compiled contact pass from the cache (before the built-in laws
    were exponents, every process compiled it again: ~15 s at the first contact evaluation)."""
    import os
    import subprocess
    import sys

    script = """
import numpy as np
from kneenlp.geometry import kernels
from kneenlp.model.laws import ElasticFoundation
c = np.zeros((6, 6, 6)); pts = np.zeros((1, 3)); R = np.eye(3)[None]; p = np.zeros((1, 3))
out = np.empty((1, 271))
none = np.zeros((0, 0, 0))
femur = ((c, np.zeros(3), 1e-3), c, (none, none), (np.zeros(3), np.ones(3) * 1e-3), 1e-3)
kernels.contact_batch((femur, (pts, np.ones(1))), (R, p, 0, 1), (ElasticFoundation().kernel, 1e-5), 2, out)
print(len(kernels.contact_batch.stats.cache_misses), len(kernels.contact_batch.stats.cache_hits))
"""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    runs = [subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
            for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[-1].stderr[-2000:]
    first, second = (tuple(map(int, r.stdout.split())) for r in runs)
    assert first[0] == 1  # compiled in the first process ...
    assert second == (0, 1)  # ... and loaded in the second


@pytest.mark.parametrize("law", [ElasticFoundation(), PowerFoundation()], ids=lambda law: law.name)
def test_batched_contact_pass_equals_the_numpy_expansion_over_every_point(box, law):
    """The compiled pass over all poses (cell-minimum rejection, then the expansion) against the
    NumPy reference summed over every penetrating point, for each pressure law; the passes of
    order 0 (value) and 1 (Jacobian) give the same wrench (and Jacobian), zeros beyond."""
    from kneenlp.geometry import kernels
    from kneenlp.model.kinematics import rot_x, rot_y
    from kneenlp.model.mesh_contact import WS_SIZE, wrench_expansion

    mesh, half = box
    fld = DistanceField.from_mesh(mesh, np.array([-half - 3e-3, half + 3e-3]), spacing=0.5e-3)
    rng = np.random.default_rng(5)
    points = np.column_stack([rng.uniform(-6e-3, 6e-3, 400), np.zeros(400), rng.uniform(-5e-3, 5e-3, 400)])
    areas = rng.uniform(0.2e-6, 0.6e-6, 400)
    T = 4
    R = np.stack([np.asarray(rot_x(0.02 * t) @ rot_y(-0.03 * t), float) for t in range(T)])
    p = np.array([[0.0, half[1] - 0.3e-3 * (t + 1), 0.1e-3 * t] for t in range(T)])  # 0.3 .. 1.2 mm into the top
    rows = {}
    for order in (2, 1, 0):
        out = np.empty((T, WS_SIZE))
        kernels.contact_batch(kernels.compartment(fld, points, areas), (R, p, 0, T), (law.kernel, 1e-5), order, out)
        rows[order] = out
    for t in range(T):
        X = points @ R[t].T + p[t]
        d = fld.evaluate(X)[0]
        sel = (d < 0) & (d > -0.99 * fld.depth)
        d, g, h, t3 = fld.evaluate(X[sel], order=3)
        W, J, H = wrench_expansion((d, g, h, t3), (X[sel] - p[t], areas[sel]), 1e-5, law)
        row = rows[2][t]
        assert np.allclose(row[:9].reshape(3, 3, order="F"), R[t]) and np.allclose(row[9:12], p[t])
        for got, ref in ((row[12:18], W), (row[18:54].reshape(6, 6, order="F"), J),
                         (row[54:-1].reshape(6, 6, 6).transpose(0, 2, 1), H)):
            assert np.allclose(got, ref, rtol=1e-10, atol=1e-10 * max(np.abs(ref).max(), 1e-30))
        assert row[-1] == pytest.approx(max(-d.min(), 0.0) if len(d) else 0.0, abs=1e-15)
        value, first = rows[0][t], rows[1][t]
        assert np.allclose(value[12:18], W, rtol=1e-10, atol=1e-10 * max(np.abs(W).max(), 1e-30))
        assert not np.any(value[18:-1]) and value[-1] == pytest.approx(row[-1], abs=1e-15)
        assert np.array_equal(first[:54], row[:54]) and first[-1] == row[-1]  # order 1: the same wrench, Jacobian
        assert not np.any(first[54:-1])
    assert np.any(rows[2][:, 12:18]) and np.any(rows[2][:, 54:-1])  # the poses do touch


def _split_edge(mesh: trimesh.Trimesh, face: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """The mesh's vertices with the midpoint of the first edge of ``face`` added, its faces, and the
    (a, b, midpoint) indices."""
    v, f = np.asarray(mesh.vertices).copy(), np.asarray(mesh.faces).copy()
    a, b, _ = f[face]
    return np.vstack([v, 0.5 * (v[a] + v[b])]), f, (a, b, len(v))


def test_a_rim_is_where_the_surface_ends_not_a_crack_or_a_sliver():
    """A closed surface stays closed with a T-junction (a vertex on the next face's edge), a face with
    a repeated vertex, or a zero-area face along an edge; a cropped surface keeps every edge of its
    cut, and nothing else (checked against the edge count of the cut, an independent count)."""
    from kneenlp.geometry.rim import OpenEdges

    sphere = trimesh.creation.icosphere(3)
    assert OpenEdges(sphere).closed
    v, f, (a, b, m) = _split_edge(sphere, 0)
    c = f[0, 2]
    t_junction = trimesh.Trimesh(v, np.vstack([f[1:], [[a, m, c], [m, b, c]]]), process=False)
    assert OpenEdges(t_junction).closed
    sliver = trimesh.Trimesh(v, np.vstack([f, [[a, b, m]]]), process=False)
    assert OpenEdges(sliver).closed
    repeated = trimesh.Trimesh(sphere.vertices, np.vstack([sphere.faces, [[0, 0, 1]]]), process=False)
    assert OpenEdges(repeated).closed
    keep = sphere.triangles_center[:, 2] < 0.5
    cropped = trimesh.Trimesh(sphere.vertices, sphere.faces[keep], process=True)
    cut = len(trimesh.grouping.group_rows(cropped.edges_sorted, require_count=1))
    assert len(OpenEdges(cropped)) == cut > 0
    v, f, (a, b, m) = _split_edge(cropped, 0)  # a T-junction inside the cropped surface
    c = f[0, 2]
    assert len(OpenEdges(trimesh.Trimesh(v, np.vstack([f[1:], [[a, m, c], [m, b, c]]]), process=False))) == cut


def _half_plate(spacing: float = 0.5e-3) -> trimesh.Trimesh:
    """A flat sheet z = 0 (outward normal +z) over x in [-10, 0] mm, y in [-8, 8] mm: a surface cropped
    along x = 0, its rim."""
    x, y = np.arange(-10e-3, 1e-9, spacing), np.arange(-8e-3, 8e-3 + 1e-9, spacing)
    v = np.array([(a, b, 0.0) for a in x for b in y])
    ny = len(y)
    f = []
    for i in range(len(x) - 1):
        for j in range(ny - 1):
            a, b, c, d = i * ny + j, (i + 1) * ny + j, (i + 1) * ny + j + 1, i * ny + j + 1
            f += [[a, b, c], [a, c, d]]
    return trimesh.Trimesh(v, np.array(f), process=False)


@pytest.fixture(scope="module")
def half_plate():
    mesh = _half_plate()
    fld = DistanceField.from_mesh(mesh, np.array([[-12e-3, -9e-3, -3e-3], [4e-3, 9e-3, 3e-3]]), spacing=0.5e-3)
    return mesh, fld


def test_a_cropped_surface_ends_at_its_rim(half_plate):
    """The contact weight of a surface cropped along x = 0: exactly 1 two and a half spacings inside,
    exactly 0 as far beyond, a half at the rim; within [0, 1] everywhere."""
    _, fld = half_plate
    assert fld.weights is not None and fld.info["rim_edges"] == 2 * (20 + 32)  # the sheet's four sides
    x = np.linspace(-5e-3, 3e-3, 161)
    pts = np.column_stack([x, 0.7e-3 * np.sin(40 * x), np.full_like(x, -0.4e-3)])
    w = fld.weight_spline.evaluate(pts)[0]
    assert np.allclose(w[x <= -2.5 * fld.spacing], 1.0, rtol=0, atol=1e-12) and np.all(w[x >= 2.5 * fld.spacing] == 0)
    assert np.all((w >= 0) & (w <= 1 + 1e-12)) and np.all(np.diff(w) <= 1e-12)
    assert fld.weight_spline.evaluate(np.array([[0.0, 0.0, -0.4e-3]]))[0][0] == pytest.approx(0.5, abs=0.02)


def test_the_weighted_contact_pass_equals_the_numpy_expansion_and_its_own_derivatives(half_plate):
    """Over a cropped surface, the compiled pass (weight included) against the NumPy expansion with the
    weight's value, gradient and Hessian, and its Jacobian and Hessian against central differences of
    its own wrench and Jacobian over rigid displacements of the tibia."""
    from kneenlp.geometry import kernels
    from kneenlp.model.kinematics import rot_x, rot_z
    from kneenlp.model.mesh_contact import WS_SIZE, wrench_expansion

    _, fld = half_plate
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.uniform(-5e-3, 3e-3, 500), rng.uniform(-6e-3, 6e-3, 500), np.zeros(500)])
    areas = rng.uniform(0.2e-6, 0.4e-6, 500)

    def rows(R: np.ndarray, p: np.ndarray, order: int = 2) -> np.ndarray:
        out = np.empty((len(R), WS_SIZE))
        kernels.contact_batch(kernels.compartment(fld, points, areas), (R, p, 0, len(R)), (1.0, 1e-5), order, out)
        return out

    R0, p0 = np.asarray(rot_x(0.03) @ rot_z(-0.02), float), np.array([0.2e-3, 0.1e-3, -0.6e-3])
    row = rows(R0[None], p0[None])[0]
    X = points @ R0.T + p0
    d = fld.evaluate(X)[0]
    sel = (d < 0) & (d > -0.99 * fld.depth)
    d, g, h, t3 = fld.evaluate(X[sel], order=3)
    weight = fld.weight_spline.evaluate(X[sel], order=2)
    W, J, H = wrench_expansion((d, g, h, t3), (X[sel] - p0, areas[sel]), 1e-5, None, weight)
    assert 0.05 < np.mean(weight[0]) < 0.95  # the contact straddles the rim
    for got, ref in ((row[12:18], W), (row[18:54].reshape(6, 6, order="F"), J),
                     (row[54:-1].reshape(6, 6, 6).transpose(0, 2, 1), H)):
        assert np.allclose(got, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
    # central differences over xi = (u, w): X(xi) = exp([w]x) (X - p0) + p0 + u, as the expansion
    step = np.array([1e-7] * 3 + [1e-5] * 3)
    for c in range(6):
        xi = np.zeros(6)
        xi[c] = step[c]
        poses = [(np.asarray(trimesh.transformations.rotation_matrix(np.linalg.norm(s * xi[3:]), s * xi[3:]
                                                                    if np.any(xi[3:]) else [1, 0, 0])[:3, :3]) @ R0,
                  p0 + s * xi[:3]) for s in (1.0, -1.0)]
        plus, minus = rows(np.stack([poses[0][0], poses[1][0]]), np.stack([poses[0][1], poses[1][1]]))
        dW = (plus[12:18] - minus[12:18]) / (2 * step[c])
        dJ = ((plus[18:54] - minus[18:54]) / (2 * step[c])).reshape(6, 6, order="F")
        assert np.allclose(dW, J[:, c], rtol=1e-4, atol=1e-4 * np.abs(J).max())
        Hc = np.array([H[k][:, c] for k in range(6)])  # d J[k, e] / d xi_c = H[k][e, c]
        assert np.allclose(dJ, Hc, rtol=2e-3, atol=2e-3 * np.abs(H).max())


def test_the_brute_force_reference_ends_a_cropped_surface_at_its_rim(half_plate):
    """Tibial points 0.4 mm below the cropped sheet, half of them under it and half beyond its edge:
    the exact contact counts those under it only (the closed form), and the model's weighted contact
    (the weight's fall is symmetric about the rim) agrees with it to 1 %."""
    from kneenlp.geometry.rim import OpenEdges
    from kneenlp.model.mesh_contact import MeshContact
    from kneenlp.testing.reference import ExactSurface, reference_contact

    mesh, fld = half_plate
    gx, gy = np.meshgrid(np.arange(-4.9e-3, 5e-3, 0.2e-3), np.arange(-5e-3, 5.01e-3, 0.2e-3), indexing="ij")
    points = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, -0.4e-3)])
    areas = np.full(len(points), 0.04e-6)
    K = 1e10
    contact = MeshContact(Compartment("medial", None, points, areas, np.zeros(3)), fld, 1e-5)
    ref = reference_contact(ExactSurface(MeshDistance(mesh), 0.0, OpenEdges(mesh)), contact, (np.eye(3), np.zeros(3)),
                            K)
    under = points[:, 0] < 0
    assert ref.force[2] == pytest.approx(K * 0.4e-3 * areas[under].sum(), rel=1e-3)
    got = contact.pressure(np.eye(3), np.zeros(3), K)
    assert got["force"][2] == pytest.approx(ref.force[2], rel=0.01)


@pytest.mark.parametrize("layout", ["vector", "loop"])
def test_the_exported_contact_of_a_cropped_surface_is_the_compiled_one(half_plate, layout):
    """The contact in the CasADi graph (what ``export`` writes) weighs by the rim weight as the
    compiled pass does: the same wrench at a pose straddling the rim."""
    import casadi as ca

    from kneenlp.model.kinematics import rot_x
    from kneenlp.model.mesh_contact import MeshContact

    _, fld = half_plate
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(-4e-3, 3e-3, 300), rng.uniform(-5e-3, 5e-3, 300), np.zeros(300)])
    contact = MeshContact(Compartment("medial", None, points, np.full(300, 0.04e-6), np.zeros(3)), fld, 1e-5)
    R, p, K = np.asarray(rot_x(0.02), float), np.array([0.1e-3, 0.0, -0.5e-3]), 1e10
    probe = ca.MX(ca.DM(np.concatenate([R.ravel(order="F"), p, [K]])))
    got = np.asarray(ca.evalf(ca.vertcat(*contact.exact_wrench(probe, layout)))).ravel()
    W = K * contact.working_data(R, p, {})[12:18]
    assert np.allclose(got, W,
                       rtol=1e-9, atol=1e-9 * np.abs(W).max())
    assert 0 < contact.rim_batch(R[None], p[None])[0] < 1  # the rim carries part of it


@pytest.fixture(scope="module")
def cartilage_shell():
    """A closed cylindrical layer 3 mm thick about the Z axis (inner radius 30 mm, outer 33 mm, 24 mm
    long; metres): the shape of a condyle's cartilage, with rim walls at its ends."""
    n = 256  # a ring of quads between two circles of the same angles, at each end and on each wall
    a = 2 * np.pi * np.arange(n) / n
    rings = [np.c_[r * np.cos(a), r * np.sin(a), np.full(n, z)] for r, z in
             ((33e-3, -12e-3), (33e-3, 12e-3), (30e-3, 12e-3), (30e-3, -12e-3))]
    vertices = np.vstack(rings)
    faces = []
    for k in range(4):  # outer wall, top rim, inner wall, bottom rim: ring k to ring k + 1
        b, c = k * n, ((k + 1) % 4) * n
        for i in range(n):
            j = (i + 1) % n
            faces += [[b + i, b + j, c + j], [b + i, c + j, c + i]]
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    for _ in range(2):
        mesh = mesh.subdivide()
    return mesh


def test_a_cartilage_shell_is_deep_below_its_articular_side_not_its_mid_plane(cartilage_shell):
    """Pressed into a closed 3 mm layer, the plain signed distance turns at mid-thickness (1.5 mm:
    the contact force would turn); the shell's field is the depth below the articular (outer) side,
    the closed form ``r - 33 mm``, through the layer and behind it, and the rim walls belong to the
    articular side (a point beside the layer's edge is outside)."""
    from kneenlp.geometry.shell import ShellDistance, articular_faces, shell_thickness

    mesh = cartilage_shell
    assert mesh.is_watertight and shell_thickness(mesh) == pytest.approx(2 * mesh.volume / mesh.area)
    assert 2.5e-3 < shell_thickness(mesh) < 3e-3
    assert shell_thickness(trimesh.creation.box(extents=[0.04, 0.04, 0.04])) is None  # a bone: 13 mm
    side = articular_faces(mesh, np.zeros(3), np.array([0.0, 0, 1]))
    radius = np.linalg.norm(mesh.triangles_center[:, :2], axis=1)
    wall = np.abs(mesh.face_normals[:, 2]) < 0.1
    assert np.all(side[radius > 32.9e-3]) and not np.any(side[(radius < 30.1e-3) & wall])
    assert np.all(side[np.abs(mesh.face_normals[:, 2]) > 0.99])  # the rim walls
    r = np.linspace(27e-3, 35e-3, 33)
    pts = np.c_[r * np.cos(0.3), r * np.sin(0.3), np.zeros_like(r)]
    plain = MeshDistance(mesh)(pts)[0]
    d, _, grad = ShellDistance(mesh, side)(pts)
    assert np.max(np.abs(d - (r - 33e-3))) < 2e-6  # the closed form, 6 mm deep
    assert np.allclose(grad @ np.array([np.cos(0.3), np.sin(0.3), 0]), 1.0, atol=1e-3)
    assert plain[r == 31.5e-3].item() == pytest.approx(-1.5e-3, abs=2e-6) and plain[r == 30.5e-3].item() > -1.0e-3
    beside = np.array([[31.5e-3, 0, 13e-3]])  # 1 mm beyond the top rim wall
    assert ShellDistance(mesh, side)(beside)[0].item() == pytest.approx(1e-3, abs=2e-6)
    box = np.array([[24e-3, 5e-3, -6e-3], [36e-3, 14e-3, 6e-3]])  # a sector of the layer
    fld = DistanceField.from_mesh(mesh, box, spacing=0.5e-3, articular=side)
    accurate = (r >= 31.5e-3) & (r <= 34e-3)  # the field's accurate band, -1.5 to 1 mm
    assert np.max(np.abs(fld.evaluate(pts[accurate])[0] - (r[accurate] - 33e-3))) < 20e-6
    assert np.all(np.diff(fld.evaluate(pts[(r >= 30.5e-3) & (r < 34e-3)])[0]) > 1e-4)  # deeper down to the clip
