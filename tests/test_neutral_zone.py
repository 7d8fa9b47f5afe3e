"""The apparatus' dead band in the loaded direction (kneenlp.experiment.parts.NeutralZone).

Oracles: the closed form of the reading (the knee's pose plus the half-width in the load's sense at
the loaded coordinate, nothing elsewhere: the laxity widened by twice the half-width), and the
identification of noise-free data made with a known band.
"""

from __future__ import annotations

import numpy as np
import pytest

import kneenlp
from kneenlp.base.conventions import COORDINATES, TO_USER
from kneenlp.experiment.measured import read_measured

BAND = {"neutral_zone.anterior_translation": 1.5e-3, "neutral_zone.internal_rotation": np.deg2rad(2.0)}


@pytest.fixture(scope="module")
def banded(knee):
    """Set 3 of the synthetic knee read through a dead band, and read without one."""
    return kneenlp.simulate(knee, "set3"), kneenlp.simulate(knee, "set3", parameters=BAND)


def test_a_dead_band_moves_the_reading_in_the_loads_sense_and_no_pose(banded):
    plain, with_band = banded
    np.testing.assert_array_equal(plain.q, with_band.q)  # the knee itself is the same
    cols = [c for c in with_band.measured().columns if c.startswith(COORDINATES)]
    shift = with_band.measured()[cols].to_numpy() - plain.measured()[cols].to_numpy()
    expected = np.zeros_like(shift)
    for i, s in enumerate(with_band.solutions):
        word = s.trial.dominant
        sign = {"anterior": 1, "posterior": -1, "internal": 1, "external": -1}.get(word, 0)
        j = COORDINATES.index("anterior_translation" if word in ("anterior", "posterior") else "internal_rotation")
        if sign:
            expected[i, j] = sign * BAND[f"neutral_zone.{COORDINATES[j]}"] * TO_USER[j]
    assert np.count_nonzero(expected) > 0 and any(s.trial.dominant in ("varus", "none") for s in with_band.solutions)
    np.testing.assert_allclose(shift, expected, atol=1e-12)


def test_the_identification_recovers_the_band_beside_the_ligaments(knee, banded, tmp_path):
    _, with_band = banded
    path = tmp_path / "measured.csv"
    with_band.measured().to_csv(path, index=False)
    free = ["ACL.k", "PCL.k", *BAND]
    truth = {n: with_band.parameters[n] for n in free}
    fit = kneenlp.identify(knee, read_measured(path), free=free, start={"ACL.k": 0.8 * truth["ACL.k"]})
    assert fit.success
    for name, value in truth.items():
        assert fit.params[name] == pytest.approx(value, rel=1e-4), name


def test_a_band_is_a_candidate_of_the_adequacy_check_and_never_negative(knee):
    model = kneenlp.experiment.kneemodel.KneeModel.of(knee)
    effect = model.effect("neutral_zone")
    assert effect.free_names() == [f"neutral_zone.{c}" for c in COORDINATES[:4]]
    assert all(model.parameter(n).bounds[0] == 0.0 and model.parameter(n).one_sided for n in effect.free_names())
