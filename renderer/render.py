"""Rendering new geometry into the footage: crop → rasterize → neural render → paste back.

The frame renderer (:class:`FrameRenderer`) with its two parts, the mouth interior
(:mod:`renderer.interior`) and the detail band (:mod:`renderer.band`); the render loop over many frames is
:func:`renderer.loop.render_frames`, its worker pool :class:`renderer.workers.RenderWorkers`.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import torch

from nvp.face_model import FaceModel
from nvp.tracked import TrackedSequence
from renderer.band import DetailBand
from renderer.crop import box_slices, colour_match, cut, feather, paste_region, region_weight
from renderer.inputs import FaceRender, FrameGeometry, Rasterizer, blank_face, face_region, sequence_boxes
from renderer.interior import MouthInteriors
from renderer.masks import box_blur, dilate, erode
from renderer.networks import fast_bf16, load_renderer
from renderer.warp import mesh_edges

LOWER_FACE = 0.02
"""Mouth weight (``FaceModel.mouth_weights``) above which a mesh pixel is part of the re-rendered lower
face."""

WINDOW_MARGIN = 0.125
"""The networks run on the part of the crop around the painted lower face, grown by this fraction of the
crop side (see :func:`network_window`): the upper face is never pasted, so it is not rendered either. An
eighth (24 px of a 192² crop) keeps a dub's frames within 4 levels of 255 of the whole crop's in float32
(`scripts.tools.compare_dub`, three people: mouth box 55.7-57.7 dB, 44.7 on the worst frame, where a quarter
gave 46.3) with two thirds of a quarter's network time; a twelfth moved pixels by 12 levels (39 dB on the
worst frame). docs/performance.md."""


SURFACE_MARGIN = 16 / 192
"""The first network's context around the mesh in :meth:`FrameRenderer.surface`, a fraction of the crop side
(16 pixels of a 192² crop)."""


class FrameRenderer(MouthInteriors, DetailBand):
    """Renders face-model geometry into frames of the footage a renderer was trained on.

    Args:
        renderer_dir: folder with ``renderer.{json,npz}``.
        model: the face model.
        seq: the footage's tracking (camera, per-frame crop boxes).
        device: torch device of the networks.
        detail: move the footage's own fine detail onto the painted lower face (see :meth:`render`).
        interiors: paste the person's own mouth interiors (teeth) from the renderer folder's mouth bank
            (``mouths.json``, :mod:`renderer.mouths`) where the rendered mouth is open; a renderer without a
            bank renders the interior with its networks.

    Use as a context manager (it owns an OpenGL context).
    """

    def __init__(
        self,
        renderer_dir: Path,
        model: FaceModel,
        seq: TrackedSequence,
        device: str = "cpu",
        detail: bool = True,
        bf16: bool | None = None,
        interiors: bool = True,
    ) -> None:
        self.net, self.preset, self.manifest = load_renderer(renderer_dir, device)
        self._load_interiors(renderer_dir, model, interiors)
        self.bf16 = fast_bf16(device) if bf16 is None else bf16
        self.model, self.seq, self.device = model, seq, device
        self.boxes = sequence_boxes(model, seq)
        self.raster = Rasterizer(model, self.preset.crop, self.preset.region_grow)
        self.weight = feather(self.preset.crop)
        self.detail = detail
        self.window_margin = round(WINDOW_MARGIN * self.preset.crop)
        self._triangles = torch.from_numpy(model.triangles)
        self._movable = torch.from_numpy(~model.triangle_regions["mouth_interior"])
        self._edges = mesh_edges(model.triangles)

    def __enter__(self) -> FrameRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.raster.close()

    def twin(self) -> FrameRenderer:
        """Another renderer of the same person sharing this one's networks (read-only at inference) but
        with its own OpenGL context, so two threads can render frames at once; close it (``with``)."""
        other = copy.copy(self)
        other.raster = Rasterizer(self.model, self.preset.crop, self.preset.region_grow)
        return other

    def tracked(self, index: int) -> np.ndarray:
        """``(V, 3)`` camera-frame vertices of frame ``index`` as tracked."""
        return self.seq.camera_vertices(self.model, np.array([index]))[0]

    @torch.inference_mode()
    def render(
        self,
        frame: np.ndarray,
        index: int,
        vertices_cam: np.ndarray,
        original_cam: np.ndarray | None = None,
        source: tuple[np.ndarray, int, np.ndarray] | None = None,
        with_weight: bool = False,
        mouth: int | None = None,
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Frame ``index`` of the footage (``(H, W, 3)`` uint8) with the face replaced by a render of
        ``vertices_cam`` ``(V, 3)``; ``original_cam`` (the tracked geometry of that frame) widens the
        replaced region so the original mouth and chin are covered too. Returns ``(H, W, 3)`` uint8.

        With ``self.detail`` on, the painted lower face also gets the fine detail (stubble, pores, lip
        texture) of a source frame moved with the surface onto the new geometry (see
        :mod:`renderer.warp`): ``source = (frame, index, tracked_cam)``, by default this very frame under
        ``original_cam`` (or ``vertices_cam`` when there is none). The mouth interior gets none; the band
        around the mesh that the networks paint keeps this footage frame's own pixels whatever the source
        (:meth:`_kept_background`), as a dub of it would.

        With a mouth bank (``self.mouths``), where the new geometry shows the mouth interior the interior
        of bank entry ``mouth`` is pasted, moved onto it (default: the best entry for this frame alone,
        :meth:`entry_costs`; a stream of frames chooses without flicker,
        :class:`renderer.mouths.EntryChooser`).

        ``with_weight``: also return the ``(H, W)`` float32 weight of the render in the output (0 = the
        footage's own pixel), i.e. where nvp changed the picture.

        The same as :meth:`composite` of :meth:`prepare`, the two steps a caller choosing the bank entry
        from :meth:`entry_costs` takes."""
        face = self.prepare(frame, index, vertices_cam, original_cam, source)
        return self.composite(face, mouth, with_weight)

    @torch.inference_mode()
    def prepare(
        self,
        frame: np.ndarray,
        index: int,
        vertices_cam: np.ndarray,
        original_cam: np.ndarray | None = None,
        source: tuple[np.ndarray, int, np.ndarray] | None = None,
    ) -> FaceRender:
        """The networks' render of ``vertices_cam`` over footage frame ``index`` and what the paste needs
        (arguments as :meth:`render`), before a mouth-bank entry is chosen."""
        under = self._under_box(frame, index)
        if under is None:  # the face is outside the frame: nothing to paint
            slices = box_slices(self.boxes[index], *frame.shape[:2], grow=2)
            return FaceRender(frame, index, vertices_cam, slices)
        (ys, xs), offset, box, img, crop = under
        f, c = self.seq.focal, self.seq.center - offset[:2]
        geo = self.raster(vertices_cam, f, c, box)
        region, lower = geo.region, geo.lower
        orig = None
        if original_cam is not None:
            orig = self.raster(original_cam, f, c, box)
            region, lower = torch.maximum(region, orig.region), torch.maximum(lower, orig.lower)
        # only the lower face (where the geometry can differ from the footage) and its surroundings are
        # pasted: eyes, brows and forehead keep the footage's own pixels at full resolution; around the
        # painted part the footage keeps its full-resolution detail too (the crop is softer), while inside
        # it nothing of the footage's own mouth and chin shows through
        paint = face_region((lower > LOWER_FACE).float(), self.preset.region_grow) * region
        dev, (rows, cols) = self.device, network_window(paint, self.window_margin)
        source_in, moved = None, None
        # the footage frame's own geometry (its background off the mesh is kept, whatever the source)
        own_cam, own_geo = (vertices_cam, geo) if original_cam is None else (original_cam, orig)
        if self.detail or self.net.source_input:  # the source moved onto the networks' window only
            if source is None:  # this very frame under its own tracked geometry
                source_in, moved = self._moved(
                    geo, img, index, own_cam, own_geo, crop[0], offset[:2], window=(rows, cols)
                )
                source = (frame, index, own_cam)
            else:
                src_img = torch.from_numpy(source[0]).permute(2, 0, 1).float()
                source_in, moved = self._moved(geo, src_img, source[1], source[2], window=(rows, cols))
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
            _, inside = self.net(
                geo.uv[:, rows, cols].to(dev),
                geo.mask[..., rows, cols].to(dev),
                geo.mouth[..., rows, cols].to(dev),
                blank_face(crop[..., rows, cols].to(dev), region[..., rows, cols].to(dev)),
                region[..., rows, cols].to(dev),
                source_in[None, ..., rows, cols].to(dev) if self.net.source_input else None,
            )
        inside = inside.float()
        # the footage frame may show the face in other light than the frames the networks learned (a fade
        # to white, a brighter take): their render of the face the frame keeps (the mesh above and around
        # the painted part, whose geometry a dub leaves alone) says how, and the painted part follows
        mesh = geo.mask[..., rows, cols]
        kept_face = (erode(mesh, 2) > 0.5) & (dilate(paint[..., rows, cols], 3) == 0)
        gain, offset = colour_match(
            inside[0].cpu(), crop[0, :, rows, cols], kept_face[0, 0], min_pixels=paint.shape[-1]
        )
        lit = bool((gain != 1).any() or (offset != 0).any())  # most frames: the light the networks learned
        final = crop.to(inside).clone()  # outside the window the crop itself (its paste weight is 0)
        final[..., rows, cols] = inside
        # where a bank entry's interior may go, and the lips its colours follow (in the light the networks
        # learned, as the bank's own lips are): found once per frame
        window = self._interior_window(geo) if self.mouths is not None else None
        lips = self._rendered_lips(geo, final[0]) if window is not None else None
        if lit:  # on the mesh only: off it the compositing network paints from the footage, in its light
            on_mesh = box_blur(mesh, 2).to(dev)
            inside = (inside + on_mesh * (inside * (gain.to(dev) - 1) + offset.to(dev))).clamp(0, 1)
            final[..., rows, cols] = inside
        if self.detail:  # the footage's band of skin detail too where the surface moved rigidly
            own = (own_geo, own_cam, source[0] is frame)
            moved = self._band(moved, inside, (rows, cols), geo, vertices_cam, source, own)
        return FaceRender(
            frame,
            index,
            vertices_cam,
            (ys, xs),
            img,
            box,
            geo,
            crop[0],
            final[0],
            paint,
            moved if self.detail else None,
            window,
            lips,
            (gain, offset) if lit else None,
        )

    def _under_box(self, frame: np.ndarray, index: int) -> tuple | None:
        """The frame pixels under frame ``index``'s crop box, the only ones read and written: taken out of
        the frame (2 pixels more for the bilinear samples), every pixel position after is relative to them
        (box and principal point shifted alike, so the crop camera is the same). Returns their ``(rows,
        columns)`` slices, the ``(x, y, 0)`` offset, the shifted box, the pixels ``(3, h, w)`` float and the
        crop ``(1, 3, S, S)`` in [0, 1]; None when the box lies outside the frame."""
        ys, xs = box_slices(self.boxes[index], *frame.shape[:2], grow=2)
        if ys.stop <= ys.start or xs.stop <= xs.start:
            return None
        offset = np.array([xs.start, ys.start, 0.0])
        box = self.boxes[index] - offset
        img = torch.from_numpy(frame[ys, xs]).permute(2, 0, 1).float()
        crop = cut(img[None], torch.from_numpy(box[None]).float(), self.preset.crop) / 255
        return (ys, xs), offset, box, img, crop

    @torch.inference_mode()
    def surface(
        self, frame: np.ndarray, index: int, vertices_cam: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor, FrameGeometry] | None:
        """Footage frame ``index``'s crop ``(3, S, S)`` in [0, 1], the face network's render of
        ``vertices_cam`` in it (``(3, S, S)``, 0 off the mesh; only the first network, on the mesh's bounding
        box grown by :data:`SURFACE_MARGIN`, from the neural texture alone: the render the final image keeps
        well inside the mesh) and the crop's geometry; None when the face is outside the frame. What
        registration compares (:mod:`renderer.register`), at about half the networks' cost of
        :meth:`prepare`."""
        under = self._under_box(frame, index)
        if under is None:
            return None
        _, offset, box, _, crop = under
        geo = self.raster(vertices_cam, self.seq.focal, self.seq.center - offset[:2], box)
        # a renderer taking the footage's moved pixels gets none (validity 0): this frame's own pixels moved
        # onto its own tracked surface would copy the crop wherever the tracking puts the face
        source = torch.zeros(1, 4, *crop.shape[-2:]) if self.net.source_input else None
        dev, (rows, cols) = self.device, network_window(geo.mask, round(SURFACE_MARGIN * self.preset.crop))
        face = torch.zeros_like(crop[0])
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
            face[:, rows, cols] = (
                self.net.face(
                    geo.uv[:, rows, cols].to(dev),
                    geo.mask[..., rows, cols].to(dev),
                    geo.mouth[..., rows, cols].to(dev),
                    source[..., rows, cols].to(dev) if source is not None else None,
                )[0]
                .float()
                .cpu()
            )
        return crop[0], face, geo

    @torch.inference_mode()
    def composite(
        self, face: FaceRender, mouth: int | None = None, with_weight: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """:meth:`prepare`'s render pasted into its footage frame with bank entry ``mouth``'s interior
        (default: the entry of least :meth:`entry_costs`); as :meth:`render` returns."""
        frame = face.frame
        out = frame.copy()
        # the weight only when asked for: zeroing a float (H, W) plane is a full-frame pass (1080p: 8 MB)
        painted = np.zeros(frame.shape[:2], np.float32) if with_weight else None
        if face.geo is not None:
            interior = None
            if face.interior is not None:
                if mouth is None:
                    mouth = int(np.argmin(self.entry_costs(face)))
                interior = self._interior(face, mouth)
            # only the lower face and its surroundings are pasted, the footage keeping its full-resolution
            # detail where the paste weight is below 1 (1 - paint)
            pasted = paste_region(
                face.image,
                face.render.cpu() * 255,
                face.box,
                self.weight * region_weight(face.paint),
                detail=(face.crop * 255, 1 - face.paint),
                moved=face.moved,
                paint=face.paint,
                interior=interior,
            )
            # only the pixels under the crop box change: the rest of the uint8 frame is copied as it is
            if pasted is not None:
                ys, xs = face.slices
                pixels, alpha, (rows, cols) = pasted
                out[ys, xs][rows, cols] = pixels.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()
                if painted is not None:
                    painted[ys, xs][rows, cols] = alpha.numpy()
        return (out, painted) if with_weight else out


def network_window(paint: torch.Tensor, margin: int, multiple: int = 16) -> tuple[slice, slice]:
    """The rows and columns of the crop the networks need for ``paint`` ``(1, 1, S, S)`` (the part that is
    pasted): its bounding box grown by ``margin`` pixels (the networks' context, :data:`WINDOW_MARGIN`) and
    widened outwards to multiples of ``multiple`` (the strided U-Nets halve the size 4 times); the whole crop
    when nothing is painted."""
    size = paint.shape[-1]
    rows = torch.nonzero(paint[0, 0].amax(1) > 0)[:, 0]
    cols = torch.nonzero(paint[0, 0].amax(0) > 0)[:, 0]
    if len(rows) == 0:
        return slice(0, size), slice(0, size)

    def span(first: int, last: int) -> slice:
        lo = max(0, first - margin) // multiple * multiple
        hi = min(size, -(-(last + 1 + margin) // multiple) * multiple)
        return slice(lo, hi)

    return span(int(rows[0]), int(rows[-1])), span(int(cols[0]), int(cols[-1]))
