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


@pytest.fixture(scope="session")
def demo_clip(tmp_path_factory):
    """A 1.2 s, 256x256 talking clip (mp4 with audio) animated from the astronaut photo."""
    from nvp.app.demo_clip import make_demo_clip

    path = tmp_path_factory.mktemp("demo") / "clip.mp4"
    return make_demo_clip(path, seconds=1.2, size=256)
