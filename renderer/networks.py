"""Deferred neural rendering modules: the neural texture and the U-Nets (thin ``nn.Module``s).

Thies et al. 2019/2020: a learned 16-channel texture is sampled by the rasterized UVs; a U-Net turns the
sampled features into the face interior; a second U-Net of the same structure takes that render and the
background (6 channels) and outputs the final image, inpainting the seam.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from nvp.artifact import load_artifact, save_artifact
from nvp.errors import FormatError
from renderer import masks
from renderer.preset import Preset

FORMAT_VERSION = 6  # 2: the interior render is kept inside the mesh; 3: opaque inside the region;
# 4: the preset records its region_grow (version 3 files were all trained with 0.06 and still load);
# 5: the compositing network is given the blanked region (versions 3 and 4 load without it);
# 6: the face network may take the footage's moved pixels (Preset.source_input; 3-5 load without them)


class NeuralTexture(nn.Module):
    """``C × N × N`` learned features, sampled bilinearly by UV.

    UVs follow the face model (u right, v down, both in [0, 1]); pixels outside the mesh get zeros.
    """

    def __init__(self, channels: int = 16, size: int = 256) -> None:
        super().__init__()
        self.texture = nn.Parameter(torch.zeros(1, channels, size, size))

    def forward(self, uv: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``(B, C, H, W)`` features for ``uv`` ``(B, H, W, 2)`` and ``mask`` ``(B, 1, H, W)``."""
        grid = uv * 2 - 1
        tex = self.texture.expand(uv.shape[0], -1, -1, -1)
        return F.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=False) * mask


@dataclass(frozen=True)
class UNetConfig:
    """Structure of a U-Net (both networks of a preset share it)."""

    base: int = 32
    """Feature channels of the first level; doubled per level up to 8×."""
    depth: int = 5
    """Number of levels."""
    dilated: bool = False
    """True: stride-1 convolutions with dilation doubling per level (the paper, needs a GPU); False:
    stride-2 downsampling and bilinear upsampling (the CPU presets)."""


def _level_channels(cfg: UNetConfig) -> list[int]:
    return [cfg.base * min(2**i, 8) for i in range(cfg.depth)]


class UNet(nn.Module):
    """U-Net of ``depth`` levels with skip connections, 3×3 convolutions and leaky ReLU 0.2.

    ``(B, in_ch, H, W) → (B, out_ch, H, W)`` in [0, 1] (sigmoid). For the strided variant ``H`` and ``W``
    must be divisible by ``2 ** (depth - 1)``.
    """

    def __init__(self, in_ch: int, out_ch: int, cfg: UNetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        ch = _level_channels(cfg)
        act = nn.LeakyReLU(0.2, inplace=True)
        self.down = nn.ModuleList()
        c_prev = in_ch
        for i, c in enumerate(ch):
            if cfg.dilated:
                d = 2**i
                conv = nn.Conv2d(c_prev, c, 3, padding=d, dilation=d)
            else:
                conv = nn.Conv2d(c_prev, c, 3, stride=1 if i == 0 else 2, padding=1)
            self.down.append(nn.Sequential(conv, act))
            c_prev = c
        self.up = nn.ModuleList()
        for i in range(cfg.depth - 2, -1, -1):
            d = 2**i if cfg.dilated else 1
            self.up.append(nn.Sequential(nn.Conv2d(c_prev + ch[i], ch[i], 3, padding=d, dilation=d), act))
            c_prev = ch[i]
        self.out = nn.Conv2d(c_prev, out_ch, 3, padding=1)
        # channels-last (NHWC) weights and activations: oneDNN's CPU convolutions run faster on them
        # (measured on this 2-core machine: cpu-preset inference 1.2-1.4x, training 1.1x; same results)
        self.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.contiguous(memory_format=torch.channels_last)
        skips = []
        for layer in self.down:
            x = layer(x)
            skips.append(x)
        skips.pop()
        for layer in self.up:
            skip = skips.pop()
            if x.shape[-2:] != skip.shape[-2:]:
                x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = layer(torch.cat([x, skip], 1))
        return torch.sigmoid(self.out(x))


class NeuralRenderer(nn.Module):
    """Texture + interior U-Net + compositing U-Net.

    Inputs per crop: ``uv`` ``(B, H, W, 2)``, ``mask`` ``(B, 1, H, W)`` (face mesh coverage), ``mouth``
    ``(B, 1, H, W)`` (mouth-interior triangles, so the network knows where teeth and tongue go),
    ``background`` ``(B, 3, H, W)`` (the frame with the face region blanked) and ``region`` ``(B, 1, H, W)``
    (that blanked region). Returns the interior render and the final image, both ``(B, 3, H, W)`` in
    [0, 1].

    ``region_input``: the compositing network is also given ``region``, so it can tell blanked pixels
    from dark footage (a black suit) and knows where to paint when the region is wider than the mesh (a
    dub covers the footage's own chin as well). Renderers of format 4 and older were trained without it.

    ``source_input``: the face network also takes ``source`` ``(B, 4, H, W)``: a footage frame's pixels
    moved onto the rendered surface and their validity (:func:`renderer.inputs.moved_source`); it outputs
    colour plus a per-pixel weight of the moved pixels, so it can keep them exactly where they are right
    and paint where they are missing or wrong (the mouth interior, disocclusions).

    ``texture`` (forward): another person's texture to sample instead of the renderer's own (training on
    many people shares the networks, each person has a texture).
    """

    def __init__(
        self,
        unet: UNetConfig,
        texture_channels: int = 16,
        texture_size: int = 256,
        region_input: bool = True,
        source_input: bool = False,
    ) -> None:
        super().__init__()
        self.region_input, self.source_input = region_input, source_input
        self.texture = NeuralTexture(texture_channels, texture_size)
        self.interior = UNet(texture_channels + 2 + 4 * source_input, 3 + source_input, unet)
        self.composite = UNet(7 + int(region_input), 4, unet)
        with torch.no_grad():  # start by passing the background through (opacity ~0.02); learn where to paint
            self.composite.out.bias[3] = -4.0

    def forward(
        self,
        uv: torch.Tensor,
        mask: torch.Tensor,
        mouth: torch.Tensor,
        background: torch.Tensor,
        region: torch.Tensor,
        source: torch.Tensor | None = None,
        texture: NeuralTexture | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        interior = self.face(uv, mask, mouth, source, texture)
        extra = [region] if self.region_input else []
        out = self.composite(torch.cat([interior, background, mask, *extra], 1))
        # the second network paints the seam: the ring between the mesh and the untouched footage, as RGB
        # plus an opacity, so pixels it leaves alone keep the footage exactly (no blur, no drift). Well
        # inside the mesh the interior render is kept as is: a second pass through a small U-Net only
        # blurs it (measured: the composite was visibly softer than the interior render it was given).
        # Inside the blanked region the opacity is 1, so the blank (black) never shows through.
        alpha = torch.maximum(out[:, 3:], region)
        seam = alpha * out[:, :3] + (1 - alpha) * background
        keep = inner_weight(mask)
        return interior, keep * interior + (1 - keep) * seam

    def face(
        self,
        uv: torch.Tensor,
        mask: torch.Tensor,
        mouth: torch.Tensor,
        source: torch.Tensor | None = None,
        texture: NeuralTexture | None = None,
    ) -> torch.Tensor:
        """The first network's render of the mesh alone, ``(B, 3, H, W)`` (0 off it; arguments as
        :meth:`forward`): what the final image keeps as it is well inside the mesh (:func:`inner_weight`)."""
        feats = (texture or self.texture)(uv, mask)
        if not self.source_input:
            return self.interior(torch.cat([feats, mask, mouth], 1)) * mask
        if source is None:
            raise ValueError("this renderer needs the moved source pixels (source_input)")
        out = self.interior(torch.cat([feats, mask, mouth, source], 1))
        w = out[:, 3:] * source[:, 3:]
        return (w * source[:, :3] + (1 - w) * out[:, :3]) * mask


def inner_weight(mask: torch.Tensor, erode: float = 0.015) -> torch.Tensor:
    """Blend weight ``(B, 1, H, W)`` of the interior render in the final image: 0 on the mesh's
    silhouette, rising to 1 over ``2 · erode`` of the crop side inside it, so the silhouette, which never
    matches the real face contour exactly, is left to the compositing network."""
    r = max(1, round(erode * int(mask.shape[-1])))
    return masks.box_blur(masks.erode(mask, r + 1), r)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def make_renderer(preset: Preset, region_input: bool = True) -> NeuralRenderer:
    """A fresh renderer of ``preset``'s size (``region_input`` False only for format 4 and older)."""
    return NeuralRenderer(
        UNetConfig(base=preset.base, dilated=preset.dilated),
        texture_size=preset.texture_size,
        region_input=region_input,
        source_input=preset.source_input,
    )


def save_renderer(net: NeuralRenderer, out_dir: Path, preset: Preset, info: dict, half: bool = False) -> Path:
    """Write ``renderer.npz`` (weights) and ``renderer.json`` (format, preset, provenance) atomically.

    ``half``: store the weights as float16, compressed (a shipped starting point; loads as float32)."""
    arrays = {k: v.detach().cpu().numpy() for k, v in net.state_dict().items()}
    if half:
        arrays = {k: v.astype(np.float16) for k, v in arrays.items()}
    return save_artifact(
        Path(out_dir) / "renderer",
        "renderer",
        FORMAT_VERSION,
        arrays,
        {"preset": asdict(preset), **info},
        compress=half,
    )


def load_renderer(out_dir: Path, device: str = "cpu") -> tuple[NeuralRenderer, Preset, dict]:
    """A saved renderer in eval mode on ``device``, its preset and its manifest."""
    art = load_artifact(Path(out_dir) / "renderer.json", "renderer", (3, 4, 5, FORMAT_VERSION))
    m = art.manifest
    try:
        preset = Preset(**{"region_grow": 0.06, "source_input": False, **m["preset"]})
        net = make_renderer(preset, region_input=m["version"] >= 5)
        net.load_state_dict({k: torch.from_numpy(v.astype(np.float32)) for k, v in art.arrays.items()})
    except (TypeError, KeyError, RuntimeError) as e:
        raise FormatError(f"cannot load renderer from {out_dir}: {e}") from e
    return net.to(device).eval(), preset, m


GENERIC_DIR = Path(__file__).parent / "assets"
"""Shipped generic renderers (``generic_<preset>/renderer.{json,npz}``): networks pre-trained on many
people and their mean texture, the starting point of a person's renderer training."""


def generic_renderer_dir(preset: Preset) -> Path | None:
    """The shipped generic renderer trained for ``preset`` (same crop, networks and texture), or None."""
    folder = GENERIC_DIR / f"generic_{preset.name}"
    if not (folder / "renderer.json").exists():
        return None
    saved = json.loads((folder / "renderer.json").read_text())["preset"]
    return folder if same_structure(Preset(**saved), preset) else None


def same_structure(a: Preset, b: Preset) -> bool:
    """Whether renderers of presets ``a`` and ``b`` have the same weights and inputs (a training of one can
    start from the other's weights)."""
    keys = ("crop", "base", "dilated", "texture_size", "region_grow", "source_input")
    return all(getattr(a, k) == getattr(b, k) for k in keys)


def fast_bf16(device: str) -> bool:
    """Whether the networks should run in bfloat16 (autocast; weights stay float32) on ``device``: on a CPU
    that computes it natively (AVX512-BF16 or AMX). Measured on a 2-core AMD EPYC with the ``cpu`` preset:
    rendering a 144×192 window 32.5 → 18.8 ms, output within 1/255 of float32 (mean 0.2/255).
    ``NVP_PRECISION=fp32`` keeps float32; elsewhere (CPUs without it, GPUs) it is float32. Training stays
    float32: in bfloat16 a step took 0.17 s instead of 0.27-0.30, but 15 minutes of fine-tuning on
    dfrf__cnn2 (5,046 steps instead of 3,572) gave the same held-out mouth box (29.96 vs 30.06 dB)."""
    if os.environ.get("NVP_PRECISION", "").lower() == "fp32" or not device.startswith("cpu"):
        return False
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # torch.cpu's own feature checks
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)
