"""The renderer's training frames: ``FrameCache`` holds them, decoded once and kept compact (uint8 crops,
float16 UVs), rasterized as a dub rasterizes (:mod:`renderer.inputs`, where ``FrameGeometry`` and the
crops live); frames in a passing light are left out (:func:`transient_light`).
"""

from __future__ import annotations

import logging
from contextlib import ExitStack
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from nvp.artifact import load_artifact, save_artifact
from nvp.errors import FormatError
from nvp.face_model import FaceModel
from nvp.threads import frame_workers
from nvp.tracked import TrackedSequence
from renderer.crop import cut
from renderer.inputs import FrameGeometry, Rasterizer, sequence_boxes
from renderer.mouths import LIGHT_TOLERANCE, light_ratio
from renderer.preset import Preset
from renderer.workers import Workers

CACHE_FIELDS = ("frames", "crops", "uv", "mask", "mouth", "region", "boxes", "vertices", "camera")
CACHE_VERSION = 4  # 2: camera-frame vertices and the camera, for moving one frame's pixels onto another;
# 3: frames in a passing light (a fade, a flash) left out (transient_light); 4: crops averaged over the
# footage pixels they cover (renderer.crop.cut), not point-sampled

log = logging.getLogger(__name__)


@dataclass
class FrameCache:
    """Training frames at crop resolution.

    Attributes:
        frames: ``(N,)`` frame indices in the tracked sequence.
        crops: ``(N, S, S, 3)`` uint8 footage crops.
        uv: ``(N, S, S, 2)`` float16; mask, mouth, region: ``(N, S, S)`` bool.
        boxes: ``(N, 3)`` crop boxes.
        vertices: ``(N, V, 3)`` float32 tracked camera-frame vertices.
        camera: ``(3,)`` float32 focal length and principal point of the footage (pixels).
    """

    frames: np.ndarray
    crops: np.ndarray
    uv: np.ndarray
    mask: np.ndarray
    mouth: np.ndarray
    region: np.ndarray
    boxes: np.ndarray
    vertices: np.ndarray
    camera: np.ndarray

    def batch(
        self, idx: np.ndarray, device: str | torch.device = "cpu"
    ) -> tuple[torch.Tensor, FrameGeometry]:
        """Crops ``(B, 3, S, S)`` float in [0, 1] and their geometry for cache rows ``idx``."""
        crops = torch.from_numpy(self.crops[idx]).permute(0, 3, 1, 2).float().div(255)
        geo = FrameGeometry(
            uv=torch.from_numpy(self.uv[idx].astype(np.float32)).to(device),
            mask=torch.from_numpy(self.mask[idx])[:, None].float().to(device),
            mouth=torch.from_numpy(self.mouth[idx])[:, None].float().to(device),
            region=torch.from_numpy(self.region[idx])[:, None].float().to(device),
        )
        return crops.to(device), geo

    def keep(self, rows: np.ndarray) -> None:
        """Keep only the frames of ``rows`` (increasing), moved down in place: no second copy of the crops."""
        for name in (n for n in CACHE_FIELDS if n != "camera"):  # the per-frame fields
            array = getattr(self, name)
            for to, row in enumerate(rows):
                if to != row:
                    array[to] = array[row]
            setattr(self, name, array[: len(rows)])

    def save(self, path: Path, source: dict | None = None) -> Path:
        """Write ``path`` (``.json`` + ``.npz``, :mod:`nvp.artifact`); ``source`` says what it was cut from
        (checked by :meth:`load` so a cache is never reused for other footage)."""
        arrays = {k: getattr(self, k) for k in CACHE_FIELDS}
        return save_artifact(path, "renderer_frames", CACHE_VERSION, arrays, {"source": source or {}})

    @classmethod
    def load(cls, path: Path, source: dict | None = None) -> FrameCache:
        """Read a cache written by :meth:`save`; with ``source``, it must match the one saved."""
        art = load_artifact(path, "renderer_frames", CACHE_VERSION)
        if source is not None and art.manifest.get("source") != source:
            raise FormatError(f"{art.path} was made from other footage or settings")
        return cls(**{k: art.arrays[k] for k in CACHE_FIELDS})


CACHE_BUDGET_MB = 1536.0
"""Most memory the renderer's training frames may take (:func:`build_cache`). A 3-minute video is 4,500
frames: 1.6 GB at the ``cpu`` preset's 192² crop, 2.9 GB at ``quality``'s 256², which took ``nvp fit`` on a
3-minute 1080p video to 5.5 GB peak (``scripts/bench/fit.py --preset quality``). Beyond the budget every
n-th frame is kept; neighbouring frames are nearly alike, and a fit draws 16,000 training samples at most."""


LIGHT_TRANSIENT_S = 2.0
"""Longest run of frames beyond :data:`renderer.mouths.LIGHT_TOLERANCE` left out of the training
(:func:`transient_light`): a fade, a flash or a jump of the camera's exposure. A longer run is another take
shot in other light (voxceleb2_id00100's joined clips: the first 15 s magenta-lit), which the networks must
learn too."""


def face_light(crops: np.ndarray, mask: np.ndarray, mouth: np.ndarray) -> np.ndarray:
    """``(N, 3)`` each crop's light: the median colour of the face the mesh covers, without the mouth
    interior (``crops`` ``(N, S, S, 3)``; ``mask``, ``mouth`` ``(N, S, S)`` bool); NaN where it covers
    none."""
    out = np.full((len(crops), 3), np.nan, np.float32)
    for i, (crop, face) in enumerate(zip(crops, mask & ~mouth, strict=True)):
        if face.any():
            out[i] = np.median(crop[face], axis=0)
    return out


def transient_light(
    frames: np.ndarray,
    light: np.ndarray,
    fps: float,
    tolerance: float = LIGHT_TOLERANCE,
    longest_s: float = LIGHT_TRANSIENT_S,
) -> np.ndarray:
    """``(N,)`` bool: the frames (sorted frame indices ``frames`` ``(N,)``, their :func:`face_light`
    ``light``) whose light differs from the footage's median by more than ``tolerance`` in some channel, in
    runs no longer than ``longest_s``. The networks learned faded frames as they were, and a dub of them,
    whose mouth is not the footage's, showed a violet or grey-blue mouth with a dark ring around it; without
    them the networks paint the face in the footage's usual light and the render's light match
    (:func:`renderer.crop.colour_match`) puts it into the frame's (docs/experiments/renderer.md: *Fades
    left out of the renderer's training*)."""
    off = other_light(light, tolerance)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], off.astype(np.int8), [0]])))
    for start, end in zip(edges[::2], edges[1::2], strict=True):
        if (frames[end - 1] - frames[start] + 1) / fps > longest_s:
            off[start:end] = False
    return off


def other_light(light: np.ndarray, tolerance: float = LIGHT_TOLERANCE) -> np.ndarray:
    """``(N,)`` bool: the crops (their :func:`face_light` ``light`` ``(N, 3)``) whose light differs from the
    footage's median by more than ``tolerance`` in some channel (False where unknown)."""
    off = np.zeros(len(light), bool)
    known = np.isfinite(light).all(1)
    if known.any():
        off[known] = light_ratio(light[known], np.median(light[known], axis=0)) > np.log1p(tolerance)
    return off


VARIED_LIGHT_SHARE = 0.1
"""Footage whose face is in another light (:func:`other_light`) in this share of its training frames or
more was shot in several takes or sessions, and the renderer's default training is longer for it
(:attr:`renderer.preset.Preset.varied_minutes`). Measured shares (after :func:`transient_light`): 0 on
single shots (dfrf__cnn2, minimates__driving, multivsr hxn8, Trump_10s, edtalk pose_source2, cantolip
icable), 0.22-0.72 on clips of one person joined (voxceleb2_id00100's ten: 0.26; Robert Downey Jr's two,
LRS2's two, Fei-Fei Li's three, Obama's three). From 5 to 15 minutes of training the ten voxceleb clips'
mouth box gains 0.6-0.8 dB, the single shots' −0.3 to +0.4 (docs/experiments/renderer.md: *A person in 5
minutes: the default*)."""


def varied_light(cache: FrameCache) -> float:
    """Share of ``cache``'s frames whose face is in another light than the footage's usual one (other
    takes: :data:`VARIED_LIGHT_SHARE`)."""
    if not len(cache.frames):
        return 0.0
    return float(other_light(face_light(cache.crops, cache.mask, cache.mouth)).mean())


def cache_frame_bytes(size: int, num_vertices: int) -> int:
    """Bytes one cached frame takes at crop ``size``: crop (3), uv (2 × float16) and three masks per pixel,
    plus its vertices."""
    return size * size * (3 + 4 + 3) + 12 * num_vertices


def build_cache(
    video: Path,
    seq: TrackedSequence,
    model: FaceModel,
    preset: Preset,
    frames: np.ndarray,
    progress: bool = True,
    budget_mb: float = CACHE_BUDGET_MB,
) -> FrameCache:
    """Decode ``video`` once and keep the crops and geometry of ``frames`` (valid tracked frames; evenly
    thinned to fit ``budget_mb``, see :data:`CACHE_BUDGET_MB`)."""
    from nvp.media import iter_frames

    frames = np.asarray(sorted(int(f) for f in frames if seq.valid[f]), dtype=np.int64)
    s = preset.crop
    limit = max(1, int(budget_mb * 2**20 // cache_frame_bytes(s, model.num_vertices)))
    if len(frames) > limit:
        frames = np.unique(frames[np.round(np.linspace(0, len(frames) - 1, limit)).astype(int)])
    boxes = sequence_boxes(model, seq)
    n = len(frames)
    cache = FrameCache(
        frames=frames,
        crops=np.empty((n, s, s, 3), np.uint8),
        uv=np.empty((n, s, s, 2), np.float16),
        mask=np.empty((n, s, s), bool),
        mouth=np.empty((n, s, s), bool),
        region=np.empty((n, s, s), bool),
        boxes=boxes[frames].astype(np.float32),
        vertices=seq.camera_vertices(model, frames).astype(np.float32),
        camera=np.array([seq.focal, *seq.center], np.float32),
    )
    row = {int(f): i for i, f in enumerate(frames)}
    last = int(frames.max()) + 1 if n else 0

    def fill(i: int, t: int, img: np.ndarray, rast: Rasterizer) -> None:  # row i of the cache: frame t
        frame = torch.from_numpy(img).permute(2, 0, 1)[None]
        crop = cut(frame, torch.from_numpy(boxes[t : t + 1]).float(), s)[0]
        cache.crops[i] = crop.clamp(0, 255).round().byte().permute(1, 2, 0).numpy()
        g = rast(cache.vertices[i], seq.focal, seq.center, boxes[t])
        cache.uv[i] = g.uv[0].numpy().astype(np.float16)
        cache.mask[i] = g.mask[0, 0].numpy() > 0.5
        cache.mouth[i] = g.mouth[0, 0].numpy() > 0.5
        cache.region[i] = g.region[0, 0].numpy() > 0.5

    # frames side by side, one PyTorch thread and rasterizer each, while the next ones are decoded
    rasterizers, made = [], ExitStack()
    for _ in range(frame_workers()):
        rasterizers.append(Rasterizer(model, s, preset.region_grow))
        made.callback(rasterizers[-1].close)
    with (
        Workers(rasterizers, made) as pool,
        tqdm(total=n, desc="prepare renderer frames", disable=not progress, unit="frame") as bar,
    ):
        frames_in = enumerate(iter_frames(video, fps=seq.fps, max_frames=last))
        for _ in pool.in_order(partial(fill, row[t], t, img) for t, img in frames_in if t in row):
            bar.update(1)
    off = transient_light(frames, face_light(cache.crops, cache.mask, cache.mouth), seq.fps)
    if off.any():
        log.warning(
            "%s: %d frames in a passing light (a fade, a flash) are left out of the renderer's training",
            video.name,
            off.sum(),
        )
        cache.keep(np.flatnonzero(~off))
    return cache
