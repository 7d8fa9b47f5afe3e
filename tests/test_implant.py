"""The implant example knee (``Knee.named("implant")``): a synthetic total knee arthroplasty built by
:mod:`kneenlp.model.implant`, mesh contact in both compartments."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import kneenlp
from kneenlp.geometry.distance import signed_distance
from kneenlp.model import implant

MESHES = ("femur_component.stl", "inlay.stl")


@pytest.fixture(scope="module")
def implant_knee() -> kneenlp.Knee:
    return kneenlp.Knee.named("implant")


def test_implant_knee_loads_with_two_mesh_compartments(implant_knee):
    assert implant_knee.name == "implant"
    assert set(implant_knee.compartments) == {"medial", "lateral"}
    assert not any(c.sphere for c in implant_knee.compartments.values())
    assert implant_knee.femur is not None and implant_knee.femur.offset == 0.0
    assert set(implant_knee.ligaments) == {"ACL", "PCL", "MCL", "LCL"}
    medial, lateral = (implant_knee.compartments[n].points[:, 2].mean() for n in ("medial", "lateral"))
    assert medial == pytest.approx(-0.021, abs=1e-3) and lateral == pytest.approx(0.021, abs=1e-3)  # m


def test_generator_reproduces_shipped_meshes(tmp_path):
    implant.write_implant_knee(tmp_path)
    for name in MESHES:
        shipped = trimesh.load(implant.IMPLANT_DIR / "meshes" / name)
        fresh = trimesh.load(tmp_path / "meshes" / name)
        assert shipped.vertices.shape == fresh.vertices.shape, name
        assert np.allclose(shipped.vertices, fresh.vertices), name


def test_reference_pose_just_touches():
    """At 0 deg flexion, all coordinates zero, the component penetrates the inlay by 0.05-0.3 mm."""
    femur, inlay = implant.femoral_component(), implant.inlay_surface()
    depth = -signed_distance(femur, inlay.vertices)[0].min()  # mm
    assert 0.05 <= depth <= 0.3
    lowest = femur.vertices[np.argmin(femur.vertices[:, 1])]
    assert lowest[1] == pytest.approx(-21.0, abs=0.05)


@pytest.mark.slow
def test_set3_converges_and_loads_move_the_tibia_their_way(implant_knee):
    result = kneenlp.simulate(implant_knee, "set3")
    assert not result.failed, [(s.trial.id, s.reason) for s in result.failed]
    assert result.converged == 26
    assert result.max_residual <= 1e-6
    table = result.table()
    at0 = table[table.flexion_deg == 0.0]
    loads = {"anterior_force_N": "anterior_translation_mm", "varus_moment_Nm": "varus_rotation_deg",
             "internal_moment_Nm": "internal_rotation_deg"}
    unloaded = at0[(at0[list(loads)] == 0.0).all(axis=1)]
    assert len(unloaded) == 1
    for load, coordinate in loads.items():
        reference = unloaded[coordinate].iloc[0]
        positive, negative = at0[at0[load] > 0], at0[at0[load] < 0]
        assert len(positive) == 2 and len(negative) == 2, load
        assert (positive[coordinate] > reference).all(), (load, positive[coordinate].tolist(), reference)
        assert (negative[coordinate] < reference).all(), (load, negative[coordinate].tolist(), reference)


def test_open_edges_distance_is_the_distance_to_the_border():
    """Oracle: a flat square (2 x 2, z = 0) has its border as open edges; the distance of a point
    to it is the closed form of the distance to a square's boundary."""
    from kneenlp.geometry.rim import OpenEdges

    u = np.linspace(-1.0, 1.0, 9)
    x, y = np.meshgrid(u, u, indexing="ij")
    vertices = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    square = trimesh.Trimesh(vertices, implant._grid_faces(9, 9, False))
    rim = OpenEdges(square)
    assert not rim.closed and len(rim) == 32
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, (200, 3))
    ax, ay = np.abs(pts[:, 0]), np.abs(pts[:, 1])
    inside = (ax <= 1) & (ay <= 1)
    planar = np.where(inside, np.minimum(1 - ax, 1 - ay),
                      np.hypot(np.maximum(ax - 1, 0), np.maximum(ay - 1, 0)))
    exact = np.hypot(planar, pts[:, 2])
    np.testing.assert_allclose(rim.distance(pts), exact, atol=1e-12)
    # with an upper bound: the same distances where within it, inf beyond (the midpoint prefilter)
    np.testing.assert_array_equal(rim.distance(pts, upper=0.3), np.where(exact <= 0.3, rim.distance(pts), np.inf))
    assert 0 < np.sum(exact <= 0.3) < len(pts)
    assert OpenEdges(trimesh.creation.icosphere()).closed


@pytest.mark.parametrize("half_width", [10.0, 8.0])
def test_a_cropped_femur_ends_at_its_edge_and_notes_what_beyond_it_carries(tmp_path, half_width):
    """An implant femur cropped to 10 mm condyle half width (the inlay reaches 15 mm): the report
    says the mesh is open where the tibia reaches, and Set 3 solves every trial, valgus at 30 deg
    with a few per cent of its lateral force at the edge (the surface ends there).  Cropped to 8 mm,
    no trial is refused for its edge: those with more than 5 % of a compartment's force beyond it are
    solved with a note naming that share.  The shipped implant (17 mm) is open too, but not where the
    tibia reaches."""
    from kneenlp.base.resources import resource
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.model.mesh_contact import RIM_SHARE
    from kneenlp.simulation import simulate

    implant.write_implant_knee(tmp_path, implant.FemoralComponent(half_width=half_width))
    toml = tmp_path / "knee.toml"
    table1 = str(resource("parameters", "table1.toml"))
    toml.write_text(toml.read_text().replace("../../parameters/table1.toml", table1))
    cropped = kneenlp.Knee.load(tmp_path)
    assert "open where the tibia reaches" in cropped.open_edge_note()
    out = simulate(cropped, "set3")
    model = KneeModel.of(cropped)
    share = {s.trial.id: model.rim_share(s.q, model.theta(), s.trial.flexion) for s in out.solutions}
    noted = {s.trial.id: s.note for s in out.solutions if "open edge" in s.note}
    assert not any("open edge" in s.reason for s in out.solutions)  # computed, not refused
    if half_width == 10.0:
        assert out.converged == len(out.solutions)
        assert not noted and 0.0 < share["valgus_10Nm_flex30"] <= RIM_SHARE
    else:
        assert noted and all(share[t] > RIM_SHARE and f"{100 * share[t]:.1f} %" in r for t, r in noted.items())
        assert all(bool(s.note) == (share[s.trial.id] > RIM_SHARE) for s in out.solutions if s.converged)
    assert "not where the tibia reaches" in kneenlp.Knee.named("implant").open_edge_note()
