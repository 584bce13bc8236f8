"""Eye contact (renderer.eyes): the iris moved inside the eye opening, nothing else."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from renderer.eyes import OPEN_FROM, EyeMove, eye_moves, move_eyes, turn_eyes


def eye_image(gap: float = 16.0, iris_at=(100.0, 60.0), radius: float = 12.0, seed: int = 0):
    """A 200×120 eye: skin, an almond opening of half-height ``gap``, a textured iris; its outline."""
    img = np.full((120, 200, 3), (190, 150, 130), np.uint8)
    t = np.linspace(0, 2 * np.pi, 17)[:-1]
    outline = np.stack([100 + 40 * np.cos(t), 60 + gap * np.sin(t)], 1)
    opening = np.zeros((120, 200), np.uint8)
    cv2.fillPoly(opening, [np.round(outline * 16).astype(np.int32)], 1, shift=4)
    img[opening > 0] = (235, 235, 230)
    ys, xs = np.mgrid[:120, :200]
    iris = (np.hypot(xs - iris_at[0], ys - iris_at[1]) < radius) & (opening > 0)
    rng = np.random.default_rng(seed)
    img[iris] = (40 + 60 * rng.random((iris.sum(), 1))).astype(np.uint8)
    return img, outline, iris


def dark_centre(img: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(img[..., 0] < 120)
    return np.array([xs.mean(), ys.mean()])


@pytest.mark.parametrize("shift", [(10.0, 0.0), (-14.0, 3.0), (0.0, -4.0)])
def test_the_iris_goes_where_asked_and_nothing_outside_the_opening_changes(shift):
    img, outline, iris = eye_image()
    to = np.array([100.0, 60.0]) + shift
    out, weight = move_eyes(img, [EyeMove(outline, np.array([100.0, 60.0, 12.0]), to)], with_weight=True)
    # the iris keeps its size and texture: as many dark pixels, centred where asked (the lids crop it a
    # little differently where it moves up or down)
    assert abs(dark_centre(out)[0] - to[0]) < 0.6
    assert abs((out[..., 0] < 120).sum() / iris.sum() - 1) < 0.1
    np.testing.assert_array_equal(out[weight == 0], img[weight == 0])
    assert weight.max() == 1 and (weight > 0).sum() < 0.2 * weight.size
    # its old place shows the white of the eye, not a hole
    old = np.hypot(*np.meshgrid(np.arange(200) - 100, np.arange(120) - 60)) < 6
    if np.hypot(*shift) > 12 + 6:
        assert out[old & (weight == 1)].min() > 200


def test_a_move_of_nothing_leaves_the_frame_as_it_is():
    img, outline, _ = eye_image()
    assert move_eyes(img, []) is img
    same = move_eyes(img, [EyeMove(outline, np.array([100.0, 60.0, 12.0]), np.array([100.0, 60.0]))])
    np.testing.assert_array_equal(same, img)


def test_a_blinking_eye_is_left_alone_and_a_half_open_one_moves_part_of_the_way(face_model):
    from tracking.synthetic import synthetic_tracked

    seq = synthetic_tracked(face_model, frames=3, size=256, focal=500.0)
    groups = [face_model.landmark_groups[g] for g in ("left_eye", "right_eye")]
    landmarks = np.zeros((3, 468, 2), np.float32)
    iris = np.zeros((3, 2, 3), np.float32)
    for e, g in enumerate(groups):
        centre = np.array([80.0 + 90 * e, 100.0])
        t = np.linspace(0, 2 * np.pi, len(g) + 1)[:-1]
        for k, gap in enumerate([1.0, (OPEN_FROM + 0.05) * 3, 8.0]):  # closed, barely open, open (half gaps)
            landmarks[k, g] = centre + np.stack([20 * np.cos(t), gap * np.sin(t)], 1)
        iris[:, e] = [*centre, 6.0]
    import dataclasses

    seq = dataclasses.replace(seq, landmarks=landmarks, iris=iris)
    looks = np.tile([[0.5, 0.0, -0.866]], (2, 1))  # 30 degrees to the side: a long way
    moves = [
        eye_moves(face_model, seq, k, looks, centres=np.array([[-3, 0, 40.0], [3, 0, 40.0]]))
        for k in range(3)
    ]
    assert moves[0] == []
    part = [np.linalg.norm(m.to - m.iris[:2]) for m in moves[1]]
    full = [np.linalg.norm(m.to - m.iris[:2]) for m in moves[2]]
    assert len(part) == len(full) == 2 and all(0 < p < 0.5 * f for p, f in zip(part, full, strict=True))


def test_turn_eyes_looks_into_the_lens_or_along_a_gaze_and_needs_the_iris(face_model):
    import dataclasses

    from nvp.errors import NvpError
    from nvp.gaze import footage_gaze, towards_camera
    from tracking.synthetic import synthetic_tracked

    seq = synthetic_tracked(face_model, frames=4, size=256, focal=500.0)
    frame = np.full((256, 256, 3), 128, np.uint8)
    centres, looks = footage_gaze(face_model, seq, np.array([2]))
    assert np.isfinite(looks).all()
    # the synthetic footage looks around; its eyes asked to look where they already look do not move
    moves = eye_moves(face_model, seq, 2, looks[0], centres[0])
    for m in moves:
        np.testing.assert_allclose(m.to, m.iris[:2], atol=1e-3)
    lens = eye_moves(face_model, seq, 2, towards_camera(centres[0]), centres[0])
    assert all(np.linalg.norm(m.to - m.iris[:2]) > 0.5 for m in lens)
    assert turn_eyes(face_model, seq, frame, 2).shape == frame.shape
    with pytest.raises(NvpError, match="track again"):
        turn_eyes(face_model, dataclasses.replace(seq, iris=None), frame, 2)


def test_an_eye_is_turned_at_most_max_turn_towards_what_is_asked():
    from nvp.gaze import angle_between
    from renderer.eyes import MAX_TURN_DEG, within_reach

    now = np.array([[0.0, 0.0, -1.0]] * 3)
    degrees = np.radians([5.0, MAX_TURN_DEG + 1, 60.0])
    asked = np.stack([np.sin(degrees), 0 * degrees, -np.cos(degrees)], 1)
    reached = within_reach(now, asked)
    np.testing.assert_allclose(angle_between(reached, now), [5.0, MAX_TURN_DEG, MAX_TURN_DEG], atol=1e-6)
    assert reached[2, 0] > 0 and abs(reached[2, 1]) < 1e-12  # on the way to what was asked


def test_a_dub_asks_for_the_eyes_it_can_turn_and_says_when_it_cannot(face_model, tmp_path):
    import dataclasses

    from nvp.app.dub import eye_requests
    from nvp.errors import NvpError
    from tracking.synthetic import synthetic_tracked

    seq = synthetic_tracked(face_model, frames=3, size=256, focal=500.0)
    assert eye_requests("footage", seq, 5) is None
    assert np.isnan(eye_requests("camera", seq, 5)).all()  # into the lens, wherever the head is
    gaze = tmp_path / "g.csv"
    gaze.write_text("time_s,yaw_deg,pitch_deg\n0,10,-5\n")
    np.testing.assert_allclose(np.degrees(eye_requests(gaze, seq, 5)), [[10, -5]] * 5, atol=1e-4)
    with pytest.raises(NvpError, match="fit again"):
        eye_requests("camera", dataclasses.replace(seq, iris=None), 5)
    with pytest.raises(NvpError, match="cannot read the gaze file"):
        eye_requests(tmp_path / "missing.csv", seq, 5)


def test_the_thin_plate_spline_meets_its_points_and_keeps_an_affine_map_affine():
    from renderer.eyes import thin_plate_spline

    rng = np.random.default_rng(0)
    points = rng.uniform(0, 50, (12, 2))
    values = points + rng.normal(0, 2, (12, 2))
    np.testing.assert_allclose(thin_plate_spline(points, values)(points), values, atol=1e-6)
    affine = points @ np.array([[1.1, 0.2], [-0.1, 0.9]]) + [3.0, -4.0]
    query = rng.uniform(0, 50, (30, 2))
    expected = query @ np.array([[1.1, 0.2], [-0.1, 0.9]]) + [3.0, -4.0]
    np.testing.assert_allclose(thin_plate_spline(points, affine)(query), expected, atol=1e-6)
