"""Renderer presets: crop resolution, network size and default training length."""

from __future__ import annotations

from dataclasses import dataclass

from nvp.errors import NvpError


@dataclass(frozen=True)
class Preset:
    """Resolution and network size of a renderer, plus its default training length."""

    name: str
    crop: int
    """Side in pixels of the face crop the networks render (divisible by 16)."""
    base: int
    """U-Net base feature channels."""
    dilated: bool
    """Dilated stride-1 U-Nets (the paper; GPU) instead of strided ones (CPU)."""
    texture_size: int
    """Neural texture resolution (16 channels)."""
    steps: int
    """Default training steps: what a person's renderer trains without ``--steps`` or ``--budget-minutes``
    (on a CPU at most :attr:`minutes`: on the 2-core machine nvp is measured on, the minutes end first)."""
    batch: int
    """Crops per training step."""
    region_grow: float = 0.015
    """The face region that is blanked in the background input and re-rendered: the mesh grown by this
    fraction of the crop side (see :func:`face_region`). The band around the mesh is painted by the
    compositing network from the surrounding footage and loses detail there (collar and tie under the
    chin), so it is kept narrow: held-out crop PSNR on dfrf__cnn2 after 10 minutes of training 29.2 dB
    with 0.06, 31.9 with 0.03, 34.3 with 0.015. A dub blanks the union of the footage's and the new
    geometry's regions, so the footage's own chin is covered wherever the tracked mesh fits it."""
    minutes: float | None = None
    """Longest default training on a CPU (``nvp fit`` without ``--steps`` or ``--budget-minutes`` stops after
    ``steps`` or this long, whichever comes first: a slower machine still ends); None: ``steps`` only (a GPU
    preset)."""
    varied_minutes: float | None = None
    """:attr:`minutes` for footage that shows the face in several lights (several takes or sessions:
    :data:`renderer.train_data.VARIED_LIGHT_SHARE`), which the networks take longer to learn; None: the
    same as :attr:`minutes`."""
    step_seconds: float | None = None
    """Rough seconds per training step on the 2-core CPU nvp is measured on (the time a fit expects, printed
    at its start; ``python -m scripts.bench.renderer``); None: not measured."""
    source_input: bool = False
    """Give the face network the footage's own pixels moved onto the rendered surface (see
    :func:`renderer.inputs.moved_source`): in a dub the footage frame already shows this person's lower face
    with all its detail, only in the old shape, so the network corrects and fills in (the mouth interior)
    instead of repainting skin from the neural texture. Trained with a different frame as the source.
    Off in the shipped presets until it is measured against them (training is about 25 % slower)."""


PRESETS = {
    "cpu": Preset(
        "cpu",
        crop=192,
        base=16,
        dilated=False,
        texture_size=256,
        steps=8000,
        batch=2,
        minutes=5,
        varied_minutes=15,
        step_seconds=0.15,
    ),
    "quality": Preset(
        "quality", crop=256, base=32, dilated=False, texture_size=256, steps=12000, batch=4, minutes=45
    ),
    "paper": Preset("paper", crop=256, base=32, dilated=True, texture_size=256, steps=50000, batch=1),
}


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise NvpError(f"unknown renderer preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]
