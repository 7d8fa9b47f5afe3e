"""Shared fixtures.

``knee`` is the synthetic example knee (explicit spherical condyles): the machinery tests (identify,
nested, adequacy, design, export, studies) run on it because it is fast and its measured behaviour
is documented.  ``real_knee`` is the default knee (Lenhart 2015, mesh contact):
tests/test_real_knee.py checks it against its requirements.

The suite runs CasADi's own evaluation (``KNEENLP_COMPILE=off``, :mod:`kneenlp.base.compiled`): it
builds many models once each, and a compile per model would cost more than it saves;
tests/test_compiled.py tests the compiled functions.
"""

from __future__ import annotations

import os

import pytest

import kneenlp
from kneenlp.experiment.kneemodel import KneeModel

os.environ["KNEENLP_COMPILE"] = "off"  # before any model is built; subprocesses (the CLI's tests) inherit it


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
