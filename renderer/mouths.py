"""The person's own mouth interiors (teeth, tongue), retrieved from their footage for an open rendered mouth.

The networks paint the mouth interior from a 16-channel texture at crop resolution: teeth come out as a dark
or pale band, because they change with every frame and the texture cannot hold them. The footage, though,
shows this person's real teeth in every open-mouth frame. A *mouth bank* keeps a few dozen of those frames'
mouth regions at the footage's resolution (chosen at fit time to cover the shapes the person's mouth takes);
a rendered frame gets the interior of the bank frame whose inner lips are shaped most like the new
geometry's, moved onto it through the mouth-interior triangles (the same surface correspondence as
:mod:`renderer.warp`), and pasted where the new geometry shows the interior (Video Rewrite, Bregler et al.
1997, did this for the whole mouth; here only the interior, inside the rendered lips).

Pure functions for choosing frames and entries; :func:`build_mouth_bank` decodes the footage.
Shapes: ``N`` bank entries, ``P`` patch side, ``M`` inner-lip vertices, ``V`` vertices, ``T`` frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nvp.artifact import load_artifact, save_artifact
from nvp.face_model import FaceModel
from nvp.tracked import TrackedSequence

FORMAT_VERSION = 1
PATCH = (64, 256)
"""Smallest and largest side of the stored mouth patches (pixels): a patch spans 1.6 mouth widths and keeps
the footage's resolution up to a 160 px wide mouth (0.6 MB per entry at 256²), beyond that it is scaled
down."""
ENTRIES = 48
"""Most open-mouth frames a bank keeps."""
SWITCH_CM = 0.05
"""Cost (cm of mean inner-lip vertex distance) of changing the bank entry between two output frames: an
entry is kept while it stays within this much of the best one, so teeth do not flicker from frame to frame."""


def interior_vertices(model: FaceModel) -> np.ndarray:
    """``(M,)`` indices of the vertices of the mouth-interior triangles (the inner lip contour)."""
    return np.unique(model.triangles[model.triangle_regions["mouth_interior"]])


@dataclass
class MouthBank:
    """Open-mouth regions of a person's footage.

    Attributes:
        frames: ``(N,)`` footage frame of each entry.
        patches: ``(N, P, P, 3)`` uint8 the footage around the mouth.
        pixels: ``(N, V, 2)`` float32 every vertex of the entry's tracked geometry in patch pixels (x, y;
            pixel centres at +0.5).
        shapes: ``(N, M, 3)`` float32 the inner-lip vertices in the object frame (cm), what entries are
            chosen by.
    """

    frames: np.ndarray
    patches: np.ndarray
    pixels: np.ndarray
    shapes: np.ndarray

    def __len__(self) -> int:
        return len(self.frames)

    def save(self, path: Path) -> Path:
        arrays = {k: getattr(self, k) for k in ("frames", "patches", "pixels", "shapes")}
        return save_artifact(path, "mouth_bank", FORMAT_VERSION, arrays, {}, compress=True)

    @classmethod
    def load(cls, path: Path) -> MouthBank:
        a = load_artifact(path, "mouth_bank", FORMAT_VERSION).arrays
        return cls(a["frames"], a["patches"], a["pixels"], a["shapes"])

    def distances(self, shapes: np.ndarray) -> np.ndarray:
        """``(T, N)`` mean inner-lip vertex distance (cm) of object-frame ``shapes`` ``(T, M, 3)`` to
        every entry."""
        return np.linalg.norm(shapes[:, None] - self.shapes[None], axis=-1).mean(-1)

    def positions(
        self, entry: int, triangle_id: torch.Tensor, barycentric: torch.Tensor, triangles: torch.Tensor
    ) -> torch.Tensor:
        """``(S, S, 2)`` patch pixel of ``entry`` at each pixel of a rendered crop (its fragments
        ``triangle_id`` ``(S, S)``, ``barycentric`` ``(S, S, 3)``): the same surface point in the entry's
        frame."""
        from renderer.warp import surface_points

        return surface_points(triangle_id, barycentric, triangles, torch.from_numpy(self.pixels[entry]))


def bank_frames(
    shapes: np.ndarray, gaps: np.ndarray, valid: np.ndarray, entries: int = ENTRIES
) -> np.ndarray:
    """Which footage frames a bank keeps: of the valid frames whose mouth is open (inner-lip gap above a
    quarter of the way from the person's closed level, 5th percentile, to their wide-open one, 95th),
    ``entries`` spread over the shapes (farthest-point sampling from the most open one), sorted.

    Args:
        shapes: ``(T, M, 3)`` object-frame inner-lip vertices of every frame.
        gaps: ``(T,)`` inner-lip gap (cm); valid: ``(T,)`` bool (tracked).
    """
    ok = np.flatnonzero(valid)
    if len(ok) == 0:
        return np.zeros(0, np.int64)
    lo, hi = np.percentile(gaps[ok], [5, 95])
    if hi - lo < 1e-3:  # the mouth never opens
        return np.zeros(0, np.int64)
    cand = ok[gaps[ok] > lo + 0.25 * (hi - lo)]
    if len(cand) <= entries:
        return np.sort(cand)
    flat = shapes[cand].reshape(len(cand), -1)
    chosen = [int(np.argmax(gaps[cand]))]
    dist = np.linalg.norm(flat - flat[chosen[0]], axis=1)
    while len(chosen) < entries:
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(flat - flat[nxt], axis=1))
    return np.sort(cand[chosen])


def choose_entries(distances: np.ndarray, switch: float = SWITCH_CM) -> np.ndarray:
    """``(T,)`` bank entry per output frame minimising the summed shape distances ``(T, N)`` plus
    ``switch`` per change of entry (Viterbi): the nearest entry each frame, without flicker between
    near-equal ones."""
    t, n = distances.shape
    cost = distances[0].copy()
    back = np.zeros((t, n), np.int64)
    for i in range(1, t):
        best = int(np.argmin(cost))
        stay = cost
        move = cost[best] + switch
        back[i] = np.where(stay <= move, np.arange(n), best)
        cost = np.minimum(stay, move) + distances[i]
    path = np.empty(t, np.int64)
    path[-1] = int(np.argmin(cost))
    for i in range(t - 1, 0, -1):
        path[i - 1] = back[i, path[i]]
    return path


def next_entry(current: int | None, distances: np.ndarray, switch: float = SWITCH_CM) -> int:
    """The entry for the next frame of a stream (``distances`` ``(N,)``, its shape's to every entry) when
    the future is unknown: the nearest one, unless ``current`` is within ``switch`` of it."""
    best = int(np.argmin(distances))
    if current is not None and distances[current] <= distances[best] + switch:
        return current
    return best


def sequence_shapes(
    model: FaceModel, seq: TrackedSequence, expression: np.ndarray | None = None
) -> np.ndarray:
    """``(T, M, 3)`` object-frame inner-lip vertices of ``seq``'s identity with ``expression``
    ``(T, K_exp)`` (default: the tracked expressions)."""
    e = seq.expression if expression is None else expression
    return model.vertices(seq.identity, e)[:, interior_vertices(model)].astype(np.float32)


def build_mouth_bank(
    video: Path, seq: TrackedSequence, model: FaceModel, frames: np.ndarray | None = None
) -> MouthBank | None:
    """Decode ``video`` and keep the mouth regions of ``frames`` (default :func:`bank_frames` over the
    whole tracked sequence), at the footage's resolution within :data:`PATCH`; None when the mouth never
    opens."""
    from nvp.media import frames_at
    from renderer.crop import cut

    shapes = sequence_shapes(model, seq)
    if frames is None:
        gaps = model.inner_lip_gap(seq.identity, seq.expression)
        frames = bank_frames(shapes, gaps, seq.valid)
    frames = np.asarray(frames, np.int64)
    if len(frames) == 0:
        return None
    cam = seq.camera_vertices(model, frames)
    px = seq.pixels(cam)  # (N, V, 2) frame pixels
    lips = model.vertex_regions["lips"]
    lo, hi = px[:, lips].min(1), px[:, lips].max(1)
    side = 1.6 * (hi[:, 0] - lo[:, 0])
    boxes = np.concatenate([(lo + hi) / 2, side[:, None]], 1)  # (cx, cy, side), renderer.crop's boxes
    patch = int(np.clip(16 * np.ceil(np.median(side) / 16), *PATCH))
    patches = np.empty((len(frames), patch, patch, 3), np.uint8)
    for i, img in enumerate(frames_at(video, frames, seq.fps)):
        t = torch.from_numpy(img).permute(2, 0, 1)[None].float()
        crop = cut(t, torch.from_numpy(boxes[i : i + 1]).float(), patch)[0]
        patches[i] = crop.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()
    origin = boxes[:, None, :2] - boxes[:, None, 2:] / 2
    pixels = ((px - origin) * (patch / boxes[:, None, 2:])).astype(np.float32)
    return MouthBank(frames, patches, pixels, shapes[frames])
