"""tracking.detect: how many people a target shows."""

from __future__ import annotations

import numpy as np

from nvp.media import VideoWriter
from tracking.detect import count_faces


def test_count_faces_sees_one_or_two_people(tmp_path):
    from skimage import data, transform

    face = (transform.resize(data.astronaut()[:300, 100:400], (160, 160)) * 255).astype(np.uint8)
    for n in (1, 2):
        frame = np.hstack([face] * n)
        path = tmp_path / f"{n}.mp4"
        with VideoWriter(path, 25, frame.shape[1], frame.shape[0]) as w:
            for _ in range(10):
                w.write(frame)
        assert count_faces(path, samples=3) == n
