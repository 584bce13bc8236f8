"""A demo input that ships with nvp: a short synthetic "talking" clip made from a public-domain photo.

No real footage ships with the project, so ``nvp demo`` animates the astronaut portrait from scikit-image
(``skimage.data.astronaut()``, Eileen Collins, NASA, public domain): the face landmarks are detected once,
then every frame warps the photo with a smooth backward-mapping displacement field that lowers the lower
lip, chin and jaw by a speech-like mouth-opening signal, paints the mouth interior that opens up, adds blinks
and a little head motion, and pairs it with a synthetic voiced sound whose loudness follows the mouth.
Because the animation is known exactly, the clip doubles as a ground truth for the tracker.

Face frame: all geometry is computed in output-pixel coordinates of an upright, unmoving face ("face
frame"); the head motion of frame ``t`` maps the face frame to the output frame by a rotation of
``head_angle[t]`` degrees about the nose tip (counter-clockwise on screen for positive angles) followed by a
small translation.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nvp.app.demo_voice import AUDIO_RATE, smoothstep, speech_script, synth_voice
from nvp.errors import NoFaceError
from nvp.provenance import synthetic_mark

log = logging.getLogger(__name__)

# mediapipe face-mesh landmark indices
UPPER_INNER_LIP = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308)
LOWER_INNER_LIP = (78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308)
CHIN = 152
FOREHEAD = 10
NOSE_TIP = 1
MOUTH_CORNERS = (61, 291)
# eyes: (corner, upper-lid contour..., corner) and (corner, lower-lid contour..., corner), image left to right
EYE_UPPER = (
    (33, 246, 161, 160, 159, 158, 157, 173, 133),
    (362, 398, 384, 385, 386, 387, 388, 466, 263),
)
EYE_LOWER = (
    (33, 7, 163, 144, 145, 153, 154, 155, 133),
    (362, 382, 381, 380, 374, 373, 390, 249, 263),
)

# Framing: the forehead-to-chin landmark distance covers this fraction of the frame height, and the midpoint
# of those two landmarks sits at this fraction of the frame height from the top.
_FACE_HEIGHT = 0.45
_FACE_CENTER_Y = 0.48
# Largest animated inner-lip gap as a fraction of the mouth width (corner to corner).
_MAX_OPENING = 0.40


@dataclass(frozen=True)
class DemoClip:
    """The synthetic clip written by :func:`make_demo_clip` and its ground truth.

    Attributes:
        path: the mp4 file (H.264 video, AAC audio at :data:`AUDIO_RATE` Hz).
        fps: frame rate, frames/s.
        num_frames: number of frames ``T``.
        mouth_opening: ``(T,)`` float, the animated inner-lip gap in output pixels, measured along the
            face's vertical axis at the column of landmarks 13/14 (0 = lips closed).
        head_angle: ``(T,)`` float, in-plane head rotation in degrees (counter-clockwise on screen > 0).
    """

    path: Path
    fps: float
    num_frames: int
    mouth_opening: np.ndarray
    head_angle: np.ndarray


def _head_motion(num_frames: int, fps: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Slow in-plane rotation (degrees, within about ±4) and translation (pixels at 384, within about ±5)."""
    t = np.arange(num_frames) / fps
    angle = np.zeros(num_frames)
    shift = np.zeros((num_frames, 2))
    for _ in range(3):
        freq, ph = rng.uniform(0.08, 0.45), rng.uniform(0, 2 * np.pi)
        angle += rng.uniform(0.7, 1.5) * np.sin(2 * np.pi * freq * t + ph)
        for k in range(2):
            freq, ph = rng.uniform(0.1, 0.5), rng.uniform(0, 2 * np.pi)
            shift[:, k] += rng.uniform(0.6, 1.6) * np.sin(2 * np.pi * freq * t + ph)
    return angle, shift


def _blinks(num_frames: int, fps: float, rng: np.random.Generator) -> np.ndarray:
    """``(T,)`` eyelid closure in [0, 1]: a blink every 2–4.5 s, ~0.25 s long (fast close, slower open)."""
    t = np.arange(num_frames) / fps
    closure = np.zeros(num_frames)
    start = rng.uniform(0.8, 2.0)
    while start < t[-1] + 1.0:
        close_s, open_s = 0.08, 0.16
        rising = (t - start) / close_s
        falling = 1.0 - (t - start - close_s) / open_s
        shape = np.where(t < start + close_s, smoothstep(rising), smoothstep(falling))
        closure = np.maximum(closure, np.where(t >= start, shape, 0.0))
        start += rng.uniform(2.0, 4.5)
    return closure


# -------------------------------------------------------------------------------------------- the rig


def _curve(points: np.ndarray, indices: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of a landmark contour, sorted by x and made strictly increasing in x for ``np.interp``."""
    p = points[list(indices), :2].astype(float)
    order = np.argsort(p[:, 0], kind="stable")
    x, y = p[order, 0], p[order, 1]
    x = np.maximum.accumulate(x + np.arange(len(x)) * 1e-6)
    return x, y


@dataclass(frozen=True)
class _Rig:
    """The photo, its landmarks in the face frame and the warp that animates it."""

    image: np.ndarray  # source photo, RGB uint8
    to_source: np.ndarray  # (2, 3) affine: face frame -> source pixels
    size: int
    upper: tuple[np.ndarray, np.ndarray]  # upper inner lip (x, y), face frame
    lower: tuple[np.ndarray, np.ndarray]  # lower inner lip
    center_x: float  # column of landmarks 13/14
    half_left: float  # centre column to the left/right inner mouth corner, pixels
    half_right: float
    mouth_width: float  # outer corner to corner
    chin_y: float
    face_height: float
    pivot: np.ndarray  # (2,) nose tip: centre of the head rotation
    eyes: tuple[tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]], ...]

    @property
    def rest_gap(self) -> float:
        """Inner-lip gap of the photo at the centre column (the astronaut smiles with her teeth showing)."""
        return float(np.interp(self.center_x, *self.lower) - np.interp(self.center_x, *self.upper))

    @property
    def max_opening(self) -> float:
        return _MAX_OPENING * self.mouth_width

    def _u(self, x: np.ndarray) -> np.ndarray:
        """Normalised horizontal mouth coordinate: 0 at the centre column, ±1 at the inner corners."""
        d = x - self.center_x
        return np.where(d < 0, d / self.half_left, d / self.half_right)

    def lip_offset(self, x: np.ndarray, opening: float) -> np.ndarray:
        """Vertical displacement of the lower inner lip at columns ``x`` for a centre gap of ``opening``.

        The target gap has a lens shape (``opening`` at the centre, 0 at the corners); the photo's own gap
        is subtracted, so ``opening = 0`` closes the lips.
        """
        u = self._u(x)
        lens = np.clip(1.0 - u * u, 0.0, 1.0) ** 0.6
        gap = np.clip(np.interp(x, *self.lower) - np.interp(x, *self.upper), 0.0, None)
        return np.where(np.abs(u) < 1.0, opening * lens - gap, 0.0)

    @property
    def _jaw_radius(self) -> float:
        """Horizontal reach of the jaw displacement from the centre column (a compact smooth bump)."""
        return 2.0 * self.mouth_width

    @property
    def _fade(self) -> tuple[float, float]:
        """Rows where the jaw displacement starts fading out below the chin, and where it is gone."""
        start = self.chin_y + 0.05 * self.face_height
        return start, start + 0.45 * self.face_height

    def _mouth_roi(self, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """Flat indices of the pixels the mouth/jaw warp can touch (everything else is left alone)."""
        top = float(self.lower[1].min()) - self.rest_gap - 2.0
        sel = (fy >= top) & (fy < self._fade[1]) & (np.abs(fx - self.center_x) < self._jaw_radius)
        return np.flatnonzero(sel)

    def _jaw_warp(self, x: np.ndarray, y: np.ndarray, opening: float) -> tuple[np.ndarray, np.ndarray]:
        """Warp the mouth region: face-frame points ``(x, y)`` after the warp → points before it.

        Above the displaced lower inner lip (inside the mouth) nothing moves. Below it, a forward vertical
        displacement blends from the lens-shaped lip displacement (at the lower inner lip) to a wider jaw
        displacement towards the chin (chin and jaw move as one, a little more than the lip since the jaw
        rotates) and fades out below the chin so the neck stays put; outside the mouth columns it is zero
        above the mouth-corner line. The backward map is the fixed point of ``g + D(g) = y``.

        Returns ``(g, lip)``: source rows and the lower-lip displacement at each column.
        """
        lip = self.lip_offset(x, opening)
        lip_line = np.interp(x, *self.lower)
        lip_center = float(np.interp(self.center_x, *self.lower))
        reach = 0.55 * (self.chin_y - lip_center)
        d = (x - self.center_x) / self._jaw_radius
        jaw = 1.1 * (opening - self.rest_gap) * np.clip(1.0 - d * d, 0.0, None) ** 2
        fade0, fade1 = self._fade
        moving = (np.abs(self._u(x)) >= 1.0) | (y >= lip_line + lip)
        g = y.copy()
        ym, lm, jm, linem = y[moving], lip[moving], jaw[moving], lip_line[moving]
        gm = ym.copy()
        for _ in range(6):
            beta = smoothstep((gm - linem) / reach)
            fade = 1.0 - smoothstep((gm - fade0) / (fade1 - fade0))
            gm = ym - (lm + (jm - lm) * beta) * fade
        g[moving] = gm
        return g, lip

    def _blink_warp(self, fx: np.ndarray, gy: np.ndarray, blink: float) -> np.ndarray:
        """Close the eyes by ``blink`` in [0, 1]: the upper lid margin slides down towards the lower lid and
        the lid skin above it (up to 0.35 eye widths) stretches. Returns the new source rows."""
        for upper, lower in self.eyes:
            x0, x1 = upper[0][0], upper[0][-1]
            brow_gap = 0.35 * (x1 - x0)
            y_top = float(upper[1].min()) - brow_gap
            y_bottom = float(lower[1].max())
            idx = np.flatnonzero((fx > x0) & (fx < x1) & (gy >= y_top) & (gy <= y_bottom))
            if idx.size == 0:
                continue
            x, g = fx.ravel()[idx], gy.ravel()[idx]
            y_up = np.interp(x, *upper)
            margin = y_up + 0.95 * blink * np.clip(np.interp(x, *lower) - y_up, 0.0, None)
            brow = y_up - brow_gap
            lid = (g >= brow) & (g < margin)
            t = (g - brow) / np.maximum(margin - brow, 1e-6)
            gy.ravel()[idx] = np.where(lid, brow + t * (y_up - brow), g)
        return gy

    def render(self, opening: float, blink: float, angle: float, shift: np.ndarray) -> np.ndarray:
        """One RGB uint8 frame with the given centre lip gap (face-frame pixels), lid closure and pose."""
        import cv2

        s = self.size
        py, px = np.mgrid[0:s, 0:s].astype(np.float64)
        a = np.deg2rad(angle)
        ca, sa = np.cos(a), np.sin(a)
        # output p = pivot + R (f - pivot) + shift with R = [[c, s], [-s, c]] (counter-clockwise on screen)
        qx, qy = px - shift[0] - self.pivot[0], py - shift[1] - self.pivot[1]
        fx = self.pivot[0] + ca * qx - sa * qy
        fy = self.pivot[1] + sa * qx + ca * qy

        gy = fy.copy()
        roi = self._mouth_roi(fx, fy)
        x, y = fx.ravel()[roi], fy.ravel()[roi]
        g, lip = self._jaw_warp(x, y, opening)
        gy.ravel()[roi] = g
        if blink > 0:
            gy = self._blink_warp(fx, gy, blink)

        m = self.to_source
        map_x = (m[0, 0] * fx + m[0, 1] * gy + m[0, 2]).astype(np.float32)
        map_y = (m[1, 0] * fx + m[1, 1] * gy + m[1, 2]).astype(np.float32)
        frame = cv2.remap(self.image, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT101)
        self._paint_mouth(frame.reshape(-1, 3), roi, x, y, lip, opening)
        return frame

    def _paint_mouth(
        self,
        pixels: np.ndarray,
        roi: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        lip: np.ndarray,
        opening: float,
    ) -> None:
        """Paint the mouth cavity between the photo's lower inner lip and the displaced lower lip, in place.

        The photo's upper teeth (between the inner lips of the photo) stay; below them the cavity is dark,
        with a dark-red tongue towards the lower lip and shadow towards the corners.
        """
        top = np.interp(x, *self.lower)
        depth = lip
        # antialiased vertical extent: soft (teeth edge) at the top, crisp at the lower lip
        alpha = np.clip((y - top + 1.0) / 2.5, 0.0, 1.0) * np.clip(top + depth - y + 0.5, 0.0, 1.0)
        sel = np.flatnonzero((depth > 0.5) & (alpha > 0))
        if sel.size == 0:
            return
        a, xs = alpha[sel], x[sel]
        v = np.clip((y[sel] - top[sel]) / depth[sel], 0.0, 1.0)
        u = np.abs(self._u(xs))
        open_frac = np.clip(opening / self.max_opening, 0.0, 1.0)
        shadow = np.array([18.0, 8.0, 9.0])
        cavity = np.array([72.0, 18.0, 16.0])
        tongue = np.array([168.0, 72.0, 66.0])
        # shadow under the teeth -> dark cavity -> tongue near the lower lip (more visible when wide open)
        w_cav = smoothstep((v - 0.05) / 0.45)[:, None]
        w_tongue = (smoothstep((v - 0.55) / 0.45) * (0.3 + 0.5 * open_frac))[:, None]
        color = shadow + (cavity - shadow) * w_cav
        color = color + (tongue - color) * w_tongue
        color = color * (1.0 - 0.6 * smoothstep((u - 0.55) / 0.45))[:, None]  # corners in shadow
        idx = roi[sel]
        old = pixels[idx].astype(np.float64)
        pixels[idx] = np.clip(old + (color - old) * a[:, None] + 0.5, 0, 255).astype(np.uint8)


def _build_rig(image: np.ndarray, points: np.ndarray, size: int) -> _Rig:
    """Frame the face (upright, centred, large) and express the landmarks in that face frame."""
    eye_a = points[list(EYE_UPPER[0] + EYE_LOWER[0]), :2].mean(0)
    eye_b = points[list(EYE_UPPER[1] + EYE_LOWER[1]), :2].mean(0)
    roll = np.arctan2(eye_b[1] - eye_a[1], eye_b[0] - eye_a[0])
    top, chin = points[FOREHEAD, :2].astype(float), points[CHIN, :2].astype(float)
    scale = _FACE_HEIGHT * size / float(np.linalg.norm(chin - top))
    center = 0.5 * (top + chin)
    c, s = np.cos(roll), np.sin(roll)
    # source -> face frame: rotate by -roll about the face centre, scale, move the centre into place
    rot = scale * np.array([[c, s], [-s, c]])
    target = np.array([0.5 * size, _FACE_CENTER_Y * size])
    to_face = np.hstack([rot, (target - rot @ center)[:, None]])
    inv = np.linalg.inv(np.vstack([to_face, [0.0, 0.0, 1.0]]))[:2]
    pts = points[:, :2].astype(float) @ to_face[:, :2].T + to_face[:, 2]

    center_x = float(0.5 * (pts[13, 0] + pts[14, 0]))
    eyes = tuple((_curve(pts, up), _curve(pts, lo)) for up, lo in zip(EYE_UPPER, EYE_LOWER, strict=True))
    return _Rig(
        image=np.ascontiguousarray(image),
        to_source=inv,
        size=size,
        upper=_curve(pts, UPPER_INNER_LIP),
        lower=_curve(pts, LOWER_INNER_LIP),
        center_x=center_x,
        half_left=max(center_x - float(pts[78, 0]), 1.0),
        half_right=max(float(pts[308, 0]) - center_x, 1.0),
        mouth_width=float(np.linalg.norm(pts[MOUTH_CORNERS[1]] - pts[MOUTH_CORNERS[0]])),
        chin_y=float(pts[CHIN, 1]),
        face_height=float(pts[CHIN, 1] - pts[FOREHEAD, 1]),
        pivot=pts[NOSE_TIP].copy(),
        eyes=eyes,
    )


def _photo_rig(size: int) -> _Rig:
    """The astronaut portrait, its landmarks detected once with mediapipe."""
    from skimage import data

    from tracking.landmarks import LandmarkDetector

    image = data.astronaut()
    with LandmarkDetector() as det:
        found = det.detect(image, 0.0)
    if found is None:
        raise NoFaceError("no face was found in the demo photo (skimage.data.astronaut)")
    return _build_rig(image, found.points, size)


# ------------------------------------------------------------------------------------------- public API


def make_demo_clip(
    path: str | Path, seconds: float = 6.0, fps: float = 25.0, size: int = 384, seed: int = 0
) -> DemoClip:
    """Write a synthetic talking-head clip (mp4 with audio) made from ``skimage.data.astronaut()``.

    The mouth follows a random speech-like opening signal (syllables at 3–6 Hz with pauses), the eyes
    blink every few seconds and the head moves slightly; the audio is a synthetic voice whose loudness
    follows the mouth. Deterministic for a given ``seed`` (and library versions).

    Args:
        path: output mp4.
        seconds: duration; the clip has ``round(seconds * fps)`` frames.
        fps: frame rate.
        size: width and height of the square frames, pixels.
        seed: random seed of the animation and the audio.

    Returns:
        A :class:`DemoClip` with the animated ground truth.

    Raises:
        NoFaceError: mediapipe found no face in the photo.
        MediaError: the video could not be written.
        ValueError: non-positive ``seconds``, ``fps`` or a ``size`` under 64 pixels.
    """
    from nvp.media import VideoWriter

    if not seconds > 0 or not fps > 0:
        raise ValueError(f"seconds and fps must be positive, got {seconds} and {fps}")
    if size < 64:
        raise ValueError(f"size must be at least 64 pixels, got {size}")
    num_frames = max(1, round(seconds * fps))
    t0 = time.perf_counter()
    rig = _photo_rig(int(size))
    rng = np.random.default_rng(seed)
    speech = speech_script(num_frames / fps, rng)
    opening = speech(np.arange(num_frames) / fps) * rig.max_opening
    angle, shift = _head_motion(num_frames, fps, rng)
    shift = shift * (size / 384.0)
    blink = _blinks(num_frames, fps, rng)
    audio = synth_voice(speech, num_frames / fps, rng)

    path = Path(path)
    with VideoWriter(
        path,
        fps=fps,
        width=size,
        height=size,
        audio=audio,
        audio_rate=AUDIO_RATE,
        metadata=synthetic_mark("demo-target", source=f"skimage.data.astronaut, seed {seed}"),
    ) as writer:
        for i in range(num_frames):
            writer.write(rig.render(float(opening[i]), float(blink[i]), float(angle[i]), shift[i]))
    log.info(
        "wrote demo clip %s: %d frames at %g fps, %dx%d, in %.1f s",
        path,
        num_frames,
        fps,
        size,
        size,
        time.perf_counter() - t0,
    )
    return DemoClip(
        path=path,
        fps=float(fps),
        num_frames=num_frames,
        mouth_opening=opening.astype(np.float64),
        head_angle=angle.astype(np.float64),
    )
