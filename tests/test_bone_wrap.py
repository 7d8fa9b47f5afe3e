"""A ligament path over a bone's own surface (kneenlp.model.bone_wrap): the knee file's table, its bad
input, the jumps it names, and (slow) a real knee's equilibrium with it."""

from __future__ import annotations

import numpy as np
import pytest

from kneenlp.base.errors import InputError
from kneenlp.model.bone_wrap import BoneWrap
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
