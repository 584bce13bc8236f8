"""The upper face audio does not decide (nvp.upper_face) and the gaze (nvp.gaze): a person's blinks and brows
learned from footage and sampled for new speech; gaze tracks, files and eye rotations."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nvp.errors import NvpError
from nvp.gaze import gaze_direction, gaze_quaternions, gaze_track, read_gaze_file
from nvp.upper_face import (
    BLINK_BELOW,
    PRIOR_BLINKS_PER_MIN,
    PRIOR_MINUTES,
    blink_runs,
    brow_height,
    eye_openness,
    learn_upper_face,
    upper_face_motion,
)

FPS = 25.0


def _landmarks(model, expression: np.ndarray) -> np.ndarray:
    return model.vertices(np.zeros(model.num_id, np.float32), expression)[:, model.landmark_vertices]


def _strongest(model, measure) -> int:
    """The expression coefficient that moves ``measure`` of the mesh the most (per unit)."""
    eye = np.eye(model.num_exp, dtype=np.float32)
    base = measure(_landmarks(model, 0 * eye[:1]))[0]
    return int(np.argmax(np.abs(measure(_landmarks(model, eye)) - base)))


def _footage(model, seconds: float, blinks_per_min: float, rng) -> tuple[np.ndarray, int, int]:
    """Expressions of a person who blinks (3 frames, along the coefficient that closes the eyes most) at a
    known rate and raises their brows (along the one that moves them most), with small noise elsewhere."""
    n = int(seconds * FPS)
    blink_k, brow_k = _strongest(model, eye_openness), _strongest(model, brow_height)
    assert blink_k != brow_k
    base = _landmarks(model, np.zeros((1, model.num_exp), np.float32))
    closing = eye_openness(_landmarks(model, np.eye(model.num_exp, dtype=np.float32)[[blink_k]]))[0]
    shut = -1.2 * eye_openness(base)[0] / (closing - eye_openness(base)[0])  # eyes nearly closed at -1.2 x
    expr = 0.05 * rng.normal(size=(n, model.num_exp)).astype(np.float32)
    gap = 60.0 / blinks_per_min
    for start in np.arange(1.0, seconds - 0.5, gap):
        f = int(start * FPS)
        expr[f : f + 3, blink_k] += shut
    expr[:, brow_k] += np.sin(np.arange(n) / FPS * 1.7).astype(np.float32)  # brows up and down
    return expr, blink_k, brow_k


def test_eye_openness_and_brow_height_read_the_mesh(face_model):
    rest = _landmarks(face_model, np.zeros((1, face_model.num_exp), np.float32))
    assert 0.15 < eye_openness(rest)[0] < 0.6 and brow_height(rest)[0] > 0
    closed = rest.copy()
    for up, lo in ((159, 145), (386, 374)):  # lids together
        closed[:, up] = closed[:, lo] = 0.5 * (rest[:, up] + rest[:, lo])
    assert eye_openness(closed)[0] == pytest.approx(0.0, abs=1e-6)
    raised = rest.copy()
    raised[:, [105, 334], 1] -= 0.5  # the brows 0.5 cm up (y down in the face-model frame)
    assert brow_height(raised)[0] > brow_height(rest)[0]
    o = np.array([0.3, 0.3, 0.1, 0.1, 0.3, 0.3, 0.1, 0.3, 0.3])
    assert blink_runs(o, np.ones(9, bool)) == [(2, 2), (6, 1)]
    assert BLINK_BELOW * 0.3 > 0.1


def test_a_persons_blinks_and_brows_are_learned_and_sampled_for_new_speech(face_model):
    rng = np.random.default_rng(0)
    expr, blink_k, brow_k = _footage(face_model, 60.0, 20.0, rng)
    upper = learn_upper_face(_landmarks(face_model, expr), expr, np.ones(len(expr), bool), FPS)
    blinks = len(np.arange(1.0, 59.5, 3.0))
    assert upper.blinks_per_min == pytest.approx(
        (blinks + PRIOR_BLINKS_PER_MIN * PRIOR_MINUTES) / (1.0 + PRIOR_MINUTES), rel=1e-6
    )
    assert upper.blink_s == pytest.approx(3 / FPS)
    assert int(np.argmax(np.abs(upper.blink))) == blink_k
    assert int(np.argmax(np.abs(upper.brow))) == brow_k
    footage_brows = brow_height(_landmarks(face_model, expr))
    assert upper.brow_low < upper.brow_rest < upper.brow_high <= footage_brows.max()
    # 60 s of new speech: blinks at the person's rate, brows moving inside their footage's range
    t = np.arange(int(60 * 16000)) / 16000
    audio = (np.sin(2 * np.pi * 150 * t) * (0.2 + 0.8 * (np.sin(2 * np.pi * 0.4 * t) > 0))).astype(np.float32)
    voice = np.ones(int(60 * FPS), np.float32)
    motion = upper_face_motion(upper, audio, 16000, voice, FPS, seed=3)
    out = _landmarks(face_model, motion)
    rate = len(blink_runs(eye_openness(out), np.ones(len(out), bool)))
    assert 0.7 * upper.blinks_per_min <= rate <= 1.3 * upper.blinks_per_min
    h = brow_height(out)
    assert h.min() >= upper.brow_low - 0.02 * abs(upper.brow_low) and h.max() <= upper.brow_high * 1.02
    assert h.std() > 0.2 * footage_brows.std()  # they move, with the speech's emphasis
    np.testing.assert_array_equal(motion, upper_face_motion(upper, audio, 16000, voice, FPS, seed=3))
    # silence: no brow raised, blinks go on
    quiet = upper_face_motion(upper, audio * 0, 16000, voice * 0, FPS, seed=3)
    assert (
        np.ptp(brow_height(_landmarks(face_model, quiet))[eye_openness(_landmarks(face_model, quiet)) > 0.2])
        < 0.05
    )


def test_footage_without_blinks_gets_the_prior_rate_and_no_blink_shape(face_model):
    expr = np.zeros((250, face_model.num_exp), np.float32)  # 10 s, eyes open, brows still
    upper = learn_upper_face(_landmarks(face_model, expr), expr, np.ones(250, bool), FPS)
    assert upper.blink is None and upper.brow is None
    assert upper.blinks_per_min == pytest.approx(
        PRIOR_BLINKS_PER_MIN * PRIOR_MINUTES / (10 / 60 + PRIOR_MINUTES)
    )
    assert not np.any(upper_face_motion(upper, np.zeros(16000), 16000, np.ones(25), FPS))


def test_gaze_rotations_round_trip_and_turn_forward_where_asked():
    gaze = np.radians([[0, 0], [20, 0], [0, 15], [-30, -10], [44, 44]])
    q = gaze_quaternions(gaze)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(gaze_direction(q), gaze, atol=1e-5)
    # yaw 20: forward turns towards +X (the face's left); pitch 15: up (+Y)
    x, y, z, w = q[1]
    assert 2 * (x * z + w * y) == pytest.approx(np.sin(np.radians(20)), abs=1e-6)
    x, y, z, w = q[2]
    assert 2 * (y * z - w * x) == pytest.approx(np.sin(np.radians(15)), abs=1e-6)


def test_gaze_files_in_csv_and_json_and_their_errors(tmp_path):
    csv = tmp_path / "g.csv"
    csv.write_text("time_s,yaw_deg,pitch_deg\n2.0,10,-4\n0.0,0,0\n")  # unsorted: sorted by time
    js = tmp_path / "g.json"
    js.write_text(
        json.dumps(
            [{"time_s": 0, "yaw_deg": 0, "pitch_deg": 0}, {"time_s": 2, "yaw_deg": 10, "pitch_deg": -4}]
        )
    )
    for f in (csv, js):
        track = np.degrees(gaze_track(f, 75, FPS))  # 3 s: held after the last sample
        np.testing.assert_allclose(track[[0, 25, 50, 74]], [[0, 0], [5, -2], [10, -4], [10, -4]], atol=1e-4)
    np.testing.assert_array_equal(gaze_track("camera", 4, FPS), np.zeros((4, 2)))
    bad = {
        "a.csv": ("time_s,yaw_deg\n0,1\n", "pitch_deg"),
        "b.csv": ("time_s,yaw_deg,pitch_deg\n0,x,1\n", "time_s"),
        "c.csv": ("time_s,yaw_deg,pitch_deg\n0,60,0\n", "45"),
        "d.csv": ("time_s,yaw_deg,pitch_deg\n", "no gaze sample"),
        "e.json": ("{}", "time_s"),
    }
    for name, (text, message) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(NvpError, match=message):
            read_gaze_file(tmp_path / name)
    with pytest.raises(NvpError, match="cannot read"):
        read_gaze_file(tmp_path / "missing.csv")


def test_gaze_angles_and_iris_pixels_invert_each_other():
    from nvp.gaze import angle_between, gaze_angles, gaze_from_iris, gaze_vectors, iris_pixels, towards_camera

    gaze = np.radians([[0, 0], [20, 0], [0, 15], [-30, -10]])
    np.testing.assert_allclose(gaze_angles(gaze_vectors(gaze)), gaze, atol=1e-9)
    np.testing.assert_allclose(gaze_vectors([[0, 0]]), [[0, 0, -1]], atol=1e-12)  # ahead: to the camera
    assert gaze_vectors(np.radians([[0, 10]]))[0, 1] < 0  # pitch up: towards -Y (up in the image)
    centres = np.array([[3.0, -2.0, 50.0]] * 4)
    looks = np.einsum("ij,tj->ti", np.eye(3), gaze_vectors(gaze))
    pixels = iris_pixels(centres, looks, 800.0, np.array([320.0, 240.0]))
    back = gaze_from_iris(centres, pixels, 800.0, np.array([320.0, 240.0]))
    assert angle_between(back, looks).max() < 1e-6
    # a pixel off the eyeball (a bad landmark) still gives a direction, the nearest one
    off = gaze_from_iris(centres[:1], pixels[:1] + 500, 800.0, np.array([320.0, 240.0]))
    assert np.isfinite(off).all() and abs(np.linalg.norm(off) - 1) < 1e-9
    assert angle_between(towards_camera(centres[0]), -centres[0]) < 1e-5  # arccos near 1: 1e-6 degrees


def test_the_eyeballs_spread_so_that_both_eyes_look_the_same_way(face_model):
    import dataclasses

    from nvp.gaze import SPREAD_KEY, angle_between, eye_spread, footage_gaze
    from tracking.synthetic import synthetic_tracked

    seq = synthetic_tracked(face_model, frames=30, size=512, focal=1000.0)
    assert abs(eye_spread(face_model, seq)) < 0.01  # the truth: nothing to correct
    # each iris seen 1.5 px further out than the mesh's eyes put it: the eyes seem to look apart
    iris = seq.iris.copy()
    iris[:, 0, 0] += 1.5  # the face's left eye is on the image's right
    iris[:, 1, 0] -= 1.5
    apart = dataclasses.replace(seq, iris=iris)
    _, looks = footage_gaze(face_model, apart)
    assert np.median(angle_between(looks[:, 0], looks[:, 1])) > 3
    spread = eye_spread(face_model, apart)
    assert spread > 0.02
    _, looks = footage_gaze(face_model, dataclasses.replace(apart, info={SPREAD_KEY: spread}))
    assert np.median(angle_between(looks[:, 0], looks[:, 1])) < 0.5
