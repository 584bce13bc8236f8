"""Per-frame renderer inputs, the same for training and for rendering: stabilised crop boxes, the face
model rasterized into a crop (:class:`FrameGeometry`), the face region the renderer replaces, a source
frame's pixels moved onto the rendered surface, and a frame's networks pass awaiting its paste
(:class:`FaceRender`). The training frames' cache is :mod:`renderer.train_data`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nvp.face_model import FaceModel
from nvp.geometry import pinhole
from nvp.tracked import TrackedSequence
from renderer.crop import MovedDetail, crop_boxes, crop_camera
from renderer.masks import dilate
from renderer.warp import sample_pixels, source_positions


@dataclass
class FrameGeometry:
    """The face model rasterized into a batch of crops.

    Attributes:
        uv: ``(B, S, S, 2)`` float32 texture coordinates (0 outside the mesh).
        mask: ``(B, 1, S, S)`` float32 1 where the mesh covers the pixel.
        mouth: ``(B, 1, S, S)`` float32 1 on the mouth-interior triangles.
        region: ``(B, 1, S, S)`` float32 1 on the face region blanked in the background input (see
            :func:`face_region`).
        lower: ``(B, 1, S, S)`` float32 the face model's mouth weights (1 on lips and jaw, 0 on the eyes and
            upper face) interpolated over the mesh, 0 outside it; made when rendering, not cached for
            training (None there).
    """

    uv: torch.Tensor
    mask: torch.Tensor
    mouth: torch.Tensor
    region: torch.Tensor
    lower: torch.Tensor | None = None
    triangle_id: torch.Tensor | None = None
    """``(S, S)`` int64 visible triangle (-1 = background); made when rendering (None in the cache)."""
    barycentric: torch.Tensor | None = None
    """``(S, S, 3)`` float32 barycentrics of the visible triangle; made when rendering."""
    depth: torch.Tensor | None = None
    """``(S, S)`` float32 camera z of the visible surface (0 = background); made when rendering."""


def sequence_boxes(model: FaceModel, seq: TrackedSequence) -> np.ndarray:
    """``(T, 3)`` crop boxes of a whole tracked sequence (from its tracked geometry)."""
    return crop_boxes(seq.pixels(seq.camera_vertices(model, np.arange(seq.num_frames))))


class Rasterizer:
    """Rasterizes face-model vertices into crops (moderngl), returning ``FrameGeometry``."""

    def __init__(self, model: FaceModel, size: int, grow: float) -> None:
        from renderer.gl import GLRasterizer
        from renderer.raster import empty_output

        self.model, self.size, self.grow = model, size, grow
        self._gl = GLRasterizer(size, size)
        self._out = empty_output(size, size)
        self._is_mouth = torch.from_numpy(model.triangle_regions["mouth_interior"])  # (F,) bool
        self._tri_weights = torch.from_numpy(model.mouth_weights()[model.triangles])  # (F, 3)

    def close(self) -> None:
        self._gl.release()

    def __call__(
        self, vertices_cam: np.ndarray, focal: float, center: np.ndarray, box: np.ndarray
    ) -> FrameGeometry:
        """Geometry of one crop: ``vertices_cam`` ``(V, 3)``, the frame camera and the crop ``box``."""
        f, c = crop_camera(focal, center, box, self.size)
        r = self._gl.rasterize(
            vertices_cam.astype(np.float32), self.model.triangles, self.model.uvs, f, c, out=self._out
        )
        # a lookup, not torch.isin (0.9 ms per call on a 192² crop; this 0.1 ms)
        mouth = self._is_mouth[r.triangle_id.clamp_min(0)] & (r.triangle_id >= 0)
        mask = r.mask.float()[None, None]
        lower = (self._tri_weights[r.triangle_id.clamp_min(0)] * r.barycentric).sum(-1) * r.mask
        return FrameGeometry(
            uv=r.uv.clone()[None],
            mask=mask,
            mouth=mouth.float()[None, None],
            region=face_region(mask, self.grow),
            lower=lower[None, None],
            triangle_id=r.triangle_id.clone(),
            barycentric=r.barycentric.clone(),
            depth=r.depth.clone(),
        )


def face_region(mask: torch.Tensor, grow: float) -> torch.Tensor:
    """``mask`` ``(B, 1, S, S)`` grown by ``grow`` of the crop side: the part of the footage that the
    renderer replaces (pass the union of the old and new masks when the geometry changes)."""
    return dilate(mask, max(1, int(round(grow * mask.shape[-1]))))


def blank_face(crops: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
    """The background input: ``crops`` ``(B, 3, S, S)`` with ``region`` ``(B, 1, S, S)`` set to 0, so the
    original mouth and chin cannot leak through."""
    return crops * (1 - region)


def moved_source(
    geo: FrameGeometry,
    source_crop: torch.Tensor,
    source_box: np.ndarray,
    source_cam: np.ndarray,
    source_depth: torch.Tensor,
    camera: tuple[float, np.ndarray],
    triangles: torch.Tensor,
    movable: torch.Tensor,
    window: tuple[slice, slice] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A source frame's pixels moved onto the surface of ``geo`` (one rendered crop), or onto its
    ``window`` ``(rows, columns)`` only (0 and invalid elsewhere: the rest of the crop is not painted).

    Args:
        geo: fragments of the geometry being rendered (``triangle_id``, ``barycentric``).
        source_crop: ``(3, S, S)`` the source frame's crop at ``source_box``, any value range.
        source_box: ``(3,)`` crop box of the source frame.
        source_cam: ``(V, 3)`` the source frame's tracked camera-frame vertices.
        source_depth: ``(S, S)`` depth buffer of ``source_cam`` rasterized into the source crop.
        camera: ``(focal, center)`` of the footage.
        triangles: ``(F, 3)`` int64; movable: ``(F,)`` bool (see :func:`renderer.warp.source_positions`).

    Returns:
        ``(4, S, S)``: the moved crop (0 where invalid) and its validity; and the source-frame pixel
        positions ``(S, S, 2)`` and validity ``(S, S)`` (for the full-resolution detail layer).
    """
    size = source_crop.shape[-1]
    focal, center = camera
    scale, origin = size / float(source_box[2]), source_box[:2] - source_box[2] / 2
    rows, cols = window or (slice(None), slice(None))
    pixels = torch.from_numpy(pinhole(source_cam, focal, center)).float()
    pos_w, valid_w = source_positions(
        geo.triangle_id[rows, cols],
        geo.barycentric[rows, cols],
        triangles,
        pixels,
        torch.from_numpy(np.ascontiguousarray(source_cam[:, 2])).float(),
        source_depth,
        (scale, origin),
        movable,
    )
    crop_pos = (pos_w - torch.as_tensor(origin, dtype=pos_w.dtype)) * scale
    out = torch.zeros(source_crop.shape[0] + 1, size, size)
    out[:-1, rows, cols] = sample_pixels(source_crop, crop_pos) * valid_w
    out[-1, rows, cols] = valid_w
    pos = torch.zeros(size, size, 2)
    pos[rows, cols] = pos_w
    return out, pos, out[-1].clone()


@dataclass
class FaceRender:
    """A frame's networks pass (:meth:`FrameRenderer.prepare`), awaiting its mouth interior and paste
    (:meth:`FrameRenderer.composite`). The fields after ``slices`` are None when the face lies outside
    the frame.

    Attributes:
        frame: ``(H, W, 3)`` uint8 the footage frame; index: its footage index.
        vertices_cam: ``(V, 3)`` the rendered geometry.
        slices: the frame rows and columns under the crop box (the only pixels read and written).
        image: ``(3, h, w)`` float the frame there.
        box: ``(3,)`` the crop box relative to ``slices``.
        geo: the rasterized geometry; crop: ``(3, S, S)`` the footage crop in [0, 1].
        render: ``(3, S, S)`` the networks' crop in [0, 1] (the crop itself outside their window), in the
            footage frame's light (:func:`renderer.crop.colour_match`).
        paint: ``(1, 1, S, S)`` the painted lower face; moved: the detail moved onto it, if any.
        interior: with a mouth bank, the crop window around the mouth interior the geometry shows
            (:meth:`FrameRenderer._interior_window`; None when it shows none); lips: the rendered lips
            there (:meth:`FrameRenderer._rendered_lips`, in the light the networks learned), which the bank
            entries' colours follow; light: ``(gain, offset)`` ``(3, 1, 1)`` each that took the networks'
            render into the frame's light, and takes a bank entry's interior there too (None: the light the
            networks learned, nothing changed).
    """

    frame: np.ndarray
    index: int
    vertices_cam: np.ndarray
    slices: tuple[slice, slice]
    image: torch.Tensor | None = None
    box: np.ndarray | None = None
    geo: FrameGeometry | None = None
    crop: torch.Tensor | None = None
    render: torch.Tensor | None = None
    paint: torch.Tensor | None = None
    moved: MovedDetail | None = None
    interior: tuple[int, int, int, int] | None = None
    lips: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    light: tuple[torch.Tensor, torch.Tensor] | None = None
