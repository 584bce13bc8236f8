"""Rendering new geometry into the footage: crop → rasterize → neural render → paste back."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from nvp.face_model import FaceModel
from nvp.tracked import TrackedSequence
from renderer.crop import cut, feather, paste, region_weight
from renderer.data import Rasterizer, blank_face, face_region, sequence_boxes
from renderer.networks import load_renderer

LOWER_FACE = 0.02
"""Mouth weight (``FaceModel.mouth_weights``) above which a mesh pixel is part of the re-rendered lower
face."""


class FrameRenderer:
    """Renders face-model geometry into frames of the footage a renderer was trained on.

    Args:
        renderer_dir: folder with ``renderer.{json,npz}``.
        model: the face model.
        seq: the footage's tracking (camera, per-frame crop boxes).
        device: torch device of the networks.

    Use as a context manager (it owns an OpenGL context).
    """

    def __init__(
        self, renderer_dir: Path, model: FaceModel, seq: TrackedSequence, device: str = "cpu"
    ) -> None:
        self.net, self.preset, self.manifest = load_renderer(renderer_dir, device)
        self.model, self.seq, self.device = model, seq, device
        self.boxes = sequence_boxes(model, seq)
        self.raster = Rasterizer(model, self.preset.crop, self.preset.region_grow)
        self.weight = feather(self.preset.crop)

    def __enter__(self) -> FrameRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.raster.close()

    def tracked(self, index: int) -> np.ndarray:
        """``(V, 3)`` camera-frame vertices of frame ``index`` as tracked."""
        return self.seq.camera_vertices(self.model, np.array([index]))[0]

    @torch.inference_mode()
    def render(
        self, frame: np.ndarray, index: int, vertices_cam: np.ndarray, original_cam: np.ndarray | None = None
    ) -> np.ndarray:
        """Frame ``index`` of the footage (``(H, W, 3)`` uint8) with the face replaced by a render of
        ``vertices_cam`` ``(V, 3)``; ``original_cam`` (the tracked geometry of that frame) widens the
        replaced region so the original mouth and chin are covered too. Returns ``(H, W, 3)`` uint8."""
        box = self.boxes[index]
        f, c = self.seq.focal, self.seq.center
        geo = self.raster(vertices_cam, f, c, box)
        region, lower = geo.region, geo.lower
        if original_cam is not None:
            orig = self.raster(original_cam, f, c, box)
            region, lower = torch.maximum(region, orig.region), torch.maximum(lower, orig.lower)
        img = torch.from_numpy(frame).permute(2, 0, 1).float()
        crop = cut(img[None], torch.from_numpy(box[None]).float(), self.preset.crop) / 255
        dev = self.device
        _, final = self.net(
            geo.uv.to(dev),
            geo.mask.to(dev),
            geo.mouth.to(dev),
            blank_face(crop.to(dev), region.to(dev)),
            region.to(dev),
        )
        # only the lower face (where the geometry can differ from the footage) and its surroundings are
        # pasted: eyes, brows and forehead keep the footage's own pixels at full resolution; around the
        # painted part the footage keeps its full-resolution detail too (the crop is softer), while inside
        # it nothing of the footage's own mouth and chin shows through
        paint = face_region((lower > LOWER_FACE).float(), self.preset.region_grow) * region
        weight = self.weight * region_weight(paint)
        out = paste(img, final[0].cpu() * 255, box, weight, detail=(crop[0] * 255, 1 - paint))
        return out.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()


Geometry = Callable[[int, int, np.ndarray], np.ndarray]
"""``(j, index, tracked_cam) → (V, 3)`` camera-frame vertices to render for output frame ``j`` over footage
frame ``index`` whose tracked vertices are ``tracked_cam``."""


def render_frames(
    fr: FrameRenderer,
    frames: Iterable[np.ndarray],
    indices: Sequence[int],
    variants: Mapping[str, Geometry | None],
    progress: bool = True,
    desc: str = "render",
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """The one render loop: footage ``frames`` (``(H, W, 3)`` uint8, one per entry of ``indices``, the
    footage frame each one is) in; for each, the footage frame and its renders ``{name: (H, W, 3) uint8}``
    out, with a progress bar that is closed however the loop ends (an error, or the consumer stopping).

    A variant ``None`` re-renders the frame from its own tracking (re-creation); a :data:`Geometry` renders
    ``geometry(j, index, tracked_cam)`` and the replaced region also covers the tracked face (a dub)."""
    from tqdm import tqdm

    bar = tqdm(total=len(indices), desc=desc, unit="frame", disable=not progress)
    try:
        for j, (k, frame) in enumerate(zip(indices, frames, strict=False)):
            k = int(k)
            tracked = fr.tracked(k)
            out = {
                name: fr.render(frame, k, tracked)
                if geo is None
                else fr.render(frame, k, geo(j, k, tracked), tracked)
                for name, geo in variants.items()
            }
            yield frame, out
            bar.update(1)
    finally:
        bar.close()
