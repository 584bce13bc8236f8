"""Eye contact: the footage's eyes turned to look where asked (``nvp dub --gaze``).

Inside each eye opening (its outline from tracking) the iris, its centre and radius from mediapipe's iris
landmarks, is moved to where an eyeball of the tracked head looking the asked way shows it
(:func:`nvp.gaze.iris_pixels`), over the white of the eye filled in where it was (:func:`turned_eye`).
The footage's own pixels move: no network paints them, so the eyes keep the footage's sharpness and light.
Lids, lashes and blinks stay the footage's and nothing outside the openings changes (no seam to hide). A
closing eye is let go gradually (:data:`OPEN_FROM`, :data:`OPEN_FULL`): in a blink the iris is hidden and
its landmarks mean nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from nvp.gaze import EYES, footage_gaze, gaze_vectors, iris_pixels, towards_camera

OPEN_FROM = 0.5
"""Lid gap over iris radius at and below which an eye is left alone (closed or closing: a blink). Open eyes
of ten test people: median 1.2-1.8, 10th percentile 0.65-1.55, blinks below 0.5."""
OPEN_FULL = 0.8
"""Lid gap over iris radius from which the iris moves all the way (between, part of the way)."""
IRIS_EDGE = (1.0, 1.25)
"""The moved iris covers the white fully out to the first of these radii (over mediapipe's iris radius) and
fades out at the second (its dark outer ring, the limbus, goes with it without a hard edge); its old place
is filled with white out to the second."""
MARGIN = 0.5
"""The warped patch around an eye: its opening's box grown by this fraction of the eye's width."""


@dataclass(frozen=True)
class EyeMove:
    """One eye of one frame to turn: its opening's outline ``(16, 2)`` (pixels, a closed loop), the iris
    ``(3,)`` as seen (centre ``x, y``, radius) and ``(2,)`` where its centre should be."""

    outline: np.ndarray
    iris: np.ndarray
    to: np.ndarray


def openness(outline: np.ndarray, radius: float) -> float:
    """The eye's lid gap (the opening's height across its middle) over the iris radius."""
    gap = np.ptp(outline[:, 1]) if len(outline) else 0.0
    return float(gap / radius) if radius > 0 else 0.0


def eye_moves(model, seq, index: int, directions: np.ndarray, centres: np.ndarray | None = None) -> list:
    """The :class:`EyeMove` of each eye of footage frame ``index`` of ``seq`` (its tracking, with iris) to
    look along camera-frame ``directions`` ``(2, 3)`` (left eye first), from eyeball ``centres`` ``(2, 3)``
    (default: the tracked head's, :func:`nvp.gaze.footage_gaze`). An eye without iris landmarks (no face
    found) or closing (:data:`OPEN_FROM`) is left out; a half-open one moves part of the way."""
    if centres is None:
        centres = footage_gaze(model, seq, np.array([index]))[0][0]
    to = iris_pixels(centres, directions, seq.focal, seq.center)
    moves = []
    for e, group in enumerate(EYES):
        outline = seq.landmarks[index, model.landmark_groups[group]].astype(np.float64)
        iris = seq.iris[index, e].astype(np.float64)
        if not (np.isfinite(outline).all() and np.isfinite(iris).all() and np.isfinite(to[e]).all()):
            continue
        share = np.clip((openness(outline, iris[2]) - OPEN_FROM) / (OPEN_FULL - OPEN_FROM), 0, 1)
        if share > 0:
            moves.append(EyeMove(outline, iris, iris[:2] + share * (to[e] - iris[:2])))
    return moves


def _opening_mask(outline: np.ndarray, shape: tuple[int, int], origin: np.ndarray) -> np.ndarray:
    """``(h, w)`` float32 coverage (anti-aliased) of the eye opening in a patch at ``origin``."""
    mask = np.zeros(shape, np.uint8)
    pts = np.round((outline - origin) * 16).astype(np.int32)  # 4 bits of sub-pixel precision
    cv2.fillPoly(mask, [pts], 255, cv2.LINE_AA, shift=4)
    return mask.astype(np.float32) / 255


def _disc(shape: tuple[int, int], centre: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """``(h, w)`` float32 coverage of a disc: 1 out to radius ``inner``, falling to 0 at ``outer``."""
    ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    return np.clip((outer - np.hypot(xs - centre[0], ys - centre[1])) / max(outer - inner, 1.0), 0, 1)


def turned_eye(patch: np.ndarray, opening: np.ndarray, iris: np.ndarray, to: np.ndarray) -> np.ndarray:
    """``(h, w, 3)`` float32 eye ``patch`` with its iris (centre ``iris[:2]``, radius ``iris[2]``, patch
    pixels) moved to ``to``, inside ``opening`` (``(h, w)`` coverage of the eye opening; outside it the
    patch is returned as it is: the lids stay). Two layers: the white of the eye, the iris's place filled
    from the white around it (OpenCV's inpainting), and over it the iris, each of its pixels from where it
    was; a part of it the lids hid in the footage is taken from its mirror image across the iris's
    horizontal middle (an iris is much the same all around), else from its colour at that radius."""
    h, w = opening.shape
    seen = opening > 0.5
    old = _disc((h, w), iris[:2], IRIS_EDGE[1] * iris[2], IRIS_EDGE[1] * iris[2] + 1) > 0
    white = cv2.inpaint(
        np.clip(patch, 0, 255).astype(np.uint8), (old & seen).astype(np.uint8) * 255, 3, cv2.INPAINT_TELEA
    ).astype(np.float32)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    shift = np.asarray(to, np.float32) - iris[:2].astype(np.float32)
    sx, sy = xs - shift[0], ys - shift[1]  # where each output pixel's iris pixel was
    cx, cy = float(iris[0]), float(iris[1])
    mirrored = 2 * cy - sy
    # pixels right inside the outline are lashes and the lid's shadow as often as eye: not taken
    inner = cv2.erode(seen.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    visible = cv2.remap(inner, sx, sy, cv2.INTER_LINEAR, borderValue=0) > 0.99
    source_y = np.where(visible, sy, mirrored)
    ring = np.zeros((h, w, 3), np.float32)
    hidden_too = ~visible & (cv2.remap(inner, sx, mirrored, cv2.INTER_LINEAR) <= 0.99)
    if hidden_too.any():  # neither the pixel nor its mirror image was seen: the iris's mean colour
        inside = seen & old
        ring[:] = patch[inside].mean(0) if inside.any() else patch[seen].mean(0)
    moved = cv2.remap(patch, sx, source_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    moved = np.where(hidden_too[..., None], ring, moved)
    cover = _disc((h, w), to, IRIS_EDGE[0] * iris[2], IRIS_EDGE[1] * iris[2])[..., None]
    eye = white + cover * (moved - white)
    return patch + opening[..., None] * (eye - patch)


def move_eyes(frame: np.ndarray, moves: list[EyeMove], with_weight: bool = False):
    """``frame`` ``(H, W, 3)`` uint8 with each eye of ``moves`` turned (a new array; ``frame`` itself when
    nothing moves). ``with_weight``: also the ``(H, W)`` float32 share of each output pixel that changed
    (the eye openings)."""
    out = frame
    weight = np.zeros(frame.shape[:2], np.float32) if with_weight else None
    for move in moves:
        if np.abs(move.to - move.iris[:2]).max() < 1e-3:
            continue
        width = np.ptp(move.outline[:, 0])
        lo = np.floor(move.outline.min(0) - MARGIN * width).astype(int).clip(0)
        hi = np.ceil(move.outline.max(0) + MARGIN * width).astype(int) + 1
        hi = np.minimum(hi, [frame.shape[1], frame.shape[0]])
        if (hi - lo).min() < 4:
            continue
        (x0, y0), (x1, y1) = lo, hi
        h, w = y1 - y0, x1 - x0
        patch = out[y0:y1, x0:x1].astype(np.float32)
        mask = _opening_mask(move.outline, (h, w), lo)
        iris = np.concatenate([move.iris[:2] - lo, move.iris[2:]])
        made = turned_eye(patch, mask, iris, move.to - lo)
        if out is frame:
            out = frame.copy()
        out[y0:y1, x0:x1] = np.clip(np.round(made), 0, 255).astype(np.uint8)
        if weight is not None:
            weight[y0:y1, x0:x1] = np.maximum(weight[y0:y1, x0:x1], mask)
    return (out, weight) if with_weight else out


def turn_eyes(model, seq, frame: np.ndarray, index: int, gaze: np.ndarray | None = None) -> np.ndarray:
    """``frame`` (footage frame ``index`` of ``seq`` or a render over it, which keeps its eyes) with the eyes
    looking into the lens (``gaze`` None) or along ``gaze`` ``(2,)`` (yaw and pitch in radians in the face's
    frame, :mod:`nvp.gaze`)."""
    centres = footage_gaze(model, seq, np.array([index]))[0][0]
    if gaze is None:
        directions = towards_camera(centres)
    else:
        directions = np.repeat((seq.rotation[index] @ gaze_vectors(gaze))[None], 2, 0)
    return move_eyes(frame, eye_moves(model, seq, index, directions, centres))
