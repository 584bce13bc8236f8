"""Catching a renderer training that diverges (``RendererTrainConfig.diverge_ratio``).

A batch unlike the rest can push the networks where their sigmoid output saturates: the gradient vanishes
and the loss stays about ten times above where it was, for good (pre-training the generic renderer on 31
videos did so at step 2,000, deterministically; docs/training.md). Gradient clipping makes it rarer; this
guard catches what remains: the loss is averaged over blocks of :data:`BLOCK` steps, a block far above the
best one (or not finite) means the training diverged, and it goes back to the state it kept at the last
healthy block, with half the learning rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

BLOCK = 50
"""Steps whose mean loss is judged at once: one batch's loss varies up to 8× between videos, a block's
mean does not."""


@dataclass
class DivergenceGuard:
    """The best block mean so far and the rollbacks made (both saved with a checkpoint)."""

    ratio: float
    """A block mean more than this many times the best one is a divergence."""
    best: float = math.inf
    rollbacks: list[dict] = field(default_factory=list)
    """One ``{"step", "loss", "best", "back_to"}`` per divergence caught (``loss``: the block's mean)."""

    def diverged(self, block_mean: float) -> bool:
        """Whether the block that ends now diverged; a healthy block can lower the best."""
        if not math.isfinite(block_mean) or block_mean > self.ratio * self.best:
            return True
        self.best = min(self.best, block_mean)
        return False

    @property
    def lr_scale(self) -> float:
        """The learning rate's factor: halved by every rollback."""
        return 0.5 ** len(self.rollbacks)

    def state(self) -> dict:
        return {"best": self.best, "rollbacks": self.rollbacks}

    @classmethod
    def from_state(cls, ratio: float, state: dict | None) -> DivergenceGuard:
        return cls(ratio, **(state or {}))
