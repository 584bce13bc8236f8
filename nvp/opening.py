"""How far the mouth is open, read from speech by one generic linear model (``OpeningModel``).

The person map of :mod:`nvp.person` is solved on the target's own footage, often a few seconds, and the
generic network it reads was trained through one such map per training video; both leave the mouth's
opening only loosely tied to the sound. This model is the other half: a ridge regression from a window of
speech features (Whisper's encoder states, ``"whisper"``, :mod:`nvp.audio_features`; the first shipped
model read the phoneme recogniser's hidden features, ``"phonetic"``) to the *standardised*
inner-lip gap (each training video's gap minus its mean, over its standard deviation), so it needs no
person and no map. It predicts a held-out person's opening better than the network and map do, and the
person layer blends the two (:class:`nvp.person.OpeningStyle`).

It is trained in closed form by ``nvp train-opening`` (:mod:`nvp.app.train_opening`) and ships as
``nvp/assets/opening_whisper.{npz,json}``. The earlier ``opening_phonetic`` model still ships, so that
people fitted with it keep dubbing exactly as before (:func:`shipped_opening_model` finds a style's model by
its hash).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from nvp.artifact import load_artifact, save_artifact

FORMAT_VERSION = 1
FEATURE_KIND = "whisper"
"""Features new opening models read (and ``nvp fit`` calibrates people on)."""
WINDOW_STEP = 2
"""Every ``WINDOW_STEP``-th sample of a feature window is read (8 of 16 at 25 Hz over 320 ms; all 16
predict no better on the validation people)."""
SMOOTHING_S = 0.08
"""Half-width in seconds of the triangular filter over the per-frame predictions (weights 1/4, 1/2, 1/4 at
25 fps: a 2-frame closure keeps 3/4 of its depth). On the validation people it brought the mouth's
frame-to-frame jitter back to that without the model (ratio to the real mouth 0.99 → 0.81; without the
model 0.81) and raised the opening correlation 0.588 → 0.597."""
ADAPT_MIN_FRAMES = 400
"""Valid footage frames (16 s at 25 fps) from which :func:`adapted_opening_model` corrects the model.
Chosen on the validation people (whole clips, first 80 % to fit, last 20 % held out): the four with more
than 400 such frames all gained (held-out opening correlation 0.781 → 0.825, 0.779 → 0.821, 0.625 →
0.715, 0.695 → 0.812), the eight with 100-230 gained on average but three lost 0.08-0.14."""
ADAPT_RIDGES = (3e2, 1e3, 3e3, 1e4, 1e5)
"""Ridge strengths (raw feature units) tried for the person's correction; none is also a candidate."""
ADAPT_TAIL = 0.25
"""Fraction of the footage's valid frames, its last ones, held out to choose the ridge."""
ASSETS = Path(__file__).parent / "assets"
DEFAULT_PATH = ASSETS / "opening_whisper.json"
SHIPPED_PATHS = (DEFAULT_PATH, ASSETS / "opening_phonetic.json")
"""Every opening model that ships: the default first, then earlier ones that fitted people may use."""


@dataclass(frozen=True)
class OpeningModel:
    """``z_t = sum(weight * windows[t, ::window_step]) + bias``: the standardised mouth opening of frame t.

    Attributes:
        weight: ``(W', D)`` float32 weights on the raw window samples (input standardisation folded in).
        bias: the intercept.
        window_step: stride over the window's samples.
        sha256: hash of the weights file (empty for a model not loaded from disk); person styles record it.
        info: provenance (corpus, ridge, validation correlations).
        feature_kind: the speech features it reads (:data:`nvp.audio_features.FEATURE_KINDS`).
    """

    weight: np.ndarray
    bias: float
    window_step: int = WINDOW_STEP
    sha256: str = ""
    info: dict = field(default_factory=dict)
    feature_kind: str = FEATURE_KIND

    def predict(self, windows: np.ndarray | Iterable[np.ndarray], fps: float) -> np.ndarray:
        """``(T,)`` float32 standardised openings of the feature windows ``(T, W, D)`` (or consecutive blocks
        of them) of video frames at ``fps``, low-passed over :data:`SMOOTHING_S`."""
        from nvp.windows import tent_smooth

        blocks = [windows] if isinstance(windows, np.ndarray) else windows
        out = [
            np.einsum("twd,wd->t", np.asarray(b, np.float32)[:, :: self.window_step], self.weight) + self.bias
            for b in blocks
        ]
        if not out:
            return np.zeros(0, np.float32)
        return tent_smooth(np.concatenate(out), SMOOTHING_S * fps).astype(np.float32)

    def save(self, path: Path) -> Path:
        """Write ``path`` (.npz) and its ``.json`` manifest (:mod:`nvp.artifact`); returns the manifest."""
        fields = {"feature_kind": self.feature_kind, "window_step": self.window_step, "info": self.info}
        arrays = {"weight": self.weight, "bias": np.float32(self.bias)}
        return save_artifact(Path(path), "opening", FORMAT_VERSION, arrays, fields)

    @classmethod
    def load(cls, path: Path) -> OpeningModel:
        art = load_artifact(Path(path), "opening", FORMAT_VERSION)
        m = art.manifest
        return cls(
            art.arrays["weight"],
            float(art.arrays["bias"]),
            int(m["window_step"]),
            m["sha256"],
            m["info"],
            m["feature_kind"],
        )


def adapted_opening_model(
    model: OpeningModel, windows: np.ndarray, gap: np.ndarray, fps: float
) -> tuple[OpeningModel, dict]:
    """``model`` corrected for one person from their own footage, and what was chosen.

    The generic read-out predicts the opening any speaker's sound implies; a person's own frames show how
    *their* mouth follows *their* sound. The correction is a ridge regression of what the generic model
    misses (the person's standardised opening on the generic output's scale, minus that output) on the same
    windows, pulled towards none: the weights are ``model``'s plus it. Its strength is chosen among
    :data:`ADAPT_RIDGES` and "no correction" by the held-out correlation over the footage's last
    :data:`ADAPT_TAIL` (fitted on the frames before), then refitted on all frames. Footage with fewer than
    :data:`ADAPT_MIN_FRAMES` frames keeps ``model`` as it is.

    Args:
        windows: ``(T, W, D)`` the footage's valid frames' feature windows, in order.
        gap: ``(T,)`` their tracked inner-lip gaps.
        fps: the footage's frame rate.
    """
    from nvp.windows import tent_smooth

    info: dict = {"frames": len(gap)}
    if len(gap) < ADAPT_MIN_FRAMES or np.std(gap) < 1e-9:
        return model, info | {"ridge": None}
    x = np.asarray(windows, np.float32)[:, :: model.window_step].reshape(len(gap), -1).astype(np.float64)
    generic = x @ model.weight.reshape(-1).astype(np.float64) + model.bias
    goal = standardized_opening(gap, np.ones(len(gap), bool)) * generic.std() + generic.mean()

    def correction(rows: np.ndarray, ridge: float) -> tuple[np.ndarray, float]:
        mean, missed = x[rows].mean(0), goal[rows] - generic[rows]
        xc, r = x[rows] - mean, missed - missed.mean()
        if len(rows) < xc.shape[1]:  # fewer frames than weights: the dual form's system is smaller
            beta = xc.T @ np.linalg.solve(xc @ xc.T + ridge * np.eye(len(rows)), r)
        else:
            beta = np.linalg.solve(xc.T @ xc + ridge * np.eye(xc.shape[1]), xc.T @ r)
        return beta, float(missed.mean() - mean @ beta)

    def held_out_corr(beta: np.ndarray, bias: float, rows: np.ndarray) -> float:
        z = tent_smooth((generic + x @ beta + bias).astype(np.float32), SMOOTHING_S * fps)[rows]
        if np.std(z) < 1e-9 or np.std(gap[rows]) < 1e-9:  # nothing to rank by: keep the model
            return -1.0
        return float(np.corrcoef(z, gap[rows])[0, 1])

    split = int(round(len(gap) * (1 - ADAPT_TAIL)))
    fit_rows, tail = np.arange(split), np.arange(split, len(gap))
    scores = {None: held_out_corr(np.zeros(x.shape[1]), 0.0, tail)}
    for ridge in ADAPT_RIDGES:
        scores[ridge] = held_out_corr(*correction(fit_rows, ridge), tail)
    best = max(scores, key=lambda k: scores[k])
    info |= {"ridge": best, "tail_corr": {str(k): round(v, 4) for k, v in scores.items()}}
    if best is None:
        return model, info
    beta, bias = correction(np.arange(len(gap)), best)
    weight = (model.weight.astype(np.float64) + beta.reshape(model.weight.shape)).astype(np.float32)
    return replace(model, weight=weight, bias=float(model.bias + bias)), info


@lru_cache(maxsize=1)
def default_opening_model() -> OpeningModel:
    """The opening model that ships with nvp (new fits are calibrated on it)."""
    return OpeningModel.load(DEFAULT_PATH)


@lru_cache(maxsize=4)
def shipped_opening_model(sha256: str) -> OpeningModel | None:
    """The shipped opening model whose weights file has this hash (:data:`SHIPPED_PATHS`), None if none."""
    for path in SHIPPED_PATHS:
        model = default_opening_model() if path == DEFAULT_PATH else OpeningModel.load(path)
        if model.sha256 == sha256:
            return model
    return None


def standardized_opening(gap: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(T,)`` float32: inner-lip gaps ``(T,)`` minus their mean over the valid frames ``(T,)`` bool, over
    their standard deviation there (the model's target; 0 where the spread is nil)."""
    g = np.asarray(gap, np.float64)
    sd = g[valid].std() if valid.any() else 0.0
    if sd < 1e-9:
        return np.zeros(len(g), np.float32)
    return ((g - g[valid].mean()) / sd).astype(np.float32)


@dataclass(frozen=True)
class NormalEquations:
    """Sums over a corpus that ridge fits of any strength solve from (:func:`normal_equations`)."""

    xtx: np.ndarray
    xty: np.ndarray
    xs: np.ndarray
    ys: float
    n: int
    dim: int
    window_step: int

    def solve(self, ridge: float) -> OpeningModel:
        """The ridge regression with inputs standardised over all frames (``ridge`` in units of frames)."""
        mean = self.xs / self.n
        scatter = self.xtx - self.n * np.outer(mean, mean)
        std = np.sqrt(np.maximum(np.diag(scatter) / self.n, 0.0)) + 1e-6
        # normal equations of the standardised inputs (x - mean) / std against the centred targets
        a = scatter / np.outer(std, std) + ridge * np.eye(len(std))
        beta = np.linalg.solve(a, (self.xty - mean * self.ys) / std) / std
        return OpeningModel(
            weight=beta.reshape(-1, self.dim).astype(np.float32),
            bias=float(self.ys / self.n - beta @ mean),
            window_step=self.window_step,
        )


def normal_equations(
    windows: Iterable[np.ndarray], targets: Iterable[np.ndarray], window_step: int = WINDOW_STEP
) -> NormalEquations:
    """Sums for regressing ``targets`` (per video ``(T,)`` standardised openings; NaN frames are left out) on
    their feature ``windows`` (per video ``(T, W, D)``), accumulated video by video, so the corpus need not
    be in memory."""
    xtx = xty = xs = None
    n, ys, dim = 0, 0.0, 0
    for w, y in zip(windows, targets, strict=True):
        keep = np.isfinite(y)
        x = np.asarray(w, np.float64)[keep][:, ::window_step]
        dim = x.shape[2]
        x = x.reshape(len(x), -1)
        t = np.asarray(y, np.float64)[keep]
        if xtx is None:
            xtx, xty, xs = np.zeros((x.shape[1],) * 2), np.zeros(x.shape[1]), np.zeros(x.shape[1])
        xtx += x.T @ x
        xty += x.T @ t
        xs += x.sum(0)
        n, ys = n + len(t), ys + t.sum()
    if xtx is None or n < 2:
        raise ValueError("no frames to fit an opening model on")
    return NormalEquations(xtx, xty, xs, ys, n, dim, window_step)


def fit_opening_model(
    windows: Iterable[np.ndarray], targets: Iterable[np.ndarray], ridge: float, window_step: int = WINDOW_STEP
) -> OpeningModel:
    """Ridge regression of ``targets`` on ``windows`` (see :func:`normal_equations`) with inputs
    standardised over all frames and ``ridge`` in units of frames."""
    return normal_equations(windows, targets, window_step).solve(ridge)
