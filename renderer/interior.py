"""The person's own mouth interior pasted where the rendered mouth is open: which mouth-bank entry
(:mod:`renderer.mouths`) suits a frame, and the entry's pixels moved onto the new geometry in the frame's
colours and light.

:class:`MouthInteriors` is a part of :class:`renderer.render.FrameRenderer` (a mixin): its methods read the
frame renderer's ``mouths`` (the bank, or None), ``seq``, ``raster``'s geometry and ``_triangles``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from nvp.face_model import FaceModel
from nvp.geometry import unposed
from renderer.inputs import FaceRender, FrameGeometry
from renderer.masks import gaussian_blur
from renderer.mouths import MouthBank, interior_vertices, light_costs
from renderer.warp import sample_pixels

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


class MouthInteriors:
    """The mouth-interior part of :class:`renderer.render.FrameRenderer`: the bank's patches and the
    choice and paste of its entries."""

    mouths: MouthBank | None

    def _load_interiors(self, renderer_dir: Path, model: FaceModel, interiors: bool) -> None:
        """Load the renderer folder's mouth bank (``mouths.json``) when ``interiors`` and it has one."""
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

    def mouth_costs(self, shapes: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """``(T, N)`` how well each mouth-bank entry suits output frames of inner-lip ``shapes`` ``(T, M, 3)``
        (:func:`renderer.mouths.sequence_shapes`) rendered over footage ``frames`` ``(T,)``: the shape
        distance (cm) plus, for a bank that recorded the footage's light, the cost of an entry shot in
        other light (:func:`renderer.mouths.light_costs`)."""
        costs = self.mouths.distances(shapes)
        if self._entry_light is not None:
            costs = costs + light_costs(self._entry_light, self.mouths.light_at(np.asarray(frames)))
        return costs

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
        blurred = gaussian_blur(
            torch.cat([moved, render[None, :, r0p:r1p, c0p:c1p].float().cpu() * 255]), 7, 1.0
        )
        diff = ((blurred[:-1] - blurred[-1:]) ** 2).mean(1)[:, inside]
        return diff.mean(1).sqrt().numpy() if diff.shape[1] else np.zeros(len(entries))

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
