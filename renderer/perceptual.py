"""Optional VGG-16 perceptual loss from a weights file the user supplies (nothing is downloaded).

The network is VGG-16's convolutional trunk up to relu3_3, built here; it loads a state dict in
torchvision's layout (``features.<i>.weight`` / ``.bias``, e.g. the ImageNet ``vgg16-397923af.pth``).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from nvp.errors import FormatError

_LAYERS = [64, 64, "M", 128, 128, "M", 256, 256, 256]  # up to relu3_3
_TAPS = (3, 8, 15)  # indices in the Sequential after relu1_2, relu2_2, relu3_3
_MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
_STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


class VGGPerceptual(nn.Module):
    """L1 distance between VGG-16 features (relu1_2, relu2_2, relu3_3) of two images ``(B, 3, H, W)``
    in [0, 1]. Frozen."""

    def __init__(self, weights: str | Path) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = 3
        for v in _LAYERS:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(c, int(v), 3, padding=1), nn.ReLU(inplace=False)]
                c = int(v)
        self.features = nn.Sequential(*layers)
        try:
            state = torch.load(weights, map_location="cpu", weights_only=True)
            mine = {k: v for k, v in state.items() if k.startswith("features.") and k in self.state_dict()}
            self.load_state_dict(mine, strict=True)
        except (
            OSError,
            RuntimeError,
            KeyError,
            AttributeError,
            ValueError,
            EOFError,
            pickle.UnpicklingError,
        ) as e:
            raise FormatError(
                f"cannot use {weights} as VGG-16 weights (torchvision layout expected): {e}"
            ) from e
        self.requires_grad_(False).eval()

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        x = torch.cat([a, b]).sub(_MEAN.to(a)).div(_STD.to(a))
        loss = a.new_zeros(())
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAPS:
                fa, fb = x.chunk(2)
                loss = loss + F.l1_loss(fa, fb)
            if i >= _TAPS[-1]:
                break
        return loss
