"""The footage's own fine detail moved with the surface onto the painted lower face (the detail band):
where the surface moved rigidly, detail finer than the networks paint comes from a source frame
(:mod:`renderer.warp`); around the mesh, the footage frame's own pixels are kept where they are right.

:class:`DetailBand` is a part of :class:`renderer.render.FrameRenderer` (a mixin): its methods read the
frame renderer's ``raster``, ``boxes``, ``seq``, ``preset`` and mesh tables (``_triangles``, ``_movable``,
``_edges``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from renderer.crop import MovedDetail, cut
from renderer.inputs import FrameGeometry, moved_source
from renderer.masks import dilate
from renderer.warp import rigidity, smooth, surface_points

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


class DetailBand:
    """The detail part of :class:`renderer.render.FrameRenderer`: a source frame moved onto the new
    surface (:meth:`_moved`) and the band of its fine detail (:meth:`_band`)."""

    def _moved(
        self,
        geo: FrameGeometry,
        src_img: torch.Tensor,
        src_index: int,
        src_cam: np.ndarray,
        src_geo: FrameGeometry | None = None,
        src_crop: torch.Tensor | None = None,
        offset: np.ndarray | None = None,
        window: tuple[slice, slice] | None = None,
    ) -> tuple[torch.Tensor, tuple]:
        """The source frame ``src_img`` ``(3, H, W)`` (frame ``src_index`` under ``src_cam`` ``(V, 3)``)
        moved onto the surface of ``geo``: the network's ``(4, S, S)`` source input and the ``moved``
        argument of :func:`renderer.crop.paste`; ``src_geo`` / ``src_crop`` (in [0, 1]) when the caller has
        them already; ``offset``: the frame pixel ``(x, y)`` where ``src_img`` starts (a part of the
        frame); ``window``: the crop's rows and columns to move it onto (the rest is invalid)."""
        shift = np.zeros(2) if offset is None else offset
        src_box = self.boxes[src_index] - np.array([*shift, 0.0])
        f, c = self.seq.focal, self.seq.center - shift
        if src_geo is None:
            src_geo = self.raster(src_cam, f, c, src_box)
        if src_crop is None:
            src_crop = cut(src_img[None], torch.from_numpy(src_box[None]).float(), self.preset.crop)[0] / 255
        source_in, pos, valid = moved_source(
            geo, src_crop, src_box, src_cam, src_geo.depth, (f, c), self._triangles, self._movable, window
        )
        no_band = torch.zeros_like(valid)  # until :meth:`_band`
        no_render_band = torch.zeros_like(src_crop)
        moved = MovedDetail(src_img, src_crop * 255, src_box, pos, valid, no_band, no_render_band, BAND_SIGMA)
        return source_in, moved

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
