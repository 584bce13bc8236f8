"""Registration: the tracked head moved to where the person's trained renderer sees it in each frame.

The landmark tracker places each frame's head to within a fraction of a pixel, but that placement wanders
from frame to frame in a way the renderer cannot know (the offset between the networks' render of a frame's
tracked geometry and the frame itself: 0.3-0.6 frame pixels standard deviation, lag-one correlation 0.9, on
dfrf__cnn2, edtalk__pose_source2, wav2lipgfpgan kim). Everything nvp paints and moves is placed by the
tracking — the networks' render, the footage's detail moved onto a new mouth, the mouth bank's teeth — so
that offset is an error in every painted pixel. Once the renderer is trained it is measured: dense optical
flow (OpenCV DIS) between the footage crop and the face network's render of the frame's tracked geometry
(:meth:`renderer.render.FrameRenderer.surface`: the neural texture alone, without the compositing network,
which paints the mesh's silhouette from the unmoved footage and so pulls the measure towards no offset:
a known shift of a 600-step dfrf__cnn2 renderer's tracking by (1, -0.5) and (2, -1) frame pixels was
measured back at 82-87 % of its length with the whole render, 101-103 % with the face network's alone, at
23 instead of 39 ms a 512² frame), its median over the skin well inside the mesh away from the lips (their
shape is what a dub changes, and the mouth interior moves on its own); the head's translation is then
moved so that its projection moves by that offset at the face's depth (:func:`registered`). Registering (with
the earlier measure) gained, on six videos (three test people), mouth-box PSNR +0.2-1.1 dB visually driven, up
to +0.9 audio-driven and +0.4 in a dub, none on a 6-second clip whose renderer learned its frames by heart
(docs/experiments/tracking.md, *Heads where the renderer sees them*); the measure used now is within ±0.11 dB
of it on three.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nvp.face_model import FaceModel
from nvp.tracked import TrackedSequence

if TYPE_CHECKING:
    from renderer.render import FrameRenderer

LIP_MARGIN = 3 / 192
"""The lips and mouth interior, grown by this fraction of the crop side (3 pixels of a 192² crop), are left
out of the measured region."""

MIN_PIXELS = 0.05
"""Fewer measured pixels than this fraction of the crop: no offset for that frame (it stays as tracked)."""

MAX_SHIFT = 2 / 192
"""Largest offset taken, as a fraction of the crop side (2 pixels of a 192² crop); a longer one is
shortened to it. Measured offsets on three videos: 99th percentile 0.67-1.11 crop pixels, largest 1.59."""


def frame_offset(crop: np.ndarray, render: np.ndarray, region: np.ndarray) -> np.ndarray:
    """``(2,)`` the ``(x, y)`` shift (crop pixels) that moves ``render`` onto ``crop`` (both ``(S, S, 3)``
    uint8), measured over ``region`` ``(S, S)`` bool: the median of the dense optical flow there; NaN when
    the region is smaller than :data:`MIN_PIXELS` of the crop. Its length is at most :data:`MAX_SHIFT`."""
    import cv2

    if region.sum() < MIN_PIXELS * region.size:
        return np.full(2, np.nan)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    grey = [cv2.cvtColor(np.ascontiguousarray(x), cv2.COLOR_RGB2GRAY) for x in (crop, render)]
    # the crop's pixel x shows what the render shows at x + flow: the render moves by -flow
    shift = -np.median(dis.calc(grey[0], grey[1], None)[region], axis=0)
    limit = MAX_SHIFT * crop.shape[0]
    length = float(np.linalg.norm(shift))
    return shift * min(1.0, limit / length) if length > 0 else shift


def registered(seq: TrackedSequence, model: FaceModel, offsets: np.ndarray) -> TrackedSequence:
    """``seq`` with each frame's head translated parallel to the image plane so that its face (``model``'s
    vertices at their mean depth) moves by ``offsets`` ``(T, 2)`` frame pixels in the image (NaN: left as
    tracked); its nearer and farther points move a little more and less (by 15 % for a face 12 cm deep seen
    from 45 cm)."""
    offsets = np.nan_to_num(np.asarray(offsets, dtype=np.float64))
    if offsets.shape != (seq.num_frames, 2):
        raise ValueError(f"expected ({seq.num_frames}, 2) offsets, found {offsets.shape}")
    depth = seq.camera_vertices(model, np.arange(seq.num_frames))[..., 2].mean(1)
    translation = seq.translation.copy()
    translation[:, :2] += offsets * depth[:, None] / seq.focal
    moved = np.linalg.norm(offsets, axis=1)
    info = {
        **seq.info,
        "registration": {
            "frames": int((moved > 0).sum()),
            "median_px": round(float(np.median(moved)), 3),
            "p95_px": round(float(np.percentile(moved, 95)), 3),
        },
    }
    return replace(seq, translation=translation, info=info)


def registration_offsets(
    renderer_dir: Path,
    video: Path,
    seq: TrackedSequence,
    indices: Sequence[int],
    device: str = "cpu",
    progress: bool = True,
) -> np.ndarray:
    """``(len(indices), 2)`` offsets (frame pixels, NaN where unmeasured or no face was tracked) of the
    renderer in ``renderer_dir``'s render of ``seq``'s frames ``indices`` of ``video``, for
    :func:`registered`."""
    from functools import partial

    from tqdm import tqdm

    from nvp.face_model import default_face_model
    from nvp.media import frames_at
    from nvp.threads import frame_workers
    from renderer.render import FrameRenderer
    from renderer.workers import RenderWorkers

    model = default_face_model()
    lips = model.vertex_regions["lips"][model.triangles].any(1) | model.triangle_regions["mouth_interior"]
    indices = np.asarray(indices, dtype=np.int64)
    out = np.full((len(indices), 2), np.nan)
    # frames side by side, one PyTorch thread each, as the dub renders them (renderer.loop.render_frames)
    workers = frame_workers() if str(device).startswith("cpu") else 1
    with (
        FrameRenderer(renderer_dir, model, seq, device, detail=False, interiors=False) as fr,
        RenderWorkers(fr, workers) as pool,
        tqdm(total=len(indices), desc="register", unit="frame", disable=not progress) as bar,
    ):
        read = zip(indices.tolist(), frames_at(video, indices, seq.fps), strict=True)
        jobs = (partial(_offset, t=t, frame=img, lips=lips) if seq.valid[t] else None for t, img in read)
        for j, offset in enumerate(pool.in_order(jobs)):
            if offset is not None:
                out[j] = offset
            bar.update()
    return out


def _offset(fr: FrameRenderer, t: int, frame: np.ndarray, lips: np.ndarray) -> np.ndarray:
    """``(2,)`` frame ``t``'s offset (frame pixels, NaN when unmeasured) by renderer ``fr``; ``lips``: the
    face model's triangles left out with the margin :data:`LIP_MARGIN`."""
    import cv2

    from renderer.networks import inner_weight

    seen = fr.surface(frame, t, fr.tracked(t))
    if seen is None:
        return np.full(2, np.nan)
    crop, render, geo = seen
    grow = max(1, round(LIP_MARGIN * fr.preset.crop)) * 2 + 1
    tri = geo.triangle_id.numpy()
    on_lips = ((tri >= 0) & lips[np.clip(tri, 0, None)]).astype(np.uint8)
    region = (inner_weight(geo.mask)[0, 0] > 0.99).numpy()  # where the final image is this render
    region &= cv2.dilate(on_lips, np.ones((grow, grow), np.uint8)) == 0
    crop, render = ((x.permute(1, 2, 0) * 255).round().clamp(0, 255).byte().numpy() for x in (crop, render))
    # crop pixels to frame pixels: the box side over the crop side
    return frame_offset(crop, render, region) * fr.boxes[t][2] / fr.preset.crop
