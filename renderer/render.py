"""Rendering new geometry into the footage: crop → rasterize → neural render → paste back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from nvp.face_model import FaceModel
from nvp.tracked import TrackedSequence
from renderer.crop import cut, feather, paste, region_weight
from renderer.data import Rasterizer, blank_face, camera_vertices, face_region, sequence_boxes
from renderer.train import load_renderer

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
        expression = self.seq.expression[index : index + 1]
        return camera_vertices(self.model, self.seq, np.array([index]), expression)[0]

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
