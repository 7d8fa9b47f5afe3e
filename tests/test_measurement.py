"""The experiment's description is its own layer (kneenlp.experiment.parts): force elements
only add forces, experiment parts only change how the knee is flexed, loaded and read."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from kneenlp.base.conventions import LOAD_SIZE
from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.parts import ExperimentPart, Measurement
from kneenlp.model.elements import ForceElement
from kneenlp.model.knee import Knee
from kneenlp.model.parameters import Parameter

HOOKS = ("flexion_offset", "measurement_bias", "load_point_offset", "tibial_axes", "joint_origin_offset")


class AnteriorBias(ExperimentPart):
    """A user's part: the tracker reads every anterior translation ``bias.anterior`` too far."""

    name = "bias"

    def parameters(self) -> list[Parameter]:
        return [Parameter("bias.anterior", "length", "anterior bias of the tracker", 0.0, 0.0)]

    def measurement_bias(self, pose, values) -> ca.SX:
        return ca.vertcat(0, 0, 0, values["bias.anterior"], 0)


@pytest.fixture(scope="module")
def knee() -> Knee:
    return Knee.named("synthetic")


def test_force_elements_only_add_forces():
    assert not [h for h in HOOKS if hasattr(ForceElement, h)]
    assert all(hasattr(ExperimentPart, h) for h in HOOKS)
    assert not any(isinstance(p, ForceElement) for p in Measurement.standard().parts)


def test_the_standard_experiment_at_zero_is_the_bare_knee(knee):
    """Without any experiment part the residual and the observation are the standard model's with
    every experiment parameter at zero, bit for bit."""
    standard, bare = KneeModel(knee), KneeModel(knee, measurement=Measurement(()))
    experiment = {p.name for part in standard.measurement.parts for p in part.parameters()}
    assert experiment and not experiment & set(bare.parameter_names)
    assert [n for n in standard.parameter_names if n not in experiment] == bare.parameter_names
    rng = np.random.default_rng(3)
    theta_s, theta_b = standard.theta(), bare.theta()
    for _ in range(5):
        q = rng.normal(0, [0.05, 0.1, 1e-3, 2e-3, 1e-3])
        load, flexion = rng.normal(0, 10, LOAD_SIZE), rng.uniform(0, 1.5)
        ws_s = standard.working_data(q, theta_s, flexion)
        ws_b = bare.working_data(q, theta_b, flexion)
        r_s = np.asarray(standard.residual(q, theta_s, load, flexion, ws_s)).ravel()
        r_b = np.asarray(bare.residual(q, theta_b, load, flexion, ws_b)).ravel()
        np.testing.assert_array_equal(r_s, r_b)
        np.testing.assert_array_equal(standard.observe(q, theta_s, load, flexion),
                                      bare.observe(q, theta_b, load, flexion))


def test_a_user_part_changes_the_reading_not_the_forces(knee):
    model = KneeModel(knee, extra_elements=[AnteriorBias()])
    assert model.parameter_names[-1] == "bias.anterior" and model.element("bias").name == "bias"
    q, flexion = np.array([0.01, -0.05, 1e-3, 2e-3, -1e-3]), 0.5
    theta0, theta1 = model.theta(), model.theta({"bias.anterior": 1.5e-3})
    unloaded = np.zeros(LOAD_SIZE)
    y0, y1 = model.observe(q, theta0, unloaded, flexion)[0], model.observe(q, theta1, unloaded, flexion)[0]
    np.testing.assert_allclose(y1 - y0, [0, 0, 0, 1.5, 0], atol=1e-12)  # mm
    ws = model.working_data(q, theta0, flexion)
    load = np.zeros(LOAD_SIZE)
    np.testing.assert_array_equal(np.asarray(model.residual(q, theta0, load, flexion, ws)),
                                  np.asarray(model.residual(q, theta1, load, flexion, ws)))


def test_a_part_of_neither_kind_is_refused(knee):
    with pytest.raises(InputError, match="neither a ForceElement nor an ExperimentPart"):
        KneeModel(knee, extra_elements=[object()])
