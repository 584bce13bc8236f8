"""tracking.detect: how many people a target shows, and detectors side by side."""

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


def test_threads_that_silence_native_stderr_together_give_it_back():
    """Segments detected side by side each silence mediapipe's start-up chatter on file descriptor 2: the
    first thread out must not give back the silence the second saved (stderr lost for good)."""
    import os
    import threading

    from tracking.landmarks import _native_stderr_silenced

    def where() -> tuple[int, int]:
        st = os.fstat(2)
        return st.st_ino, st.st_dev

    before, seen = where(), {}
    both_in, first_out = threading.Barrier(2), threading.Event()

    def first() -> None:
        with _native_stderr_silenced():
            both_in.wait()
        first_out.set()

    def second() -> None:
        with _native_stderr_silenced():
            both_in.wait()
            first_out.wait()
            seen["after the first left"] = where()

    threads = [threading.Thread(target=f) for f in (first, second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert seen["after the first left"] != before  # still silenced while the second is inside
    assert where() == before
