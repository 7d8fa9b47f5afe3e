"""Shared fixtures.

``knee`` is the synthetic example knee (explicit spherical condyles): the machinery tests (identify,
nested, adequacy, design, export, studies) run on it because it is fast and its measured behaviour
is documented.  ``real_knee`` is the default knee (Lenhart 2015, mesh contact):
tests/test_real_knee.py checks it against its requirements.
"""

from __future__ import annotations

import pytest

import kneenlp
from kneenlp.experiment.kneemodel import KneeModel


@pytest.fixture(scope="session")
def knee():
    return kneenlp.Knee.named("synthetic")


@pytest.fixture(scope="session")
def model(knee):
    return KneeModel.of(knee)


@pytest.fixture(scope="session")
def set3(knee):
    return kneenlp.simulate(knee, "set3")


@pytest.fixture(scope="session")
def real_knee():
    return kneenlp.Knee.default()
