"""A ligament path over a bone's own surface (kneenlp.model.bone_wrap): the knee file's table, its bad
input, the jumps it names, and (slow) a real knee's equilibrium with it."""

from __future__ import annotations

import numpy as np
import pytest

from kneenlp.base.errors import InputError
from kneenlp.model.bone_wrap import BONE_REACH, BoneWrap
from tests.test_paths import _knee_with_wrap
from tests.test_taut_path import Cylinder

BONE = '\n[ligaments.MCL.wrap]\nshape = "bone"\nbody = "tibia"\n'


def test_a_path_over_a_bone_needs_the_bones_mesh(tmp_path):
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap\.body: a path over the tibia's surface needs its mesh"):
        _knee_with_wrap(tmp_path, BONE)


def test_a_bone_path_takes_no_obstacle_keys(tmp_path):
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap\.centre.*centre belongs to a cylinder, not a bone"):
        _knee_with_wrap(tmp_path, BONE + "centre = [0.0, 0.0, 0.0]\n")


def test_a_path_over_a_bone_names_where_it_jumps():
    """An attachment deeper in the bone than attachments lie, and a straight line through the bone's
    middle (where the side the path goes round flips), are named; a smooth wrap is not."""
    path = BoneWrap(Cylinder(), "femur")
    rotation, origin = np.eye(3), np.zeros(3)
    S, E = np.array([-0.03, 0.004, 0.0]), np.array([0.025, 0.002, 0.01])
    assert path.jump(E, S, rotation, origin) == ""
    through = np.array([0.025, 0.0005, 0.01]), np.array([-0.03, 0.0, 0.0])  # 0.3 mm from the axis
    assert "near its middle" in path.jump(*through, rotation, origin)
    assert "tibial attachment lies inside" in path.jump(E, np.array([0.005, 0.0, 0.0]), rotation, origin)
    assert path.jump(E, np.array([0.0099, 0.0, 0.0]), rotation, origin) == ""  # on the surface: an attachment


class CutCylinder(Cylinder):
    """The cylinder's field on a grid cut at :data:`BONE_REACH` below the knee (the shaft goes on)."""

    spacing = 1e-3
    bounds = np.array([[-0.03, -0.03, -BONE_REACH + 1e-3], [0.03, 0.03, 0.01]])


def test_an_attachment_beyond_where_the_bones_field_was_cut_is_named():
    """Below the cut the bone goes on unseen (a path there would cut through it): named; above the
    mesh's own box (no bone there) and inside the grid: not."""
    path = BoneWrap(CutCylinder(), "tibia")
    rotation, origin = np.eye(3), np.zeros(3)
    femur, tibia = np.array([0.012, 0.0, 0.03]), np.array([0.012, 0.0, -0.07])
    assert path.uncovered(femur, tibia, rotation, origin) == []
    assert path.uncovered(femur, np.array([0.012, 0.0, -0.085]), rotation, origin) == ["tibial"]


def test_the_banded_kkt_solve_is_the_dense_one_and_a_singular_step_is_least_squares():
    """The KKT systems are banded node by node (taut_path.BANDWIDTH): the banded solve equals the
    dense one; a contact whose distance has no gradient (a node deeper than the field's clip) makes
    its system singular: that path's step is the least-squares one, the others' are unchanged."""
    from kneenlp.geometry.taut_path import BANDWIDTH, _node_major, _solve

    K = 4
    order, _, _ = _node_major(K)
    rng = np.random.default_rng(0)
    near = np.abs(np.subtract.outer(np.arange(5 * K), np.arange(5 * K))) <= BANDWIDTH
    M = np.zeros((3, 5 * K, 5 * K))
    M[:, order[:, None], order[None, :]] = rng.normal(size=(3, 5 * K, 5 * K)) * near + 4 * np.eye(5 * K)
    M[1, 7] = 0.0
    b = rng.normal(size=(3, 5 * K, 1))
    x = _solve(M, b)
    assert np.all(np.isfinite(x))
    for i in (0, 2):
        assert np.allclose(x[i], np.linalg.solve(M[i], b[i]), rtol=1e-10, atol=1e-12)
    assert np.allclose(x[1], np.linalg.lstsq(M[1], b[1], rcond=None)[0])


def _s192803_smcl_over_the_tibia(tmp_path):
    """The shipped S192803 knee with its superficial MCL's three groups over the tibia's surface."""
    import shutil

    import kneenlp
    from kneenlp.base.resources import resource

    folder = tmp_path / "s192803-wrapped"
    shutil.copytree(resource("knees", "s192803"), folder)
    with open(folder / "knee.toml", "a") as f:
        for group in ("MCLa", "MCLm", "MCLp"):
            f.write(f'\n[ligaments.{group}.wrap]\nshape = "bone"\nbody = "tibia"\n')
    return kneenlp.Knee.load(folder)


@pytest.mark.slow
def test_a_real_knee_over_its_bone_keeps_exact_derivatives_and_reaches_equilibrium(tmp_path, capsys):
    """S192803 with its superficial MCL over the tibia, made taut: at the straight knee's equilibrium
    of a valgus trial the wrap changes the residual (the straight lines cut the tibia), the Jacobian
    the model evaluates (the path's Lagrangian at that pose's data) is the central difference of the
    residual with the paths solved again at each pose, and the wrapped knee reaches equilibrium.  An
    export (a self-contained graph, which a path solved outside CasADi cannot join) is refused in
    one line naming the bundle."""
    import kneenlp
    from kneenlp.base.resources import resource
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.experiment.measured import read_measured
    from kneenlp.experiment.protocol import Loading
    from kneenlp.prediction.predict import predict

    taut = {f"{g}.ref_strain_offset": 0.2 for g in ("MCLa", "MCLm", "MCLp")}  # slack at the source values
    model = KneeModel.of(_s192803_smcl_over_the_tibia(tmp_path))
    straight = KneeModel.of(kneenlp.Knee.named("s192803"))
    data = read_measured(resource("datasets", "s192803_laxity.csv"))
    valgus = data.subset(np.array([t.id == "valgus_flex30" for t in data.trials]))
    q = np.array([predict(straight, valgus, taut).solutions[0].q])
    theta, loading = model.theta(taut), Loading.of(valgus.trials)
    r, J = model.trial_derivatives(q, theta, loading, threads=1)
    assert np.abs(r).max() > 1.0, r  # N, N m: the straight knee is at equilibrium there
    h = 1e-6
    for j in range(5):
        step = np.zeros((1, 5))
        step[0, j] = h
        up, _ = model.trial_derivatives(q + step, theta, loading, threads=1)
        down, _ = model.trial_derivatives(q - step, theta, loading, threads=1)
        column = (up - down)[0] / (2 * h)
        assert np.allclose(column, J[0, :, j], rtol=1e-4, atol=1e-4 * np.abs(J[0]).max()), (j, column, J[0, :, j])
    prediction = predict(model, valgus, taut)
    assert prediction.converged.all(), prediction.report()
    from kneenlp.cli import main

    csv = str(resource("datasets", "s192803_laxity.csv"))
    knee = str(tmp_path / "s192803-wrapped" / "knee.toml")
    for form in ("nl", "casadi"):
        assert main(["export", csv, "--knee", knee, "--format", form, "--approximate", "--out", str(tmp_path)]) == 2
    assert "ligament MCLa bundle" in capsys.readouterr().err
