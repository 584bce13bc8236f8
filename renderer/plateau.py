"""A renderer training that ends when the networks stop improving (``RendererTrainConfig.stop_on_plateau``).

The learning rate stays at its start while a held-out loss is measured at every checkpoint; once that loss
has stopped falling (:func:`plateaued`), or when the run's steps or time budget would otherwise run out, the
rate falls along a half cosine to its floor over a last part of the run (warmup-free "stable, then decay"):
the footage of one steady shot ends in a few minutes, varied footage trains for as long as it keeps learning.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np


def held_out_rows(frames: int, wanted: int) -> np.ndarray:
    """``wanted`` cache rows spread evenly over ``frames`` that the training never draws, at most one in
    eight of them (none for fewer than eight frames)."""
    k = min(wanted, frames // 8)
    return np.unique(np.linspace(0, frames - 1, k).round().astype(int)) if k > 0 else np.zeros(0, int)


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
