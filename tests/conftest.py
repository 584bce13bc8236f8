"""Shared fixtures: tiny synthetic data made in code."""

from __future__ import annotations

import pytest

from nvp.face_model import default_face_model
from tracking.synthetic import synthetic_sequence


@pytest.fixture(scope="session")
def face_model():
    return default_face_model()


@pytest.fixture(scope="session")
def synthetic():
    return synthetic_sequence
