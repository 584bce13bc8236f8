"""The person's own mouth interiors (teeth, tongue), retrieved from their footage for an open rendered mouth.

The networks paint the mouth interior from a 16-channel texture at crop resolution: teeth come out as a dark
or pale band, because they change with every frame and the texture cannot hold them. The footage, though,
shows this person's real teeth in every open-mouth frame. A *mouth bank* keeps a few dozen of those frames'
mouth regions at the footage's resolution (chosen at fit time to cover the shapes the person's mouth takes); a
rendered frame gets the interior of a bank frame whose inner lips are shaped like the new geometry's and
whose interior looks most like the networks' own soft one
(:meth:`renderer.interior.MouthInteriors.entry_costs`),
moved onto it through the mouth-interior triangles (the same surface correspondence as :mod:`renderer.warp`),
and pasted where the new geometry shows the interior (Video Rewrite, Bregler et al. 1997, did this for the
whole mouth; here only the interior, inside the rendered lips). Footage cut from several takes, or whose light
drifts, holds mouths of other colours: the bank records the footage's light (the colour of the skin around the
lips), an entry shot in other light than the footage frame behind the output frame costs as much as a far
shape (:func:`light_costs`), and the pasted interior takes the rendered lips' colour
(:meth:`renderer.interior.MouthInteriors._colour_gains`).

Pure functions for choosing frames and entries (:class:`EntryChooser`: a stream's entries without flicker);
:func:`build_mouth_bank` decodes the footage.
Shapes: ``N`` bank entries, ``P`` patch side, ``M`` inner-lip vertices, ``V`` vertices, ``T`` frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from nvp.artifact import load_artifact, save_artifact
from nvp.face_model import FaceModel
from nvp.tracked import TrackedSequence

FORMAT_VERSION = 2
"""2: the footage's lip colours (``light_frames``, ``light_colours``); version-1 banks load without them."""
PATCH = (64, 256)
"""Smallest and largest side of the stored mouth patches (pixels): a patch spans 1.6 mouth widths and keeps
the footage's resolution up to a 160 px wide mouth (0.6 MB per entry at 256²), beyond that it is scaled
down."""
ENTRIES = 48
"""Most open-mouth frames a bank keeps."""
SWITCH_CM = 0.05
"""Cost (cm of mean inner-lip vertex distance) of changing the bank entry between two output frames: an
entry is kept while it stays within this much of the best one, so teeth do not flicker from frame to frame."""
LIGHT_TOLERANCE = 0.15
"""Relative difference (per channel) between two frames' light (:func:`light_colour`) still taken as the
same light. Pairs of a footage frame and a bank entry of the same take beyond it: 0.0 / 0.4 / 2.5 / 5.5 % on
dfrf__cnn2, edtalk__pose_source2, wav2lipgfpgan kim, minimates__driving; of a footage cut from a magenta-lit
and a daylight interview (voxceleb2_id00100's clips joined): 61 % (:func:`light_costs`). The renderer's
training frames use it too (:func:`renderer.train_data.transient_light`): a frame's face against the footage's
median is at most 0.03-0.05 off on six single-take videos (multivsr hxn8clTtMTo's bearded face 0.135, kim's
first two frames, a fade-in from dark, 0.18), while wth2025__lamazda's fades reach 0.65."""
LIGHT_STEP = 5
"""Every this many footage frames the bank records the frame's light (it changes with a cut or a drift of
the camera's exposure and white balance, not from frame to frame)."""
LIGHT_CM = 1.0
"""Cost (cm of inner-lip shape distance) per unit of log colour ratio beyond :data:`LIGHT_TOLERANCE` of a
bank entry shot in other light than the output frame's footage (:func:`light_costs`): an entry of a
magenta-lit take (the skin beside the lips 2.2 times as blue as in the daylight one: 234 against 105) costs
0.66 cm, far more than the shape differences between near entries (a few hundredths of a cm)."""


def light_region(model: FaceModel) -> np.ndarray:
    """``(V,)`` bool: the skin around the lips (the mouth region without the lips), whose colour stands for a
    frame's light: lips change colour as the mouth opens (inner lips, teeth and shadow at their edge) — within
    one take 7-34 % of frame / bank-entry pairs differ by more than 25 % there (dfrf__cnn2, edtalk, kim,
    minimates), the skin beside them 0-2 %."""
    return model.vertex_regions["mouth"] & ~model.vertex_regions["lips"]


def light_colour(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """``(3,)`` float32 median colour of ``image`` ``(H, W, 3)`` at vertex ``pixels`` ``(K, 2)`` (x, y; the
    nearest pixel; a median, so that a hair or a highlight does not count)."""
    h, w = image.shape[:2]
    at = np.floor(pixels).astype(np.int64)
    return np.median(image[np.clip(at[:, 1], 0, h - 1), np.clip(at[:, 0], 0, w - 1)], axis=0).astype(
        np.float32
    )


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
        light_frames: ``(L,)`` footage frames whose light was recorded (sorted; every entry's frame among
            them), empty for a bank without.
        light_colours: ``(L, 3)`` float32 their light (:func:`light_colour` over :func:`light_region`).
    """

    frames: np.ndarray
    patches: np.ndarray
    pixels: np.ndarray
    shapes: np.ndarray
    light_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    light_colours: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))

    def __len__(self) -> int:
        return len(self.frames)

    def save(self, path: Path) -> Path:
        keys = ("frames", "patches", "pixels", "shapes", "light_frames", "light_colours")
        arrays = {k: getattr(self, k) for k in keys}
        return save_artifact(path, "mouth_bank", FORMAT_VERSION, arrays, {}, compress=True)

    @classmethod
    def load(cls, path: Path) -> MouthBank:
        a = load_artifact(path, "mouth_bank", (1, FORMAT_VERSION)).arrays
        bank = cls(a["frames"], a["patches"], a["pixels"], a["shapes"])
        if "light_frames" in a:
            bank.light_frames, bank.light_colours = a["light_frames"], a["light_colours"]
        return bank

    def light_at(self, frames: np.ndarray) -> np.ndarray:
        """``(T, 3)`` the recorded light nearest in time to each footage frame of ``frames`` ``(T,)``
        (the bank must have some)."""
        lf, f = self.light_frames, np.asarray(frames)
        i = np.searchsorted(lf, f)
        lo, hi = np.clip(i - 1, 0, len(lf) - 1), np.clip(i, 0, len(lf) - 1)
        return self.light_colours[np.where(np.abs(f - lf[lo]) <= np.abs(lf[hi] - f), lo, hi)]

    def distances(self, shapes: np.ndarray) -> np.ndarray:
        """``(T, N)`` mean inner-lip vertex distance (cm) of object-frame ``shapes`` ``(T, M, 3)`` to
        every entry."""
        return np.linalg.norm(shapes[:, None] - self.shapes[None], axis=-1).mean(-1)

    def positions(
        self,
        entry: int | np.ndarray,
        triangle_id: torch.Tensor,
        barycentric: torch.Tensor,
        triangles: torch.Tensor,
    ) -> torch.Tensor:
        """``(S, S, 2)`` patch pixel of ``entry`` at each pixel of a rendered crop (its fragments
        ``triangle_id`` ``(S, S)``, ``barycentric`` ``(S, S, 3)``): the same surface point in the entry's
        frame; ``(K, S, S, 2)`` for ``K`` entries (an array)."""
        from renderer.warp import surface_points

        if np.ndim(entry) == 0:
            return surface_points(triangle_id, barycentric, triangles, torch.from_numpy(self.pixels[entry]))
        pixels = torch.from_numpy(self.pixels[entry]).permute(1, 0, 2)  # (V, K, 2)
        moved = surface_points(triangle_id, barycentric, triangles, pixels.reshape(len(pixels), -1))
        return moved.reshape(*moved.shape[:-1], len(entry), 2).movedim(-2, 0)


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


def light_ratio(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The largest per-channel absolute log ratio between lights ``a`` and ``b`` (``(..., 3)``, broadcast;
    levels below 1 taken as 1): 0 for the same light, ``log1p(LIGHT_TOLERANCE)`` at the tolerance."""
    a, b = (np.maximum(np.asarray(c, np.float64), 1.0) for c in (a, b))
    return np.abs(np.log(a / b)).max(-1)


def light_costs(entries: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``(T, N)`` cost of pasting bank entries whose frames' light is ``entries`` ``(N, 3)`` into output
    frames whose footage's light is ``reference`` ``(T, 3)`` (:meth:`MouthBank.light_at`):
    :data:`LIGHT_CM` per unit of the largest per-channel log colour ratio beyond :data:`LIGHT_TOLERANCE`,
    so a mouth of another take's light is only used when no other shape comes near."""
    ratio = light_ratio(np.asarray(entries)[None], np.asarray(reference)[:, None])
    return LIGHT_CM * np.maximum(ratio - np.log1p(LIGHT_TOLERANCE), 0.0)


def best_path(costs: np.ndarray, start: int | None = None, switch: float = SWITCH_CM) -> np.ndarray:
    """``(T,)`` bank entry per output frame minimising the summed ``costs`` ``(T, N)`` plus ``switch`` per
    change of entry (Viterbi), counting a change before the first frame too when it follows entry
    ``start``: the best entry each frame, without flicker between near-equal ones."""
    t, n = costs.shape
    cost = costs[0].astype(np.float64)
    if start is not None:
        cost = cost + switch * (np.arange(n) != start)
    back = np.zeros((t, n), np.int64)
    for i in range(1, t):
        best = int(np.argmin(cost))
        stay = cost
        move = cost[best] + switch
        back[i] = np.where(stay <= move, np.arange(n), best)
        cost = np.minimum(stay, move) + costs[i]
    path = np.empty(t, np.int64)
    path[-1] = int(np.argmin(cost))
    for i in range(t - 1, 0, -1):
        path[i - 1] = back[i, path[i]]
    return path


class EntryChooser:
    """Bank entries for a stream of output frames in order, without flicker: frame ``j``'s entry is decided
    once the costs of ``lag`` more frames are known (:func:`best_path` over them, from the entry already
    decided; fixed-lag Viterbi), so a renderer needs to hold only ``lag`` frames back. ``lag`` 0: the best
    entry, unless the current one is within ``switch`` of it (``nvp live``, whose future is unknown)."""

    def __init__(self, lag: int = 0, switch: float = SWITCH_CM) -> None:
        self.lag, self.switch = lag, switch
        self.current: int | None = None
        self._window: list[np.ndarray] = []

    def push(self, costs: np.ndarray) -> list[int]:
        """Adds the next frame's ``(N,)`` costs; returns the entries decided by it (of earlier frames, in
        order; none while fewer than ``lag`` frames are held)."""
        self._window.append(np.asarray(costs, np.float64))
        return [self._decide() for _ in range(len(self._window) - self.lag)]

    def flush(self) -> list[int]:
        """The entries of the frames still held (the stream has ended)."""
        return [self._decide() for _ in range(len(self._window))]

    def _decide(self) -> int:
        self.current = int(best_path(np.stack(self._window), self.current, self.switch)[0])
        self._window.pop(0)
        return self.current


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
    whole tracked sequence), at the footage's resolution within :data:`PATCH`, and the light of every
    :data:`LIGHT_STEP`-th valid frame and of the kept ones; None when the mouth never opens."""
    from nvp.media import frames_at
    from renderer.crop import cut

    shapes = sequence_shapes(model, seq)
    if frames is None:
        gaps = model.inner_lip_gap(seq.identity, seq.expression)
        frames = bank_frames(shapes, gaps, seq.valid)
    frames = np.asarray(frames, np.int64)
    if len(frames) == 0:
        return None
    lips = model.vertex_regions["lips"]
    light = np.union1d(np.flatnonzero(seq.valid)[::LIGHT_STEP], frames)
    px = seq.pixels(seq.camera_vertices(model, light))  # (L, V, 2) frame pixels
    entry = np.searchsorted(light, frames)
    lo, hi = px[entry][:, lips].min(1), px[entry][:, lips].max(1)
    side = 1.6 * (hi[:, 0] - lo[:, 0])
    boxes = np.concatenate([(lo + hi) / 2, side[:, None]], 1)  # (cx, cy, side), renderer.crop's boxes
    patch = int(np.clip(16 * np.ceil(np.median(side) / 16), *PATCH))
    patches = np.empty((len(frames), patch, patch, 3), np.uint8)
    colours = np.empty((len(light), 3), np.float32)
    skin = light_region(model)
    for i, img in enumerate(frames_at(video, light, seq.fps)):
        colours[i] = light_colour(img, px[i, skin])
        k = int(np.searchsorted(frames, light[i]))
        if k < len(frames) and frames[k] == light[i]:
            t = torch.from_numpy(img).permute(2, 0, 1)[None].float()
            crop = cut(t, torch.from_numpy(boxes[k : k + 1]).float(), patch)[0]
            patches[k] = crop.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()
    origin = boxes[:, None, :2] - boxes[:, None, 2:] / 2
    pixels = ((px[entry] - origin) * (patch / boxes[:, None, 2:])).astype(np.float32)
    return MouthBank(frames, patches, pixels, shapes[frames], light, colours)
