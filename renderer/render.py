"""Rendering new geometry into the footage: crop → rasterize → neural render → paste back."""

from __future__ import annotations

import copy
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from nvp.face_model import FaceModel
from nvp.geometry import unposed
from nvp.tracked import TrackedSequence
from renderer.crop import MovedDetail, box_slices, cut, feather, paste_region, region_weight
from renderer.data import (
    FrameGeometry,
    Rasterizer,
    blank_face,
    face_region,
    moved_source,
    sequence_boxes,
)
from renderer.masks import dilate
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
(:meth:`FrameRenderer._in_frame_colours`)."""

INTERIOR_TOLERANCE = 0.25
"""Relative colour difference between a bank entry's lips and the rendered ones (per channel) left as it is
(:meth:`FrameRenderer._in_frame_colours`): within one take the rendered lips differ from the bank's real
ones by the networks' own error, which changes from frame to frame (gains on dfrf__cnn2 and
edtalk__pose_source2, 5th-95th percentile, 0.92-1.10 and 0.94-1.21; following it within 15 % cost 0.08 dB
of mouth-box PSNR on edtalk__pose_source2)."""

WINDOW_MARGIN = 0.25
"""The networks run on the part of the crop around the painted lower face, grown by this fraction of the
crop side (see :func:`network_window`): the upper face is never pasted, so it is not rendered either."""


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
        ``original_cam`` (or ``vertices_cam`` when there is none). The mouth interior gets none.

        With a mouth bank (``self.mouths``), where the new geometry shows the mouth interior the interior
        of bank entry ``mouth`` is pasted, moved onto it (default: the entry whose inner lips are shaped
        most like ``vertices_cam``'s; a dub passes a flicker-free choice,
        :func:`renderer.mouths.choose_entries`).

        ``with_weight``: also return the ``(H, W)`` float32 weight of the render in the output (0 = the
        footage's own pixel), i.e. where nvp changed the picture."""
        # only the frame pixels under the crop box are read and written: they are taken out of the frame
        # (2 pixels more for the bilinear samples) and every pixel position below is relative to them
        # (box and principal point shifted alike, so the crop camera is the same)
        ys, xs = box_slices(self.boxes[index], *frame.shape[:2], grow=2)
        if ys.stop <= ys.start or xs.stop <= xs.start:  # the face is outside the frame: nothing to paint
            out = frame.copy()
            return (out, np.zeros(frame.shape[:2], np.float32)) if with_weight else out
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
        source_in, moved, src_geo = None, None, None
        if self.detail or self.net.source_input:
            if source is None:  # this very frame under its own tracked geometry
                cam, src_geo = (vertices_cam, geo) if original_cam is None else (original_cam, orig)
                source_in, moved = self._moved(geo, img, index, cam, src_geo, crop[0], offset[:2])
                source = (frame, index, cam)
            else:
                src_img = torch.from_numpy(source[0]).permute(2, 0, 1).float()
                source_in, moved = self._moved(geo, src_img, source[1], source[2])
        # only the lower face (where the geometry can differ from the footage) and its surroundings are
        # pasted: eyes, brows and forehead keep the footage's own pixels at full resolution; around the
        # painted part the footage keeps its full-resolution detail too (the crop is softer), while inside
        # it nothing of the footage's own mouth and chin shows through
        paint = face_region((lower > LOWER_FACE).float(), self.preset.region_grow) * region
        dev, (rows, cols) = self.device, network_window(paint, self.window_margin)
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
        keep = 1 - paint  # where the paste adds the footage's own full-resolution detail
        if self.detail:  # the footage's band of skin detail too where the surface moved rigidly
            moved = self._band(moved, inside, (rows, cols), geo, src_geo, vertices_cam, index, source)
        final = crop.to(inside).clone()  # outside the window the crop itself (its paste weight is 0)
        final[..., rows, cols] = inside
        weight = self.weight * region_weight(paint)
        pasted = paste_region(
            img,
            final[0].cpu() * 255,
            box,
            weight,
            detail=(crop[0] * 255, keep),
            moved=moved if self.detail else None,
            paint=paint,
            interior=self._interior(geo, vertices_cam, index, mouth, final[0]),
        )
        # only the pixels under the crop box change: the rest of the uint8 frame is copied as it is
        out, painted = frame.copy(), np.zeros(frame.shape[:2], np.float32)
        if pasted is not None:
            pixels, alpha, (rows, cols) = pasted
            out[ys, xs][rows, cols] = pixels.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()
            painted[ys, xs][rows, cols] = alpha.numpy()
        return (out, painted) if with_weight else out

    def _band(
        self,
        moved: MovedDetail,
        inside: torch.Tensor,
        window: tuple[slice, slice],
        geo: FrameGeometry,
        src_geo: FrameGeometry | None,
        vertices_cam: np.ndarray,
        index: int,
        source: tuple[np.ndarray, int, np.ndarray],
    ) -> MovedDetail:
        """``moved`` with the band of detail finer than :data:`BAND_SIGMA` crop pixels taken from the
        source where the surface moved rigidly (:data:`STRAIN_LIMIT`) — and, when the source is this very
        frame (``src_geo``), from its own pixels in the band off the mesh that the networks paint (see
        :meth:`_kept_background`); ``inside`` ``(1, C, h, w)`` is the networks' render over ``window``."""
        rows, cols = window
        rigid = rigidity(vertices_cam, source[2], self._edges, STRAIN_LIMIT)
        tri, bary = geo.triangle_id[rows, cols], geo.barycentric[rows, cols]
        rigid_px = surface_points(tri, bary, self._triangles, torch.from_numpy(rigid)[:, None])[..., 0]
        band = torch.zeros_like(moved.fine)
        band[rows, cols] = moved.fine[rows, cols] * rigid_px
        fine, positions = moved.fine.clone(), moved.positions.clone()
        if src_geo is not None:  # the source is this frame: its background is this frame's too
            background = (tri < 0) & (src_geo.triangle_id[rows, cols] < 0)
            kept = self._kept_background(background, tri >= 0, rigid_px)
            band[rows, cols] = torch.where(background, kept, band[rows, cols])
            fine[rows, cols] = torch.where(background, kept, fine[rows, cols])
            # there the source pixel is the pixel itself
            size, side = self.preset.crop, float(moved.source_box[2])
            centres = (torch.arange(size, dtype=torch.float32) + 0.5) * (side / size)
            origin = torch.as_tensor(moved.source_box[:2] - side / 2, dtype=torch.float32)
            own = torch.stack(torch.meshgrid(centres, centres, indexing="xy"), -1) + origin
            positions[rows, cols] = torch.where(background[..., None], own[rows, cols], positions[rows, cols])
        # fade the band out within about a crop pixel of the border of what the source shows (the
        # silhouette, an occlusion; not the mouth interior, which has its own pixels): a source point there
        # may sit on an edge of the source frame, whose moved detail drew a dotted line along the jaw
        shown = (fine[rows, cols] > 0) | (geo.mouth[0, 0, rows, cols] > 0)
        cover = smooth(shown[None, None].float(), 1.0)[0, 0]
        band[rows, cols] *= ((cover - 0.5) * 2).clamp(0, 1)
        render_band = torch.zeros(inside.shape[1], *band.shape)
        render_band[:, rows, cols] = (inside - smooth(inside, BAND_SIGMA))[0] * 255
        return replace(moved, fine=fine, band=band, positions=positions, render_band=render_band)

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

    def _interior(
        self,
        geo: FrameGeometry,
        vertices_cam: np.ndarray,
        index: int,
        mouth: int | None,
        render: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[int, int]] | None:
        """The ``interior`` argument of :func:`renderer.crop.paste_region`: bank entry ``mouth``'s patch
        ``(3, P, P)`` in this frame's colours (:meth:`_in_frame_colours`, against ``render`` ``(3, S, S)``,
        the rendered crop in [0, 1]), and over the crop window around the interior, the patch pixel at each
        crop pixel ``(h, w, 2)``, the interior mask ``(h, w)`` and the window's first row and column; None
        without a bank or when no interior shows."""
        if self.mouths is None:
            return None
        inside = geo.mouth[0, 0]
        rows = torch.nonzero(inside.amax(1))[:, 0]
        if len(rows) == 0:
            return None
        cols = torch.nonzero(inside.amax(0))[:, 0]
        size = inside.shape[0]
        r0, r1 = max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 2, size)
        c0, c1 = max(int(cols[0]) - 1, 0), min(int(cols[-1]) + 2, size)
        if mouth is None:
            pose = self.seq.rotation[index], self.seq.translation[index]
            shape = unposed(vertices_cam[self._inner], *pose)
            mouth = int(np.argmin(self.mouth_costs(shape[None].astype(np.float32), np.array([index]))[0]))
        tri, bary = geo.triangle_id[r0:r1, c0:c1], geo.barycentric[r0:r1, c0:c1]
        pos = self.mouths.positions(mouth, tri, bary, self._triangles)
        patch = self._in_frame_colours(self._patches[mouth].float(), mouth, geo, render)
        return patch, pos, inside[r0:r1, c0:c1], (r0, c0)

    def _in_frame_colours(
        self, patch: torch.Tensor, mouth: int, geo: FrameGeometry, render: torch.Tensor
    ) -> torch.Tensor:
        """Bank entry ``mouth``'s ``patch`` ``(3, P, P)`` with each colour channel scaled so that its lips
        have the rendered lips' mean colour (``render`` ``(3, S, S)`` in [0, 1] over ``geo``): a bank frame
        shot in other light (a later take, the camera's white balance or exposure drifting) would paste
        teeth of another colour. Only the part of the gain beyond :data:`INTERIOR_TOLERANCE` is applied, and
        it stays within :data:`INTERIOR_GAIN`."""
        tri = geo.triangle_id
        lips = (tri >= 0) & self._lip_triangles[tri.clamp_min(0)]
        if int(lips.sum()) < 8:
            return patch
        pos = self.mouths.positions(mouth, tri[lips], geo.barycentric[lips], self._triangles)
        bank = sample_pixels(patch, pos).sum(-1)
        rendered = render[:, lips.to(render.device)].float().sum(-1).cpu()  # only the lips leave the device
        gain = (rendered * 255 / bank.clamp_min(1.0)).clamp(*INTERIOR_GAIN)
        gain = gain / gain.clamp(1 / (1 + INTERIOR_TOLERANCE), 1 + INTERIOR_TOLERANCE)
        return patch * gain[:, None, None]

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
    mouths: Sequence[int] | None = None,
    sources: Callable[[int], tuple[np.ndarray, int, np.ndarray]] | None = None,
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """The one render loop: footage ``frames`` (``(H, W, 3)`` uint8, one per entry of ``indices``, the
    footage frame each one is) in; for each, in order, the footage frame and its renders
    ``{name: (H, W, 3) uint8}`` out, with a progress bar that is closed however the loop ends (an error,
    or the consumer stopping).

    A variant ``None`` re-renders the frame from its own tracking (re-creation); a :data:`Geometry` renders
    ``geometry(j, index, tracked_cam)`` and the replaced region also covers the tracked face (a dub), with
    mouth-bank entry ``mouths[j]`` in its open mouth when given (see :meth:`FrameRenderer.render`).
    ``sources(j)``: the ``source`` of frame ``j``'s fine detail (default: the footage frame itself), e.g. an
    evaluation that must not move the real frame's own detail onto its re-creation.

    On the CPU, ``workers`` frames are rendered at once, each by its own thread and renderer
    (:meth:`FrameRenderer.twin`) on one PyTorch thread, while the caller consumes (encodes) the previous
    ones. Default: one per core PyTorch would use (``NVP_THREADS`` / ``OMP_NUM_THREADS`` fix it). Per-frame
    work is small and partly single-threaded (rasterizing, pasting), so frames in parallel use two cores
    far better than two threads inside each frame (measured on a 2-core EPYC, 512² dub: one frame on two
    threads 56.7 ms, two frames on one thread each 30.5 ms per frame), and a single-threaded worker has no
    OpenMP barriers that stall when another process takes a core. On a GPU, one frame at a time."""
    from tqdm import tqdm

    from nvp.threads import frame_workers

    n = 1 if str(fr.device) != "cpu" else (workers or frame_workers())
    bar = tqdm(total=len(indices), desc=desc, unit="frame", disable=not progress)

    def job(renderer: FrameRenderer, j: int, k: int, frame: np.ndarray) -> dict[str, np.ndarray]:
        tracked = renderer.tracked(k)
        source = None if sources is None else sources(j)
        return {
            name: renderer.render(frame, k, tracked, source=source)
            if geo is None
            else renderer.render(
                frame,
                k,
                geo(j, k, tracked),
                tracked,
                source=source,
                mouth=None if mouths is None else mouths[j],
            )
            for name, geo in variants.items()
        }

    with ExitStack() as stack:
        stack.callback(bar.close)
        if n == 1:
            for j, (k, frame) in enumerate(zip(indices, frames, strict=False)):
                yield frame, job(fr, j, int(k), frame)
                bar.update(1)
            return
        idle = [fr] + [stack.enter_context(fr.twin()) for _ in range(n - 1)]
        pool = stack.enter_context(ThreadPoolExecutor(n, initializer=torch.set_num_threads, initargs=(1,)))
        stack.callback(pool.shutdown, cancel_futures=True)  # runs first: nothing new starts on an error

        def run(j: int, k: int, frame: np.ndarray) -> dict[str, np.ndarray]:
            renderer = idle.pop()  # list.pop/append are atomic; at most n jobs run, so one is always free
            try:
                return job(renderer, j, k, frame)
            finally:
                idle.append(renderer)

        pending: deque = deque()
        for j, (k, frame) in enumerate(zip(indices, frames, strict=False)):
            pending.append((frame, pool.submit(run, j, int(k), frame)))
            if len(pending) > n:
                first, done = pending.popleft()
                yield first, done.result()
                bar.update(1)
        while pending:
            first, done = pending.popleft()
            yield first, done.result()
            bar.update(1)
