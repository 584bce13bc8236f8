"""TrackedSequence file format."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nvp.errors import FormatError
from nvp.tracked import TrackedSequence


def make(t=5, k=4):
    rng = np.random.default_rng(0)
    return TrackedSequence(
        fps=25.0,
        width=64,
        height=48,
        focal=500.0,
        center=np.array([32.0, 24.0], np.float32),
        identity=rng.normal(size=3).astype(np.float32),
        rotation=np.tile(np.eye(3, dtype=np.float32), (t, 1, 1)),
        translation=rng.normal(size=(t, 3)).astype(np.float32),
        expression=rng.normal(size=(t, k)).astype(np.float32),
        landmarks=rng.normal(size=(t, 7, 2)).astype(np.float32),
        valid=np.ones(t, bool),
        fit_error=np.zeros(t, np.float32),
        face_model_sha256="abc",
        info={"note": "test"},
    )


def test_round_trip(tmp_path):
    seq = make()
    seq.save(tmp_path / "track")
    back = TrackedSequence.load(tmp_path / "track")
    for name in ("rotation", "translation", "expression", "landmarks", "valid", "identity"):
        np.testing.assert_array_equal(getattr(back, name), getattr(seq, name))
    assert back.fps == 25.0 and back.info == {"note": "test"} and back.face_model_sha256 == "abc"
    assert back.iris is None  # tracked before nvp kept the iris


def test_the_iris_travels_with_the_frames_and_the_file(tmp_path):
    import dataclasses

    iris = np.random.default_rng(1).normal(size=(5, 2, 3)).astype(np.float32)
    seq = dataclasses.replace(make(), iris=iris)
    seq.save(tmp_path / "track")
    np.testing.assert_array_equal(TrackedSequence.load(tmp_path / "track").iris, iris)
    np.testing.assert_array_equal(seq.frames(np.array([4, 1])).iris, iris[[4, 1]])
    with pytest.raises(FormatError, match="iris"):
        dataclasses.replace(seq, iris=iris[:3])


def test_save_replaces_existing_and_keeps_other_files(tmp_path):
    out = tmp_path / "track"
    make(t=5).save(out)
    (out / "preview.mp4").write_bytes(b"x")
    make(t=9).save(out)
    assert TrackedSequence.load(out).num_frames == 9
    assert (out / "preview.mp4").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["track"]  # no temp dirs left behind


def test_shape_mismatch_is_rejected():
    seq = make()
    with pytest.raises(FormatError, match="expression"):
        TrackedSequence(**{**seq.__dict__, "expression": np.zeros((3, 4), np.float32)})


def test_load_errors(tmp_path):
    with pytest.raises(FormatError):
        TrackedSequence.load(tmp_path / "nothing")
    make().save(tmp_path / "t")
    m = json.loads((tmp_path / "t" / "tracked.json").read_text())
    m["version"] = 7
    (tmp_path / "t" / "tracked.json").write_text(json.dumps(m))
    with pytest.raises(FormatError, match="version"):
        TrackedSequence.load(tmp_path / "t")


def test_head_keeps_camera_and_identity(face_model):
    from tracking.synthetic import synthetic_tracked

    seq = synthetic_tracked(face_model, frames=10)
    first = seq.head(4)
    assert first.num_frames == 4 and first.landmarks.shape[0] == first.valid.shape[0] == 4
    np.testing.assert_array_equal(first.expression, seq.expression[:4])
    np.testing.assert_array_equal(first.identity, seq.identity)
    assert first.focal == seq.focal
