"""A renderer training that ends when the networks stop improving (``RendererTrainConfig.stop_on_plateau``).

The learning rate stays at its start while a loss on held-out stretches of the footage is measured at every
checkpoint; once that loss has stopped falling (:func:`plateaued`), or when the run's steps or time budget
would otherwise run out, the rate falls along a half cosine to its floor over a last part of the run
(warmup-free "stable, then decay"): the footage of one steady shot can end in a few minutes, varied footage
trains for as long as it keeps learning.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np


def held_out_blocks(
    frames: np.ndarray, wanted: int, blocks: int = 4, reach: int = 20
) -> tuple[np.ndarray, np.ndarray]:
    """The cache rows a plateau is judged on and the rows the training leaves out for it.

    ``frames``: the cache's frame indices (increasing). ``blocks`` stretches spread evenly over the footage
    are left out, each the rows within ``reach`` frames of its centre (0.8 s at 25 fps); the ``wanted``
    measured rows are the ones nearest the centres. Neighbouring frames of a video are near copies, so a
    held-out frame between trained ones measures how well the footage is remembered, which improves for as
    long as the training runs; a frame most of a second away from any trained one measures how well the
    networks render a face they have not seen, as a dub asks of them. At most one row in eight is left out
    (fewer blocks, or none). Returns ``(measured, left_out)`` row indices."""
    frames = np.asarray(frames)
    none = np.zeros(0, int)
    if len(frames) == 0:
        return none, none
    for k in range(min(blocks, wanted), 0, -1):
        quantiles = frames[0] + (np.arange(k) + 0.5) / k * (frames[-1] - frames[0])
        centres = frames[np.abs(frames[:, None] - quantiles[None]).argmin(0)]  # frames of the footage
        distance = np.abs(frames[:, None] - centres[None])  # (rows, blocks)
        left_out = np.flatnonzero((distance <= reach).any(1))
        if len(left_out) <= len(frames) // 8:
            per = -(-wanted // k)
            measured = [np.argsort(d, kind="stable")[: min(per, int((d <= reach).sum()))] for d in distance.T]
            return np.unique(np.concatenate(measured)), left_out
    return none, none


def plateaued(history: list[tuple[int, float]], window: int, gain: float) -> bool:
    """Whether the held-out loss ``history`` (``(step, loss)`` in step order) has stopped falling: its best
    over the last ``window`` steps is less than ``gain`` (a fraction) below its best before them. Noise at
    a constant learning rate moves single values; the best of each span does not move back."""
    if not history:
        return False
    last = history[-1][0]
    before = [loss for step, loss in history if step <= last - window]
    recent = [loss for step, loss in history if step > last - window]
    if not before or not recent:
        return False
    return min(before) - min(recent) < gain * min(before)


@dataclass
class PlateauSchedule:
    """Where a plateau-ended run is on its learning rate's curve, and where the run ends.

    ``decay_from``: the step the decay started at (None: still at the constant rate); ``decay_steps``: its
    length; ``decay_t0``: training seconds at its start; ``history``: the held-out losses so far.
    """

    decay_fraction: float
    decay_from: int | None = None
    decay_steps: int = 0
    decay_t0: float = 0.0
    reason: str = ""
    history: list[tuple[int, float]] = field(default_factory=list)

    def start_decay(self, step: int, elapsed: float, reason: str, steps_left: int) -> None:
        """Begin the decay at ``step``: over ``decay_fraction`` of the steps trained so far, or over
        ``steps_left`` when the run's own limit is nearer."""
        self.decay_from, self.decay_t0, self.reason = step, elapsed, reason
        self.decay_steps = max(1, min(round(self.decay_fraction * step), steps_left))

    def must_decay(self, step: int, elapsed: float, steps: int, budget_s: float | None) -> bool:
        """Whether the run's limit is so near that the decay has to start now to fit in it."""
        share = 1 / (1 + self.decay_fraction)
        return step >= steps * share or (budget_s is not None and elapsed >= budget_s * share)

    def end(self, steps: int) -> int:
        """The step the run ends at: ``steps`` until the decay starts."""
        return steps if self.decay_from is None else self.decay_from + self.decay_steps

    def progress(self, step: int, elapsed: float, budget_s: float | None) -> float:
        """Where ``step`` is on the learning rate's half cosine (``renderer.train.learning_rate``): 0 until
        the decay starts, then up to 1 by the decay's last step or by the time budget, whichever is first."""
        if self.decay_from is None:
            return 0.0
        p = (step - self.decay_from) / self.decay_steps
        if budget_s is not None and budget_s > self.decay_t0:
            p = max(p, (elapsed - self.decay_t0) / (budget_s - self.decay_t0))
        return p

    def state(self) -> dict:
        return asdict(self)

    @classmethod
    def from_state(cls, state: dict) -> PlateauSchedule:
        s = cls(**state)
        s.history = [(int(a), float(b)) for a, b in s.history]
        return s
