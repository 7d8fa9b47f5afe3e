"""The experiment as one unit (kneenlp.experiment.kind), and its worked example: a device that
reads only two coordinates and pushes at a named point, added by one file (tests/data/strap.toml)."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.experiment.kind import Experiment
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.protocol import Protocol

STRAP = Path(__file__).parent / "data" / "strap.toml"
#: sideways pushes at the ankle and internal-external moments, at two flexions (N, N m, deg)
PROTOCOL = {"name": "strap_test", "cases": [
    *({"name": f"push{f:+g}", "loads": {"lateral_force": f}, "flexion": [0.0, 30.0]} for f in (-15.0, 15.0)),
    *({"name": f"turn{m:+g}", "loads": {"internal_moment": m}, "flexion": [0.0, 30.0]} for m in (-3.0, 3.0)),
]}
FREE = ["MCL.k", "LCL.k"]


@pytest.fixture(scope="module")
def strap_data(tmp_path_factory, knee):
    """The device's noise-free data of the synthetic knee, as a file beside the device's file."""
    device = Experiment.load(STRAP)
    folder = tmp_path_factory.mktemp("strap")
    shutil.copy(STRAP, folder / "strap.toml")
    protocol = Protocol.from_dict(PROTOCOL)
    sim = kneenlp.simulate(knee, protocol, experiment=device)
    assert sim.converged == len(protocol)
    sim.measured().to_csv(folder / "data.csv", index=False)
    return read_measured(folder / "data.csv", protocol=protocol), sim


def test_the_data_declare_the_device_and_carry_only_what_it_reads(strap_data):
    data, _ = strap_data
    assert data.experiment.name == "strap" and not data.experiment.laboratory
    assert data.experiment.observed == ("varus_rotation", "internal_rotation")
    assert np.isfinite(data.q[:, :2]).all() and np.isnan(data.q[:, 2:]).all()
    assert all(np.allclose(t.point, [0.0, -0.35, 0.0]) for t in data.trials)


def test_the_force_acts_at_the_ankle(knee, strap_data):
    """The push at the ankle is the push at the tuberosity plus the couple of the arm between them
    (a pure moment, femoral frame); the knee pushed at the ankle ends elsewhere."""
    data, sim = strap_data
    model = KneeModel.of(knee)
    i, push = next((i, t) for i, t in enumerate(data.trials) if "push" in t.id)
    q, flexion, theta = sim.q[i], push.flexion, model.theta()
    R = np.asarray(model.pose(q, flexion, theta)[0])
    at_tuberosity = replace(push, point=None).load
    at_tuberosity[3:6] += np.cross(R @ (np.array([0.0, -0.35, 0.0]) - knee.tuberosity), push.load[0:3])
    np.testing.assert_allclose(np.asarray(model.evaluate(q, theta, push.load, flexion)).ravel(),
                               np.asarray(model.evaluate(q, theta, at_tuberosity, flexion)).ravel(), atol=1e-9)
    pushed_at_tuberosity = kneenlp.simulate(knee, Protocol.from_dict(PROTOCOL))
    assert np.abs(pushed_at_tuberosity.q[:, :2] - sim.q[:, :2]).max() > np.deg2rad(0.5)


def test_a_fit_of_the_device_data_recovers_the_knee_from_two_coordinates(knee, strap_data):
    data, sim = strap_data
    truth = {n: sim.parameters[n] for n in FREE}
    fit = kneenlp.identify(knee, data, free=FREE, start={n: 0.7 * v for n, v in truth.items()})
    assert fit.success and fit.n_observations == 2 * len(data)
    for n, v in truth.items():
        assert fit.params[n] == pytest.approx(v, rel=1e-4)
    assert np.isnan(fit.residuals[:, 2:]).all() and np.abs(fit.residuals[:, :2]).max() < 1e-4


def test_a_device_file_that_names_an_unknown_point_is_one_line(tmp_path):
    bad = tmp_path / "strap.toml"
    bad.write_text(STRAP.read_text().replace('load_point = "ankle"', 'load_point = "heel"'))
    with pytest.raises(InputError, match=r"strap.toml: load_point: unknown load point 'heel'; known: ankle"):
        Experiment.load(bad)


def test_data_with_a_coordinate_the_device_does_not_read_are_refused(tmp_path, strap_data):
    _, sim = strap_data
    shutil.copy(STRAP, tmp_path / "strap.toml")
    df = sim.measured()
    df["lateral_translation_mm"] = 0.0
    df.to_csv(tmp_path / "data.csv", index=False)
    with pytest.raises(InputError, match="lateral_translation_mm: experiment 'strap' does not observe"):
        read_measured(tmp_path / "data.csv")
    df.drop(columns="lateral_translation_mm").assign(experiment="stirrup").to_csv(tmp_path / "data.csv", index=False)
    with pytest.raises(InputError, match="unknown experiment 'stirrup'"):
        read_measured(tmp_path / "data.csv")


def test_older_files_keep_their_meaning(tmp_path):
    """A file without the column: laboratory with a side or joint loads, else simulated."""
    folder = Path(kneenlp.__file__).parent / "resources" / "datasets"
    real = read_measured(folder / "s192803_laxity.csv")
    assert real.experiment.laboratory
    text = (folder / "s192803_laxity.csv").read_text().replace(",experiment", "", 1).replace(",laboratory", "")
    (tmp_path / "old.csv").write_text(text)
    assert read_measured(tmp_path / "old.csv").experiment.laboratory


def test_a_ramp_scales_the_load_not_where_it_acts(strap_data):
    from kneenlp.base.conventions import scaled_load

    data, _ = strap_data
    load = next(t for t in data.trials if "push" in t.id).load
    half = scaled_load(load, 0.5)
    np.testing.assert_array_equal(half[:11], 0.5 * load[:11])
    np.testing.assert_array_equal(half[11:], load[11:])


def test_the_reduced_space_fit_of_two_coordinates_recovers_the_knee(knee, strap_data):
    """Gauss-Newton in reduced space (the calibration's and the rescue's solver) weighs the unread
    coordinates zero and starts them at the knee's reference pose."""
    from kneenlp.estimation.solve import reduced_fit
    from kneenlp.experiment.problem import IdentificationProblem

    data, sim = strap_data
    problem = IdentificationProblem.from_data(KneeModel.of(knee), data, FREE)
    assert np.isfinite(problem.measured_q).all()
    fit = reduced_fit(problem, {n: 0.7 * sim.parameters[n] for n in FREE})
    for n in FREE:
        assert fit.params[n] == pytest.approx(sim.parameters[n], rel=1e-4)


def test_what_needs_every_coordinate_refuses_in_one_line(knee, strap_data):
    data, _ = strap_data
    with pytest.raises(InputError, match=r"experiment: a calibration .* needs all five coordinates; experiment "
                                         r"'strap' observes varus_rotation, internal_rotation"):
        kneenlp.identify(knee, data, strategy="calibration")
    fit = kneenlp.identify(knee, data, free=FREE, start={n: 5000.0 for n in FREE})
    from kneenlp.adequacy.diagnosis import diagnose

    with pytest.raises(InputError, match="diagnose needs all five coordinates"):
        diagnose(fit)


FOOTPLATE = Path(__file__).parent / "data" / "footplate.toml"


@pytest.fixture(scope="module")
def footplate_data(tmp_path_factory, knee):
    """Set 1 on the rig that holds internal rotation, simulated through the command line (the
    experiment file copied beside the data), and read back."""
    from kneenlp.cli import main

    out = tmp_path_factory.mktemp("footplate")
    assert main(["simulate", "--knee", str(knee.source), "--protocol", "set1", "--experiment", str(FOOTPLATE),
                 "--noise", "uniform:0.5", "--seed", "3", "--no-plots", "--out", str(out)]) == 0
    assert (out / "footplate.toml").is_file()
    device = Experiment.load(FOOTPLATE)
    return read_measured(out / "measured.csv"), kneenlp.simulate(knee, "set1", experiment=device)


def test_a_held_coordinate_is_prescribed_and_the_others_balance(knee, footplate_data):
    """Every trial sits at 0 deg internal rotation exactly, converged; the internal moments move
    nothing (the rig carries them), the other loads move the knee as their equilibrium says."""
    data, sim = footplate_data
    assert data.experiment.held == {"internal_rotation": 0.0}
    assert sim.converged == len(sim.solutions)
    assert np.abs(sim.q[:, 1]).max() < 1e-12
    free = kneenlp.simulate(knee, "set1")
    turned = [i for i, s in enumerate(sim.solutions) if s.trial.loads.get("internal_moment", 0.0)]
    assert turned and np.abs(free.q[turned, 1]).max() > np.deg2rad(5)
    model = KneeModel.of(knee)
    for s in sim.solutions:  # the four free equations hold at the solved pose, the held one is its value
        r = np.asarray(model.evaluate(s.q, model.theta(), s.trial.load, s.trial.flexion)).ravel()
        assert np.abs(r[[0, 2, 3, 4]]).max() < 1e-6 and abs(r[1]) < 1e-9


def test_a_fit_of_the_rig_data_holds_each_trial_at_its_measured_rotation(knee, footplate_data):
    """The data observe the held rotation: each trial is held at its measured value, which is an
    input, not an observation (4 per trial); the fit recovers the ligaments from them."""
    data, sim = footplate_data
    assert all(t.held == ((1, pytest.approx(np.deg2rad(row[1]))),) for t, row in zip(data.trials, data.q_user,
                                                                                         strict=True))
    truth = {n: sim.parameters[n] for n in FREE}
    fit = kneenlp.identify(knee, data, free=FREE, start={n: 0.7 * v for n, v in truth.items()}, noise="uniform:0.5")
    assert fit.success and fit.n_observations == 4 * len(data)
    np.testing.assert_allclose(fit.q_pred[:, 1], np.deg2rad(data.q_user[:, 1]), atol=1e-12)
    for n, v in truth.items():
        assert fit.params[n] == pytest.approx(v, rel=0.1)
    with pytest.raises(InputError, match="holds internal_rotation"):
        data.check_observed("cross-validation")


@pytest.mark.parametrize("held, needle", [
    ("internal_rotatoin = 0.0", r"footplate.toml: held.internal_rotatoin: unknown coordinate 'internal_rotatoin'"),
    ("\n".join(f"{c} = 0.0" for c in ("varus_rotation", "internal_rotation", "lateral_translation",
                                      "anterior_translation", "proximal_translation")),
     r"footplate.toml: held: holds every coordinate"),
    ("internal_rotation = 400.0", r"footplate.toml: held.internal_rotation: 400 deg is beyond what a knee reaches"),
    ("internal_rotation = 0.0\n[points]\nankle = [0.0, -350000.0, 0.0]",
     r"footplate.toml: points.ankle: 350000 mm from the tibial origin, beyond 600 mm"),
])
def test_held_coordinates_that_leave_nothing_free_or_are_unknown_are_one_line(tmp_path, capsys, knee, held, needle):
    from kneenlp.cli import main

    bad = tmp_path / "footplate.toml"
    bad.write_text(FOOTPLATE.read_text().replace("internal_rotation = 0.0  # deg", held))
    assert main(["simulate", "--knee", str(knee.source), "--protocol", "set1", "--experiment", str(bad),
                 "--no-plots", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    import re

    assert re.search(needle, err), err


def test_a_preload_acts_at_its_own_point(knee, tmp_path):
    """A rig that pushes the drawer at the tuberosity and compresses the knee at the ankle: the
    wrench is the tuberosity's push plus the preload moved to the ankle (its couple); a preload
    point at the load point is the plain load; an unknown point is one line."""
    rig = Experiment("rig", points={"ankle": (0.0, -0.35, 0.02)}, preload_point="ankle")
    trial = Protocol.from_dict({"name": "pre", "cases": [{"name": "drawer", "flexion": [30.0],
                                "loads": {"anterior_force": 50.0, "proximal_force": 40.0}}]}).trials[0]
    (applied,) = rig.applied_to([trial])
    model = KneeModel.of(knee)
    q, theta = np.array([0.01, 0.02, 0.001, 0.002, -0.001]), model.theta()
    R = np.asarray(model.pose(q, trial.flexion, theta)[0])
    together = trial.load.copy()
    preload = np.array([0.0, 40.0, 0.0])  # femoral axes: the proximal force
    together[3:6] += np.cross(R @ (np.array([0.0, -0.35, 0.02]) - knee.tuberosity), preload)
    np.testing.assert_allclose(np.asarray(model.evaluate(q, theta, applied.load, trial.flexion)).ravel(),
                               np.asarray(model.evaluate(q, theta, together, trial.flexion)).ravel(), atol=1e-9)
    (same,) = Experiment("same", preload_point="tibial_tuberosity").applied_to([trial])
    np.testing.assert_array_equal(same.load, trial.load)
    bad = tmp_path / "rig.toml"
    bad.write_text('name = "rig"\npreload_point = "heel"\n')
    with pytest.raises(InputError, match=r"rig.toml: preload_point: unknown preload point 'heel'"):
        Experiment.load(bad)
