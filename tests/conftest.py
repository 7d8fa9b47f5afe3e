"""Shared fixtures: the default knee, its model and Set 3 simulated once per session."""

from __future__ import annotations

import pytest

import kneenlp
from kneenlp.simulation import model_for


@pytest.fixture(scope="session")
def knee():
    return kneenlp.Knee.default()


@pytest.fixture(scope="session")
def model(knee):
    return model_for(knee)


@pytest.fixture(scope="session")
def set3(knee):
    return kneenlp.simulate(knee, "set3")
