"""Eye contact: the footage's eyes turned to look where asked (``nvp dub --gaze``).

Inside each eye opening (its outline from tracking) the iris, its centre and radius from mediapipe's iris
landmarks, is moved to where an eyeball of the tracked head looking the asked way shows it
(:func:`nvp.gaze.iris_pixels`), over the white of the eye filled in where it was (:func:`turned_eye`).
The footage's own pixels move: no network paints them, so the eyes keep the footage's sharpness and light.
The lids follow a raised or lowered gaze, the skin around them warped smoothly to the patch's unchanged
border (no seam to hide); lashes and blinks stay the footage's. Limits: a turn of at most
:data:`MAX_TURN_DEG`, no eye seen edge-on (:data:`SIDEWAYS`) or smaller than :data:`MIN_IRIS_PX`, and a
closing eye let go gradually (:data:`OPEN_FROM`, :data:`OPEN_FULL`): in a blink the iris is hidden and its
landmarks mean nothing. Measured in docs/experiments/gaze.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from nvp.gaze import EYES, footage_gaze, gaze_from_iris, gaze_vectors, iris_pixels, towards_camera

MAX_TURN_DEG = 15.0
"""The farthest an eye is turned from where it looks in the footage (degrees): the irises of people who read
a script beside the camera are 5-15 degrees off; beyond, moving the footage's pixels shows (an iris pulled
out from behind a lid or a corner, half an eye of white invented) and mediapipe's iris of an eye turned far
aside is itself up to half a radius off."""
MIN_IRIS_PX = 6.0
"""Smallest iris radius (pixels) whose eye is turned. Below it (an eye under about 30 pixels wide) the few
pixels of white, filled in flat, make a staring eye (looked at on two 224² test people, iris 4 px), and
mediapipe's iris is off by a good part of its radius."""
SIDEWAYS = (3.5, 4.0)
"""Eye width over iris radius below which an eye is left alone (the far eye of a head turned aside, seen
edge-on: a few pixels of white, no room to move an iris) and from which it moves all the way. Facing eyes
of test people: 4-5 (5th percentile 4.0-4.9); the far eye of a three-quarter view: 2.5-3.9."""
OPEN_FROM = 0.5
"""Lid gap over iris radius at and below which an eye is left alone (closed or closing: a blink). Open eyes
of ten test people: median 1.2-1.8, 10th percentile 0.65-1.55, blinks below 0.5."""
OPEN_FULL = 0.8
"""Lid gap over iris radius from which the iris moves all the way (between, part of the way)."""
IRIS_EDGE = (1.0, 1.25)
"""The moved iris covers the white fully out to the first of these radii (over mediapipe's iris radius) and
fades out at the second (its dark outer ring, the limbus, goes with it without a hard edge); its old place
is filled with white out to the second."""
LIDS_FOLLOW = (1.0, 0.35)
"""Share of the iris's vertical move the middle of the upper and of the lower lid follow (a lowered gaze
lowers the upper lid with it, almost one to one; the lower lid moves less)."""
LASHES = 0.2
"""The band just inside the opening's outline that shows lashes and the lids' shadow rather than eye, over
the iris radius: no iris or white is taken from it."""
WHITE_DETAIL = 6
"""The white of the eye is filled in at a resolution of this many pixels per iris radius."""
LID_EDGE = 0.12
"""Blur (Gaussian sigma over the iris radius) of the lids' edge over the turned eye."""
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


def within_reach(now: np.ndarray, asked: np.ndarray) -> np.ndarray:
    """``(..., 3)`` unit directions ``asked`` (camera frame), each turned at most :data:`MAX_TURN_DEG` away
    from where its eye looks ``now`` (towards ``asked``, along the great circle); ``asked`` itself where
    ``now`` is unknown (NaN)."""
    now = np.asarray(now, np.float64)
    asked = np.asarray(asked, np.float64) / np.linalg.norm(asked, axis=-1, keepdims=True)
    cos = np.clip((now * asked).sum(-1, keepdims=True), -1, 1)
    angle = np.arccos(cos)
    limit = np.radians(MAX_TURN_DEG)
    # the part of ``asked`` square to ``now``: the way to turn
    side = asked - cos * now
    side /= np.maximum(np.linalg.norm(side, axis=-1, keepdims=True), 1e-12)
    turned = np.cos(limit) * now + np.sin(limit) * side
    return np.where(angle > limit, turned, asked)


def eye_moves(model, seq, index: int, directions: np.ndarray, centres: np.ndarray | None = None) -> list:
    """The :class:`EyeMove` of each eye of footage frame ``index`` of ``seq`` (its tracking, with iris) to
    look along camera-frame ``directions`` ``(2, 3)`` (left eye first), from eyeball ``centres`` ``(2, 3)``
    (default: the tracked head's, :func:`nvp.gaze.footage_gaze`), or as far towards them as
    :data:`MAX_TURN_DEG` lets it (:func:`within_reach`). An eye without iris landmarks (no face found) or
    closing (:data:`OPEN_FROM`), seen from the side (:data:`SIDEWAYS`) or too small (:data:`MIN_IRIS_PX`) is
    left out; a half-open one moves part of the way."""
    if centres is None:
        centres = footage_gaze(model, seq, np.array([index]))[0][0]
    now = gaze_from_iris(centres, seq.iris[index, :, :2], seq.focal, seq.center)
    to = iris_pixels(centres, within_reach(now, directions), seq.focal, seq.center)
    moves = []
    for e, group in enumerate(EYES):
        outline = seq.landmarks[index, model.landmark_groups[group]].astype(np.float64)
        iris = seq.iris[index, e].astype(np.float64)
        if not (np.isfinite(outline).all() and np.isfinite(iris).all() and np.isfinite(to[e]).all()):
            continue
        if iris[2] < MIN_IRIS_PX:
            continue
        share = np.clip((openness(outline, iris[2]) - OPEN_FROM) / (OPEN_FULL - OPEN_FROM), 0, 1)
        wide = np.ptp(outline[:, 0]) / iris[2]
        share *= np.clip((wide - SIDEWAYS[0]) / (SIDEWAYS[1] - SIDEWAYS[0]), 0, 1)
        if share > 0:
            moves.append(EyeMove(outline, iris, iris[:2] + share * (to[e] - iris[:2])))
    return moves


def _opening_mask(outline: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(h, w)`` float32 coverage (anti-aliased) of the eye opening ``outline`` (patch pixels)."""
    mask = np.zeros(shape, np.uint8)
    pts = np.round(outline * 16).astype(np.int32)  # 4 bits of sub-pixel precision
    cv2.fillPoly(mask, [pts], 255, cv2.LINE_AA, shift=4)
    return mask.astype(np.float32) / 255


def _disc(shape: tuple[int, int], centre: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """``(h, w)`` float32 coverage of a disc: 1 out to radius ``inner``, falling to 0 at ``outer``."""
    ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    return np.clip((outer - np.hypot(xs - centre[0], ys - centre[1])) / max(outer - inner, 1.0), 0, 1)


def lids_moved(outline: np.ndarray, shift_y: float) -> np.ndarray:
    """``(N, 2)`` eye-opening ``outline`` with its lids following the iris's vertical ``shift_y`` (pixels)
    as real lids follow the eye (:data:`LIDS_FOLLOW`): most in the middle of each lid, not at all at the
    two corners (the outline's leftmost and rightmost points)."""
    o = np.asarray(outline, np.float64)
    a, b = o[np.argmin(o[:, 0])], o[np.argmax(o[:, 0])]
    u = np.clip((o[:, 0] - a[0]) / max(b[0] - a[0], 1e-6), 0, 1)
    chord = a[1] + u * (b[1] - a[1])
    follow = np.where(o[:, 1] < chord, LIDS_FOLLOW[0], LIDS_FOLLOW[1])  # above the corners' line: upper lid
    return o + np.stack([np.zeros(len(o)), 4 * u * (1 - u) * follow * shift_y], 1)


def thin_plate_spline(points: np.ndarray, values: np.ndarray):
    """The thin-plate spline through ``values`` ``(N, 2)`` at ``points`` ``(N, 2)`` (the smoothest map of
    the plane taking each point to its value), as a function of ``(M, 2)`` points. (kornia's
    ``get_tps_transform`` centres its kernels on the values, not the points: it meets them at the points
    but bends between them.)"""
    p = np.asarray(points, np.float64)
    n = len(p)

    def kernel(q: np.ndarray) -> np.ndarray:
        d2 = ((q[:, None] - p[None]) ** 2).sum(-1)
        return 0.5 * d2 * np.log(np.where(d2 > 0, d2, 1.0))  # r² log r

    affine = np.concatenate([np.ones((n, 1)), p], 1)
    system = np.block([[kernel(p), affine], [affine.T, np.zeros((3, 3))]])
    rhs = np.concatenate([np.asarray(values, np.float64), np.zeros((3, 2))])
    weights = np.linalg.lstsq(system, rhs, rcond=None)[0]
    return lambda q: kernel(q) @ weights[:n] + np.concatenate([np.ones((len(q), 1)), q], 1) @ weights[n:]


def _lids_warped(patch: np.ndarray, outline: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """``patch`` warped so that its eye-opening ``outline`` lies on ``moved`` (the skin, lids and lashes
    carried along smoothly), the patch's border staying where it is."""
    h, w = patch.shape[:2]
    border = np.array(
        [[x, y] for x in (0, w / 2, w - 1) for y in (0, h / 2, h - 1) if (x, y) != (w / 2, h / 2)]
    )
    spline = thin_plate_spline(np.concatenate([moved, border]), np.concatenate([outline, border]))
    step = 3  # the spline is smooth: computed at every third pixel, interpolated between
    ys, xs = np.mgrid[0 : h + step : step, 0 : w + step : step].astype(np.float64)
    coarse = spline(np.stack([xs.ravel(), ys.ravel()], 1)).reshape(*xs.shape, 2).astype(np.float32)
    fine = cv2.resize(
        coarse, (coarse.shape[1] * step, coarse.shape[0] * step), interpolation=cv2.INTER_LINEAR
    )
    grid = fine[1 : 1 + h, 1 : 1 + w]  # cv2.resize puts coarse sample k at fine pixel 3 k + 1
    return cv2.remap(patch, grid[..., 0], grid[..., 1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def _spread(patch: np.ndarray, known: np.ndarray, step: int) -> np.ndarray:
    """``patch`` with its pixels outside ``known`` filled from those inside (OpenCV's Telea inpainting),
    the filling done at 1 / ``step`` of the resolution (the white of an eye holds no detail worth the time:
    a large eye took 32 ms at full resolution)."""
    h, w = known.shape
    size = (max(1, w // step), max(1, h // step))
    small = cv2.resize(patch, size, interpolation=cv2.INTER_AREA)
    small_known = cv2.resize(known.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.99
    if not small_known.any():
        small_known = cv2.resize(known.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0
    filled = cv2.inpaint(
        np.clip(small, 0, 255).astype(np.uint8), (~small_known).astype(np.uint8), 3, cv2.INPAINT_TELEA
    )
    filled = cv2.resize(filled.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    return np.where(known[..., None], patch, filled)


def turned_eye(patch: np.ndarray, outline: np.ndarray, iris: np.ndarray, to: np.ndarray):
    """``(h, w, 3)`` float32 eye ``patch`` with its iris (centre ``iris[:2]``, radius ``iris[2]``, patch
    pixels) moved to ``to`` and the ``(h, w)`` share of each pixel that changed. ``outline``: the eye
    opening in the patch.

    The lids follow the iris's vertical move (:func:`lids_moved`, the skin around them warped smoothly,
    :func:`thin_plate_spline`); inside the new opening, two layers: the white of the eye, spread by OpenCV's
    inpainting from the white the footage shows (over the iris's old place and where the lids open wider
    than in the footage), and over it the iris, each of its pixels from where it was; a part the lids hid in
    the footage is taken from a mirror image of it (an iris is much the same all around), else from its
    mean colour."""
    h, w = patch.shape[:2]
    seen = _opening_mask(outline, (h, w)) > 0.5
    reach = 2 * max(1, round(LASHES * iris[2])) + 1
    inner = cv2.erode(seen.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (reach, reach)))
    luma = patch @ np.array([0.299, 0.587, 0.114], np.float32)
    shift = np.asarray(to, np.float64) - iris[:2]
    opened = lids_moved(outline, shift[1])
    skin = patch if abs(shift[1]) < 0.05 else _lids_warped(patch, outline, opened)
    old = _disc((h, w), iris[:2], IRIS_EDGE[1] * iris[2], IRIS_EDGE[1] * iris[2] + 1) > 0
    # the white the footage shows: the brighter half of the opening outside the iris (a part of the iris
    # mediapipe's circle misses, lashes or the lids' shadow are darker; not spread as white)
    white_seen = inner.astype(bool) & ~old
    if white_seen.any():
        white_seen &= luma >= np.median(luma[white_seen])
    if white_seen.sum() >= 4:
        white = _spread(patch, white_seen, max(1, int(iris[2] // WHITE_DETAIL)))
    else:  # no white in sight (a narrow eye filled by its iris): its brightest pixels
        bright = np.percentile(patch[seen], 95, axis=0) if seen.any() else patch.mean((0, 1))
        white = np.broadcast_to(bright, patch.shape)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    sx, sy = xs - np.float32(shift[0]), ys - np.float32(shift[1])  # where each output pixel's iris pixel was
    inner = inner.astype(np.float32)
    # each iris pixel from where it was, else (hidden by a lid or a corner) from its mirror image across the
    # iris's horizontal middle, its vertical middle or its centre
    mx, my = np.float32(2 * iris[0]) - sx, np.float32(2 * iris[1]) - sy
    take_x, take_y = sx.copy(), sy.copy()
    hidden = cv2.remap(inner, sx, sy, cv2.INTER_LINEAR, borderValue=0) <= 0.99
    for cx, cy in ((sx, my), (mx, sy), (mx, my)):
        found = hidden & (cv2.remap(inner, cx, cy, cv2.INTER_LINEAR, borderValue=0) > 0.99)
        take_x[found], take_y[found] = cx[found], cy[found]
        hidden &= ~found
    moved = cv2.remap(patch, take_x, take_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    if hidden.any():  # nowhere seen: the iris's mean colour
        where = seen & old
        moved[hidden] = patch[where].mean(0) if where.any() else patch[seen].mean(0)
    cover = _disc((h, w), to, IRIS_EDGE[0] * iris[2], IRIS_EDGE[1] * iris[2])[..., None]
    eye = white + cover * (moved - white)
    # the lids' edge is as soft as the footage's (blurred by optics and compression), not a polygon's
    opening = cv2.GaussianBlur(_opening_mask(opened, (h, w)), (0, 0), LID_EDGE * iris[2])
    made = skin + opening[..., None] * (eye - skin)
    changed = np.maximum(opening, (np.abs(skin - patch).max(-1) > 0.5).astype(np.float32))
    return made, changed


def move_eyes(frame: np.ndarray, moves: list[EyeMove], with_weight: bool = False):
    """``frame`` ``(H, W, 3)`` uint8 with each eye of ``moves`` turned (a new array; ``frame`` itself when
    nothing moves). ``with_weight``: also the ``(H, W)`` float32 share of each output pixel that changed
    (the eye openings, and the lids where they follow the iris)."""
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
        patch = out[y0:y1, x0:x1].astype(np.float32)
        iris = np.concatenate([move.iris[:2] - lo, move.iris[2:]])
        made, changed = turned_eye(patch, move.outline - lo, iris, move.to - lo)
        if out is frame:
            out = frame.copy()
        out[y0:y1, x0:x1] = np.clip(np.round(made), 0, 255).astype(np.uint8)
        if weight is not None:
            weight[y0:y1, x0:x1] = np.maximum(weight[y0:y1, x0:x1], changed)
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
