"""Geometry under the contact model: exact mesh distances, the distance field, axes and frames."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from kneenlp.geometry.axes import fit_cylinder, rotation_about
from kneenlp.geometry.distance import MeshDistance
from kneenlp.geometry.sdf import DistanceField


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
    """kneenlp.geometry.kernels (numba) against DistanceField.evaluate and mesh_contact.wrench_expansion
    (NumPy), and the field's values against scipy's own B-spline interpolation."""
    from scipy.ndimage import map_coordinates

    from kneenlp.geometry import kernels
    from kneenlp.model.mesh_contact import wrench_expansion

    mesh, half = box
    fld = DistanceField.from_mesh(mesh, np.array([-half - 3e-3, half + 3e-3]), spacing=0.5e-3)
    rng = np.random.default_rng(3)
    pts = rng.uniform([-6e-3, half[1] - 0.8e-3, -5e-3], [6e-3, half[1] + 0.1e-3, 5e-3], (300, 3))
    scipy_values = map_coordinates(fld.coeffs, ((pts - fld.origin) / fld.spacing).T, order=3, prefilter=False)
    assert np.allclose(fld.evaluate(pts)[0], scipy_values, rtol=0, atol=1e-15)
    n = len(pts)
    d, g, h, t3 = np.empty(n), np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3, 3, 3))
    kernels.field_derivatives(fld.coeffs, fld.origin, fld.spacing, pts, d, g, h, t3)
    for got, ref in zip((d, g, h, t3), fld.evaluate(pts, order=3), strict=True):
        assert np.allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    r = pts - [0.0, -0.02, 0.0]  # arms from a tibial origin below the plateau
    areas = rng.uniform(0.2e-6, 0.6e-6, n)
    for got, ref in zip(kernels.wrench_expansion(d, g, h, t3, r, areas, 1e-5),
                        wrench_expansion(d, g, h, t3, pts, r, areas, 1e-5), strict=True):
        assert np.allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
