"""Patch-adversarial term for renderer training: a small critic that tells real skin, lips and teeth from
rendered ones, patch by patch, inside the face.

L1 and SSIM make the networks predict the average of what the inputs allow, and the average of many
stubble patterns or teeth positions is a smooth blur; a critic that sees local texture rewards the renderer
for producing texture with the footage's statistics instead (pix2pix's PatchGAN idea, here with a least-
squares objective). Only used during training; the critic is never saved with the renderer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class PatchCritic(nn.Module):
    """``(B, 3, S, S)`` images in [0, 1] → ``(B, 1, S/8, S/8)`` realness scores of overlapping patches
    (receptive field about 30 pixels of the crop)."""

    def __init__(self, base: int = 16) -> None:
        super().__init__()
        chans = [3, base, 2 * base, 4 * base]
        layers: list[nn.Module] = []
        for a, b in zip(chans[:-1], chans[1:], strict=True):
            layers += [nn.Conv2d(a, b, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        layers.append(nn.Conv2d(chans[-1], 1, 3, padding=1))
        self.net = nn.Sequential(*layers)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.net(image * 2 - 1)


def patch_weights(mask: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``(B, 1, h, w)`` share of each critic patch covered by ``mask`` ``(B, 1, S, S)`` (the rendered face):
    only patches on the face count, so the critic judges skin, lips and teeth, not the background."""
    return F.adaptive_avg_pool2d(mask, size)


def _weighted_mean(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return (x * w).sum() / w.sum().clamp_min(1e-6)


def critic_loss(
    critic: PatchCritic, real: torch.Tensor, fake: torch.Tensor, mask: torch.Tensor
) -> torch.Tensor:
    """Least-squares critic objective: real patches towards 1, rendered ones towards 0 (``fake`` is
    detached: this trains the critic only)."""
    r, f = critic(real), critic(fake.detach())
    w = patch_weights(mask, r.shape[-2:])
    return _weighted_mean((r - 1) ** 2, w) + _weighted_mean(f**2, w)


def generator_loss(critic: PatchCritic, fake: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Least-squares objective of the renderer: its patches should score as real (1)."""
    f = critic(fake)
    return _weighted_mean((f - 1) ** 2, patch_weights(mask, f.shape[-2:]))
