"""Rendering new geometry into the footage: crop → rasterize → neural render → paste back."""

from __future__ import annotations

import copy
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d

from nvp.face_model import FaceModel
from nvp.geometry import unposed
from nvp.tracked import TrackedSequence
from renderer.crop import MovedDetail, box_slices, colour_match, cut, feather, paste_region, region_weight
from renderer.data import (
    FrameGeometry,
    Rasterizer,
    blank_face,
    face_region,
    moved_source,
    sequence_boxes,
)
from renderer.masks import box_blur, dilate, erode
from renderer.mouths import light_costs
from renderer.networks import fast_bf16, load_renderer
from renderer.warp import mesh_edges, rigidity, sample_pixels, smooth, surface_points

LOWER_FACE = 0.02
"""Mouth weight (``FaceModel.mouth_weights``) above which a mesh pixel is part of the re-rendered lower
face."""

BAND_SIGMA = 2.0
"""Detail finer than about this many crop pixels (:func:`renderer.warp.smooth`) comes from the footage
moved onto the new surface rather than from the networks, where the surface moved rigidly
(:data:`STRAIN_LIMIT`; :func:`renderer.warp.moved_detail`). Chosen on dfrf__cnn2 (not a test person) with 1,
2 and 3: a dub's mouth-box high-frequency ratio 0.541 (none) → 0.570 / 0.574 / 0.573, the held-out
re-creation's mouth-box PSNR with detail from another frame −0.05 / −0.10 / −0.13 dB."""

STRAIN_LIMIT = 0.1
"""A surface point whose mesh edges stretched or shrank by this fraction between the source frame and the
new geometry gets none of the source's band of detail, a rigidly moved one all of it (linear in between,
:func:`renderer.warp.rigidity`). Chosen on dfrf__cnn2 (mouth box; the re-creation's detail from another
frame ≥ 1 s away, its PSNR honest; a dub's sharpness): strain 0.05 / 0.1 / 0.2 → re-creation 29.54 / 29.37 /
29.17 dB, dub high-frequency ratio 0.75 / 0.85 / 0.92 — against the vertices' displacement as the measure
(0.15 / 0.3 / 0.6 cm → 29.48 / 29.27 / 29.02 dB, 0.70 / 0.80 / 0.90), which refuses a chin the jaw carried
down unchanged. (Measured before the band fades at the silhouette, :meth:`FrameRenderer._band`, which took
out a dotted line there and with it 0.01-0.04 of these sharpness ratios.)"""

INTERIOR_GAIN = (0.5, 2.0)
"""Range of the per-channel gain that puts a mouth-bank entry's interior into the rendered frame's colours
(:meth:`FrameRenderer._colour_gains`)."""

INTERIOR_TOLERANCE = 0.25
"""Relative colour difference between a bank entry's lips and the rendered ones (per channel) left as it is
(:meth:`FrameRenderer._colour_gains`): within one take the rendered lips differ from the bank's real
ones by the networks' own error, which changes from frame to frame (gains on dfrf__cnn2 and
edtalk__pose_source2, 5th-95th percentile, 0.92-1.10 and 0.94-1.21; following it within 15 % cost 0.08 dB
of mouth-box PSNR on edtalk__pose_source2)."""

AGREEMENT_CM = 0.02
"""Cost (cm of inner-lip shape distance, :meth:`FrameRenderer.entry_costs`) per level of 255 of root mean
square difference between a mouth-bank entry's interior and the networks' soft interior. Chosen on open
held-out frames (inner-lip gap above 30 % of the person's range) of edtalk__pose_source2,
dfrf__cnn2 and wav2lipgfpgan kim (no test person), mouth-box PSNR: by shape 31.99 / 34.23 / 30.63 dB; by
shape + 0.005 / 0.01 / 0.02 / 0.05 cm per level (of the 8 nearest shapes) 33.56 / 34.72 / 30.81, 33.70 /
34.67 / 30.61, 33.45 / 34.87 / 30.64, 33.55 / 34.90 / 30.71; the difference alone (all 48 entries) 33.46 /
35.04 / 30.82. The entries' spread is 44-64 levels per frame (median), so the difference decides among
near shapes and the switch cost (:data:`renderer.mouths.SWITCH_CM`) is 2.5 levels."""

CANDIDATES = 8
"""Bank entries nearest in shape and light whose interior is compared with the networks' (the 8 together in
2.6 ms per open frame on one core): of 8, 12 or all 48 the same choices on the frames above but for 0.1 dB."""

MOUTH_LAG = 3
"""Output frames a stream renders ahead before it fixes a frame's mouth-bank entry
(:class:`renderer.mouths.EntryChooser`), each held in memory until then. Over 250 frames of audio-driven
dubs (edtalk__pose_source2, dfrf__cnn2) lag 0 / 1 / 3 / 6 / 12 chose 84-86 / 92-93 / 96-99 / 97-100 / 100 %
of the whole clip's best path's entries (path cost +0.8 / +0.2 / 0.0 / 0.0 / 0 %)."""

WINDOW_MARGIN = 0.25
"""The networks run on the part of the crop around the painted lower face, grown by this fraction of the
crop side (see :func:`network_window`): the upper face is never pasted, so it is not rendered either."""


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


class FrameRenderer:
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
        from renderer.mouths import MouthBank, interior_vertices

        self.net, self.preset, self.manifest = load_renderer(renderer_dir, device)
        bank = Path(renderer_dir) / "mouths.json"
        self.mouths = MouthBank.load(bank) if interiors and bank.exists() else None
        if self.mouths is not None:
            self._patches = torch.from_numpy(self.mouths.patches).permute(0, 3, 1, 2)  # uint8
            # halved and quartered, to compare an interior with the networks' at their resolution
            half = F.avg_pool2d(self._patches.float(), 2)
            self._pyramid = [half, F.avg_pool2d(half, 2)]
            self._inner = interior_vertices(model)
            lips = model.vertex_regions["lips"]
            self._lip_triangles = torch.from_numpy(
                lips[model.triangles].all(1) & ~model.triangle_regions["mouth_interior"]
            )
            recorded = len(self.mouths.light_frames) > 0  # the entries' own light, looked up once
            self._entry_light = self.mouths.light_at(self.mouths.frames) if recorded else None
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

    def mouth_costs(self, shapes: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """``(T, N)`` how well each mouth-bank entry suits output frames of inner-lip ``shapes`` ``(T, M, 3)``
        (:func:`renderer.mouths.sequence_shapes`) rendered over footage ``frames`` ``(T,)``: the shape
        distance (cm) plus, for a bank that recorded the footage's light, the cost of an entry shot in
        other light (:func:`renderer.mouths.light_costs`)."""
        costs = self.mouths.distances(shapes)
        if self._entry_light is not None:
            costs = costs + light_costs(self._entry_light, self.mouths.light_at(np.asarray(frames)))
        return costs

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
        whole: bool = False,
    ) -> FaceRender:
        """The networks' render of ``vertices_cam`` over footage frame ``index`` and what the paste needs
        (arguments as :meth:`render`), before a mouth-bank entry is chosen. ``whole``: the networks render
        the whole crop, not only the part around the painted lower face (:func:`network_window`)."""
        # only the frame pixels under the crop box are read and written: they are taken out of the frame
        # (2 pixels more for the bilinear samples) and every pixel position below is relative to them
        # (box and principal point shifted alike, so the crop camera is the same)
        ys, xs = box_slices(self.boxes[index], *frame.shape[:2], grow=2)
        if ys.stop <= ys.start or xs.stop <= xs.start:  # the face is outside the frame: nothing to paint
            return FaceRender(frame, index, vertices_cam, (ys, xs))
        offset = np.array([xs.start, ys.start, 0.0])
        box = self.boxes[index] - offset
        f, c = self.seq.focal, self.seq.center - offset[:2]
        geo = self.raster(vertices_cam, f, c, box)
        region, lower = geo.region, geo.lower
        orig = None
        if original_cam is not None:
            orig = self.raster(original_cam, f, c, box)
            region, lower = torch.maximum(region, orig.region), torch.maximum(lower, orig.lower)
        img = torch.from_numpy(frame[ys, xs]).permute(2, 0, 1).float()
        crop = cut(img[None], torch.from_numpy(box[None]).float(), self.preset.crop) / 255
        source_in, moved = None, None
        # the footage frame's own geometry (its background off the mesh is kept, whatever the source)
        own_cam, own_geo = (vertices_cam, geo) if original_cam is None else (original_cam, orig)
        if self.detail or self.net.source_input:
            if source is None:  # this very frame under its own tracked geometry
                source_in, moved = self._moved(geo, img, index, own_cam, own_geo, crop[0], offset[:2])
                source = (frame, index, own_cam)
            else:
                src_img = torch.from_numpy(source[0]).permute(2, 0, 1).float()
                source_in, moved = self._moved(geo, src_img, source[1], source[2])
        # only the lower face (where the geometry can differ from the footage) and its surroundings are
        # pasted: eyes, brows and forehead keep the footage's own pixels at full resolution; around the
        # painted part the footage keeps its full-resolution detail too (the crop is softer), while inside
        # it nothing of the footage's own mouth and chin shows through
        paint = face_region((lower > LOWER_FACE).float(), self.preset.region_grow) * region
        margin = self.preset.crop if whole else self.window_margin
        dev, (rows, cols) = self.device, network_window(paint, margin)
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

    @torch.inference_mode()
    def composite(
        self, face: FaceRender, mouth: int | None = None, with_weight: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """:meth:`prepare`'s render pasted into its footage frame with bank entry ``mouth``'s interior
        (default: the entry of least :meth:`entry_costs`); as :meth:`render` returns."""
        frame = face.frame
        out, painted = frame.copy(), np.zeros(frame.shape[:2], np.float32)
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
                painted[ys, xs][rows, cols] = alpha.numpy()
        return (out, painted) if with_weight else out

    def entry_costs(self, face: FaceRender) -> np.ndarray:
        """``(N,)`` how well each mouth-bank entry suits :meth:`prepare`'s ``face``: :meth:`mouth_costs`
        (the inner lips' shape, the light) plus, where the face shows its mouth interior, for the
        :data:`CANDIDATES` best of them, :data:`AGREEMENT_CM` per level of how far the entry's interior,
        moved onto the face, lies from the networks' own soft interior (:meth:`_disagreement`); the others
        cost infinity. The networks were trained on this person's footage, so their blurred interior
        says where the teeth, tongue and shadow lie for this geometry, which the inner lips' shape alone
        does not (on open held-out frames, the entry chosen by shape keeps 31.99 / 34.23 / 30.63 dB of
        mouth-box PSNR on edtalk__pose_source2, dfrf__cnn2, wav2lipgfpgan kim, the best one 35.71 / 35.81 /
        32.74)."""
        pose = self.seq.rotation[face.index], self.seq.translation[face.index]
        shape = unposed(face.vertices_cam[self._inner], *pose)[None].astype(np.float32)
        costs = self.mouth_costs(shape, np.array([face.index]))[0]
        if face.interior is None:
            return costs
        candidates = np.argsort(costs, kind="stable")[:CANDIDATES]
        out = np.full_like(costs, np.inf)
        apart = self._disagreement(face, face.interior, candidates)
        out[candidates] = costs[candidates] + AGREEMENT_CM * apart
        return out

    def _disagreement(
        self, face: FaceRender, window: tuple[int, int, int, int], entries: np.ndarray
    ) -> np.ndarray:
        """``(K,)`` root mean square difference (levels of 255) between each of bank ``entries``' interior
        moved onto ``face`` (in the frame's colours, :meth:`_colour_gains`) and the networks' render, inside
        the mouth interior, both blurred by a crop pixel (the networks' interior is soft; on the frames of
        :data:`AGREEMENT_CM` a blur of 0.5 / 1 / 2 crop pixels chose interiors of 33.50 / 34.89 / 30.66,
        33.45 / 34.90 / 30.65 and 33.74 / 34.66 / 30.76 dB, keeping their fine detail alike: high-frequency
        ratio 0.996 / 0.987 / 0.891, 1.014 / 0.991 / 0.890, 0.996 / 1.006 / 0.925, by shape 1.000 / 1.025 /
        0.854)."""
        geo, render = face.geo, face.render
        r0, r1, c0, c1 = window
        size = geo.mouth.shape[-1]
        pad = 3
        r0p, r1p, c0p, c1p = max(r0 - pad, 0), min(r1 + pad, size), max(c0 - pad, 0), min(c1 + pad, size)
        inside = geo.mouth[0, 0, r0p:r1p, c0p:c1p] > 0.5
        tri, bary = geo.triangle_id[r0p:r1p, c0p:c1p], geo.barycentric[r0p:r1p, c0p:c1p]
        pos = self.mouths.positions(entries, tri, bary, self._triangles)  # (K, h, w, 2)
        # patch pixels per crop pixel: read from the level of the patches' pyramid that matches it
        step = (pos[:, :, 1:] - pos[:, :, :-1]).norm(dim=-1)[:, inside[:, 1:] & inside[:, :-1]]
        scale = float(step.median()) if step.numel() else 1.0
        level = int(np.clip(np.log2(max(scale, 1.0)), 0, len(self._pyramid)))
        patches = (self._patches if level == 0 else self._pyramid[level - 1])[torch.from_numpy(entries)]
        gains = self._colour_gains(entries, face.lips)
        moved = sample_pixels(patches, pos / 2**level) * gains[:, :, None, None]  # sample_pixels: as float
        moved = self._in_light(moved, face.light)
        blurred = gaussian_blur2d(
            torch.cat([moved, render[None, :, r0p:r1p, c0p:c1p].float().cpu() * 255]),
            (7, 7),
            (1.0, 1.0),
            "replicate",
        )
        diff = ((blurred[:-1] - blurred[-1:]) ** 2).mean(1)[:, inside]
        return diff.mean(1).sqrt().numpy() if diff.shape[1] else np.zeros(len(entries))

    def _band(
        self,
        moved: MovedDetail,
        inside: torch.Tensor,
        window: tuple[slice, slice],
        geo: FrameGeometry,
        vertices_cam: np.ndarray,
        source: tuple[np.ndarray, int, np.ndarray],
        own: tuple[FrameGeometry, np.ndarray, bool],
    ) -> MovedDetail:
        """``moved`` with the band of detail finer than :data:`BAND_SIGMA` crop pixels taken from the
        source where the surface moved rigidly (:data:`STRAIN_LIMIT`), and from the painted frame's own
        pixels in the band off the mesh that the networks paint (:meth:`_kept_background`), whatever the
        source: a detail source from another frame changes the surface's detail, not what lies around it.
        ``own = (geometry, camera-frame vertices, is the source)`` of the painted footage frame; ``inside``
        ``(1, C, h, w)`` is the networks' render over ``window``."""
        rows, cols = window
        tri, bary = geo.triangle_id[rows, cols], geo.barycentric[rows, cols]
        own_geo, own_cam, own_is_source = own

        def rigid_pixels(cam: np.ndarray) -> torch.Tensor:
            rigid = torch.from_numpy(rigidity(vertices_cam, cam, self._edges, STRAIN_LIMIT))
            return surface_points(tri, bary, self._triangles, rigid[:, None])[..., 0]

        rigid_px = rigid_pixels(source[2])
        band = torch.zeros_like(moved.fine)
        band[rows, cols] = moved.fine[rows, cols] * rigid_px
        background = (tri < 0) & (own_geo.triangle_id[rows, cols] < 0)
        kept = self._kept_background(
            background, tri >= 0, rigid_px if own_is_source else rigid_pixels(own_cam)
        )
        # fade the band out within about a crop pixel of the border of what the source shows (the
        # silhouette, an occlusion; not the mouth interior, which has its own pixels): a source point there
        # may sit on an edge of the source frame, whose moved detail drew a dotted line along the jaw
        shown = (moved.fine[rows, cols] > 0) | (kept > 0) | (geo.mouth[0, 0, rows, cols] > 0)
        fade = ((smooth(shown[None, None].float(), 1.0)[0, 0] - 0.5) * 2).clamp(0, 1)
        render_band = torch.zeros(inside.shape[1], *band.shape)
        render_band[:, rows, cols] = (inside - smooth(inside, BAND_SIGMA))[0] * 255
        if own_is_source:  # the kept band is the source's too: its pixels there are the pixels themselves,
            # so a frame pixel on the silhouette reads one source point between the surface's and its own
            fine, positions = moved.fine.clone(), moved.positions.clone()
            fine[rows, cols] = torch.where(background, kept, fine[rows, cols])
            band[rows, cols] = torch.where(background, kept, band[rows, cols]) * fade
            size, side = self.preset.crop, float(moved.source_box[2])
            centres = (torch.arange(size, dtype=torch.float32) + 0.5) * (side / size)
            origin = torch.as_tensor(moved.source_box[:2] - side / 2, dtype=torch.float32)
            pixels = torch.stack(torch.meshgrid(centres, centres, indexing="xy"), -1)[rows, cols] + origin
            positions[rows, cols] = torch.where(background[..., None], pixels, positions[rows, cols])
            return replace(moved, fine=fine, band=band, positions=positions, render_band=render_band)
        band[rows, cols] *= fade
        kept_map = torch.zeros_like(moved.fine)
        kept_map[rows, cols] = kept * fade
        return replace(moved, band=band, render_band=render_band, kept=kept_map)

    def _kept_background(
        self, background: torch.Tensor, surface: torch.Tensor, rigid_px: torch.Tensor
    ) -> torch.Tensor:
        """Around the painted lower face lies a band off the mesh (the region is grown to cover the
        footage's real chin edge) that the networks paint, softly. Where it is ``background`` ``(h, w)``
        under both the footage's and the new geometry and every ``surface`` point within reach moved
        rigidly (``rigid_px``: jaw line, collar under a chin the jaw carried), the footage's own pixels there
        are right.
        Returns how far they are trusted, ``(h, w)`` in [0, 1]."""
        reach = max(1, round(self.preset.region_grow * self.preset.crop)) + 1
        moving = torch.where(surface, 1 - rigid_px, torch.zeros_like(rigid_px))
        return background * (1 - dilate(moving[None, None], reach)[0, 0])

    @staticmethod
    def _interior_window(geo: FrameGeometry) -> tuple[int, int, int, int] | None:
        """First and last-but-one rows and columns of the crop around the mouth interior ``geo`` shows (a
        pixel more each side), None when it shows none."""
        inside = geo.mouth[0, 0]
        rows = torch.nonzero(inside.amax(1))[:, 0]
        if len(rows) == 0:
            return None
        cols = torch.nonzero(inside.amax(0))[:, 0]
        size = inside.shape[0]
        r0, r1 = max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 2, size)
        c0, c1 = max(int(cols[0]) - 1, 0), min(int(cols[-1]) + 2, size)
        return r0, r1, c0, c1

    def _interior(
        self, face: FaceRender, mouth: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[int, int]]:
        """The ``interior`` argument of :func:`renderer.crop.paste_region` for a ``face`` that shows its
        mouth interior: bank entry ``mouth``'s patch ``(3, P, P)`` in this frame's colours
        (:meth:`_colour_gains` against the rendered lips), and over the crop window around the interior
        (``face.interior``), the patch pixel at each crop pixel ``(h, w, 2)``, the interior mask ``(h, w)``
        and the window's first row and column."""
        geo, (r0, r1, c0, c1) = face.geo, face.interior
        tri, bary = geo.triangle_id[r0:r1, c0:c1], geo.barycentric[r0:r1, c0:c1]
        pos = self.mouths.positions(mouth, tri, bary, self._triangles)
        gain = self._colour_gains(np.array([mouth]), face.lips)[0]
        patch = self._in_light(self._patches[mouth].float() * gain[:, None, None], face.light)
        return patch, pos, geo.mouth[0, 0, r0:r1, c0:c1], (r0, c0)

    def _rendered_lips(
        self, geo: FrameGeometry, render: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The lips of ``geo`` in the render ``render`` ``(3, S, S)`` (in [0, 1]): their pixels' triangles
        ``(L,)`` and barycentric coordinates ``(L, 3)`` and the render's summed colour there ``(3,)``; None
        when fewer than 8 pixels show them."""
        tri = geo.triangle_id
        lips = (tri >= 0) & self._lip_triangles[tri.clamp_min(0)]
        if int(lips.sum()) < 8:
            return None
        rendered = render[:, lips.to(render.device)].float().sum(-1).cpu()  # only the lips leave the device
        return tri[lips], geo.barycentric[lips], rendered

    @staticmethod
    def _in_light(levels: torch.Tensor, light: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
        """Bank pixels ``(..., 3, h, w)`` (levels of 255) put into a frame's light (``FaceRender.light``)."""
        if light is None:
            return levels
        gain, offset = light
        return levels * gain + offset * 255

    def _colour_gains(self, entries: np.ndarray, lips: tuple[torch.Tensor, ...] | None) -> torch.Tensor:
        """``(K, 3)`` per-channel gains that give bank ``entries``' lips the rendered ``lips``' mean colour
        (:meth:`_rendered_lips`): a bank frame shot in other light (a later take, the camera's white
        balance or exposure drifting) would paste teeth of another colour. Only the part of the gain beyond
        :data:`INTERIOR_TOLERANCE` is kept, within :data:`INTERIOR_GAIN`."""
        if lips is None:
            return torch.ones(len(entries), 3)
        tri, bary, rendered = lips
        pos = self.mouths.positions(entries, tri, bary, self._triangles)  # (K, L, 2)
        bank = sample_pixels(self._patches[torch.from_numpy(entries)], pos).sum(-1)
        gain = (rendered * 255 / bank.clamp_min(1.0)).clamp(*INTERIOR_GAIN)
        return gain / gain.clamp(1 / (1 + INTERIOR_TOLERANCE), 1 + INTERIOR_TOLERANCE)

    def _moved(
        self,
        geo: FrameGeometry,
        src_img: torch.Tensor,
        src_index: int,
        src_cam: np.ndarray,
        src_geo: FrameGeometry | None = None,
        src_crop: torch.Tensor | None = None,
        offset: np.ndarray | None = None,
    ) -> tuple[torch.Tensor, tuple]:
        """The source frame ``src_img`` ``(3, H, W)`` (frame ``src_index`` under ``src_cam`` ``(V, 3)``)
        moved onto the surface of ``geo``: the network's ``(4, S, S)`` source input and the ``moved``
        argument of :func:`renderer.crop.paste`; ``src_geo`` / ``src_crop`` (in [0, 1]) when the caller has
        them already; ``offset``: the frame pixel ``(x, y)`` where ``src_img`` starts (a part of the
        frame)."""
        shift = np.zeros(2) if offset is None else offset
        src_box = self.boxes[src_index] - np.array([*shift, 0.0])
        f, c = self.seq.focal, self.seq.center - shift
        if src_geo is None:
            src_geo = self.raster(src_cam, f, c, src_box)
        if src_crop is None:
            src_crop = cut(src_img[None], torch.from_numpy(src_box[None]).float(), self.preset.crop)[0] / 255
        source_in, pos, valid = moved_source(
            geo, src_crop, src_box, src_cam, src_geo.depth, (f, c), self._triangles, self._movable
        )
        no_band = torch.zeros_like(valid)  # until :meth:`_band`
        no_render_band = torch.zeros_like(src_crop)
        moved = MovedDetail(src_img, src_crop * 255, src_box, pos, valid, no_band, no_render_band, BAND_SIGMA)
        return source_in, moved


def network_window(paint: torch.Tensor, margin: int, multiple: int = 16) -> tuple[slice, slice]:
    """The rows and columns of the crop the networks need for ``paint`` ``(1, 1, S, S)`` (the part that is
    pasted): its bounding box grown by ``margin`` pixels (the networks' context: measured on dfrf__cnn2,
    48 px of a 192² crop change no output pixel by more than 5 of 255) and widened outwards to multiples of
    ``multiple`` (the strided U-Nets halve the size 4 times); the whole crop when nothing is painted."""
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


T = TypeVar("T")

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
    workers: int | None = None,
    sources: Callable[[int], tuple[np.ndarray, int, np.ndarray]] | None = None,
    start_entries: Mapping[str, int | None] | None = None,
    decided: list[dict[str, int | None]] | None = None,
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """The one render loop: footage ``frames`` (``(H, W, 3)`` uint8, one per entry of ``indices``, the
    footage frame each one is) in; for each, in order, the footage frame and its renders
    ``{name: (H, W, 3) uint8}`` out, with a progress bar that is closed however the loop ends (an error,
    or the consumer stopping).

    A variant ``None`` re-renders the frame from its own tracking (re-creation); a :data:`Geometry` renders
    ``geometry(j, index, tracked_cam)`` and the replaced region also covers the tracked face (a dub).
    ``sources(j)``: the ``source`` of frame ``j``'s fine detail (default: the footage frame itself), e.g. an
    evaluation that must not move the real frame's own detail onto its re-creation. With a mouth bank,
    each variant's open mouths get their bank entries from an :class:`renderer.mouths.EntryChooser` over
    :meth:`FrameRenderer.entry_costs` (:data:`MOUTH_LAG` frames ahead), so the teeth do not flicker.
    ``start_entries``: each variant's entry of the frame before the first (a resumed job then chooses as
    an uninterrupted one would); ``decided``, when given, receives every frame's entries, in order, before
    the frame is yielded.

    On the CPU, ``workers`` frames are rendered at once, each by its own thread and renderer
    (:meth:`FrameRenderer.twin`) on one PyTorch thread, while the caller consumes (encodes) the previous
    ones: first the networks (:meth:`FrameRenderer.prepare`), then, once the entry is chosen, the paste
    (:meth:`FrameRenderer.composite`). Default: one per core PyTorch would use (``NVP_THREADS`` /
    ``OMP_NUM_THREADS`` fix it). Per-frame work is small and partly single-threaded (rasterizing,
    pasting), so frames in parallel use two cores far better than two threads inside each frame (measured
    on a 2-core EPYC, 512² dub: one frame on two threads 56.7 ms, two frames on one thread each 30.5 ms per
    frame), and a single-threaded worker has no OpenMP barriers that stall when another process takes a
    core. On a GPU, one frame at a time."""
    from tqdm import tqdm

    from nvp.threads import frame_workers
    from renderer.mouths import EntryChooser

    n = 1 if str(fr.device) != "cpu" else (workers or frame_workers())
    bar = tqdm(total=len(indices), desc=desc, unit="frame", disable=not progress)
    choosers = {name: EntryChooser(MOUTH_LAG) for name in variants} if fr.mouths is not None else None
    for name, chooser in (choosers or {}).items():
        chooser.current = (start_entries or {}).get(name)

    def prepare(renderer: FrameRenderer, j: int, k: int, frame: np.ndarray) -> dict[str, tuple]:
        tracked = renderer.tracked(k)
        source = None if sources is None else sources(j)
        faces = {
            name: renderer.prepare(frame, k, tracked, source=source)
            if geo is None
            else renderer.prepare(frame, k, geo(j, k, tracked), tracked, source=source)
            for name, geo in variants.items()
        }
        costs = {name: renderer.entry_costs(face) if choosers else None for name, face in faces.items()}
        return {name: (face, costs[name]) for name, face in faces.items()}

    with ExitStack() as stack:
        stack.callback(bar.close)
        pool = stack.enter_context(RenderWorkers(fr, n))

        def composite(faces: dict[str, tuple], entries: dict[str, int | None]) -> Callable:
            return lambda r: {name: r.composite(face, entries[name]) for name, (face, _) in faces.items()}

        started: deque = deque()  # (frame, networks' future), in order
        waiting: deque = deque()  # (frame, prepared faces) whose bank entries are not fixed yet
        pasting: deque = deque()  # (frame, composite's future)

        def choose(item: tuple[np.ndarray, dict[str, tuple]] | None) -> None:
            """Hands the frames whose bank entries ``item`` (the next frame and its prepared faces) fixes
            to the paste; all frames still waiting when ``item`` is None (the end)."""
            if item is not None:
                waiting.append(item)
            if choosers is None:
                fixed = {name: [None] * len(waiting) for name in variants}
            elif item is None:
                fixed = {name: c.flush() for name, c in choosers.items()}
            else:
                fixed = {name: choosers[name].push(item[1][name][1]) for name in variants}
            for entries in zip(*fixed.values(), strict=True):
                frame, prepared = waiting.popleft()
                chosen = dict(zip(variants, entries, strict=True))
                if decided is not None:
                    decided.append(chosen)
                pasting.append((frame, pool.submit(composite(prepared, chosen))))

        def done(limit: int) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
            while len(pasting) > limit:
                frame, future = pasting.popleft()
                yield frame, future.result()
                bar.update(1)

        for j, (k, frame) in enumerate(zip(indices, frames, strict=False)):
            started.append((frame, pool.submit(partial(prepare, j=j, k=int(k), frame=frame))))
            while len(started) > n - 1:
                first, future = started.popleft()
                choose((first, future.result()))
                yield from done(n - 1)
        while started:
            first, future = started.popleft()
            choose((first, future.result()))
        choose(None)
        yield from done(0)


class RenderWorkers:
    """``workers`` renderers of one person (``fr`` and twins, :meth:`FrameRenderer.twin`), each on its own
    thread with one PyTorch thread (see :func:`render_frames`), or ``fr`` alone in the calling thread when
    ``workers`` is 1 (a profiler sees it; a GPU renders one frame at a time anyway). Use as a context
    manager: leaving it stops the threads (what has not started is cancelled) and closes the twins."""

    def __init__(self, fr: FrameRenderer, workers: int) -> None:
        self._stack = ExitStack()
        self._idle = [fr] + [self._stack.enter_context(fr.twin()) for _ in range(workers - 1)]
        self._pool = None
        if workers > 1:
            self._pool = ThreadPoolExecutor(workers, initializer=torch.set_num_threads, initargs=(1,))
            self._stack.enter_context(self._pool)
            self._stack.callback(self._pool.shutdown, cancel_futures=True)  # first: nothing new starts

    def __enter__(self) -> RenderWorkers:
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def submit(self, job: Callable[[FrameRenderer], T]) -> Future[T]:
        """``job(renderer)`` on a free renderer; its future."""

        def run() -> T:
            renderer = self._idle.pop()  # list.pop/append are atomic; at most `workers` jobs run at once
            try:
                return job(renderer)
            finally:
                self._idle.append(renderer)

        if self._pool is not None:
            return self._pool.submit(run)
        done: Future = Future()
        done.set_result(run())
        return done
