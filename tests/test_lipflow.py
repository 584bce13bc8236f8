"""tracking.lipflow: lip landmarks steadied by the optical flow between frames."""

from __future__ import annotations

import numpy as np

from tracking.lipflow import fuse, lip_landmarks, mouth_flow


def _texture(size: int = 160, seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.uniform(0, 255, (size, size)).astype(np.float32), (0, 0), 2.0)
    grey = cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return np.repeat(grey[..., None], 3, -1)


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    import cv2

    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, img.shape[1::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def test_mouth_flow_measures_a_known_motion_both_ways():
    prev = _texture()
    cur = _shifted(prev, 1.5, -0.75)  # the content moves right and up
    pts = np.array([[60.0, 70.0], [90.0, 75.0], [75.0, 90.0], [70.0, 60.0]])
    forward, backward = mouth_flow(prev, pts, cur, pts + [1.5, -0.75])
    np.testing.assert_allclose(forward, np.tile([1.5, -0.75], (4, 1)), atol=0.15)
    np.testing.assert_allclose(backward, np.tile([-1.5, 0.75], (4, 1)), atol=0.15)
    outside = pts + [200.0, 0.0]  # lips beyond the frame's right edge (a face cut off): not measured
    assert np.isnan(np.concatenate(mouth_flow(prev, outside, cur, outside))).all()


def test_fuse_steadies_noisy_detections_with_the_true_motion_and_restarts_where_it_breaks():
    rng = np.random.default_rng(1)
    t, n = 200, 6
    truth = np.cumsum(rng.normal(0, 1.5, (t, 1, 2)), 0) + rng.uniform(50, 150, (1, n, 2))  # lips move
    detected = truth + rng.normal(0, 1.0, truth.shape)  # a detector a pixel off, independently per frame
    forward = np.full_like(truth, np.nan)
    backward = np.full_like(truth, np.nan)
    forward[:-1] = truth[1:] - truth[:-1]  # exact motion, measured at the detected points
    backward[1:] = truth[:-1] - truth[1:]

    def error(x: np.ndarray, frames: slice = slice(None)) -> float:
        return float(np.sqrt(((x[frames] - truth[frames]) ** 2).sum(-1).mean()))

    np.testing.assert_array_equal(fuse(detected, forward, backward, 0.0), detected)
    fused = fuse(detected, forward, backward, 0.8)
    assert error(fused) < 0.4 * error(detected)  # 0.28 measured
    # no face in frame 100: neither chain crosses it (the detection is kept there and restarts both)
    detected[100] = np.nan
    forward[99:101] = backward[100:102] = np.nan
    gapped = fuse(detected, forward, backward, 0.8)
    assert np.isnan(gapped[100]).all() and np.isfinite(gapped[:100]).all() and np.isfinite(gapped[101:]).all()
    np.testing.assert_allclose(gapped[:70], fused[:70], atol=0.01)  # far from the gap: as before
    assert error(gapped, slice(101, None)) < 0.5 * error(detected, slice(101, None))


def test_detections_carry_the_lip_motion_and_the_fit_uses_it(tmp_path):
    from skimage import data, transform

    from nvp.face_model import default_face_model
    from nvp.media import VideoWriter
    from tracking.detect import Detections, detect_video
    from tracking.fit import TrackingConfig
    from tracking.track import fit_detections

    face = (transform.resize(data.astronaut()[:300, 100:400], (200, 200)) * 255).astype(np.uint8)
    path = tmp_path / "moving.mp4"
    with VideoWriter(path, 25, 240, 240) as w:
        for i in range(8):  # the face slides 1 px right per frame
            frame = np.zeros((240, 240, 3), np.uint8)
            frame[20:220, 16 + i : 216 + i] = face
            w.write(frame)
    model = default_face_model()
    lips = lip_landmarks(model)
    det = detect_video(path, progress=False, lips=lips)
    assert det.found.all() and det.lip_flow.shape == (8, 2, len(lips), 2)
    assert np.isnan(det.lip_flow[-1, 0]).all() and np.isnan(det.lip_flow[0, 1]).all()  # no neighbour
    np.testing.assert_allclose(np.nanmedian(det.lip_flow[:-1, 0], (0, 1)), [1.0, 0.0], atol=0.2)
    np.testing.assert_allclose(np.nanmedian(det.lip_flow[1:, 1], (0, 1)), [-1.0, 0.0], atol=0.2)
    # in segments of 3 frames, detected side by side (tracking.detect.MAX_WORKERS): the same landmarks (each
    # segment's detector sees the frames before it first) and the same motion, across the joins too
    parts = detect_video(path, progress=False, lips=lips, segment=3)
    np.testing.assert_array_equal(parts.points, det.points)
    np.testing.assert_array_equal(parts.lip_flow, det.lip_flow)
    det.save(tmp_path / "det.npz")
    back = Detections.load(tmp_path / "det.npz")
    np.testing.assert_array_equal(back.lip_flow, det.lip_flow)
    np.testing.assert_array_equal(back.lip_points, lips)
    steady = fit_detections(det, model)
    plain = fit_detections(det, model, TrackingConfig(lip_flow=0.0))
    moved = np.abs(steady.landmarks[:, lips] - plain.landmarks[:, lips]).max()
    assert 0 < moved < 2  # the lips the model was fitted to moved, by at most a pixel or two
    np.testing.assert_array_equal(np.delete(steady.landmarks, lips, 1), np.delete(plain.landmarks, lips, 1))
