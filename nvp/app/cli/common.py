"""Options and helpers shared by several commands (light: no torch until a command runs)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def add_device_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device",
        default="auto",
        help="torch device: auto (cuda when a GPU is available, else cpu), cpu, cuda, cuda:1, ...",
    )


def add_style_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--style",
        type=Path,
        help="talk in another person's style: their bundle folder or person-map .json (default: their own)",
    )


def add_gaze_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--gaze",
        default="footage",
        metavar="footage|camera|FILE",
        help="where the eyes look: footage (as in the person's footage, the default), camera (into the "
        "lens: eye contact) or a CSV / JSON file of time_s, yaw_deg, pitch_deg rows (see docs/commands.md)",
    )


def add_renderer_training_args(p: argparse.ArgumentParser, budget_minutes: float | None = None) -> None:
    """The renderer-training options shared by train-renderer, fit and eval."""
    from nvp.app.fit import FitConfig

    add_preset_arg(p)
    p.add_argument("--steps", type=int, help="renderer training steps (default: the preset's)")
    p.add_argument(
        "--budget-minutes",
        type=float,
        default=budget_minutes,
        help="renderer training time (with --steps: whichever ends first)",
    )
    p.add_argument(
        "--init",
        default=FitConfig.renderer_init,
        metavar="generic|scratch|FOLDER",
        help="start renderer training from the shipped generic renderer (default), from scratch, or from "
        "a renderer folder (nvp train-renderer / pretrain-renderer output)",
    )


def renderer_training_options(args: argparse.Namespace) -> dict:
    """What :func:`add_renderer_training_args` (and ``--device``) parsed, as the keywords of ``FitConfig``
    and ``EvalConfig``."""
    return {
        "preset": args.preset,
        "budget_minutes": args.budget_minutes,
        "steps": args.steps,
        "device": device(args.device),
        "renderer_init": args.init,
    }


def add_preset_arg(p: argparse.ArgumentParser) -> None:
    from nvp.app.fit import FitConfig

    p.add_argument(
        "--preset", choices=("cpu", "quality", "paper"), default=FitConfig.preset, help="renderer preset"
    )


def add_features_arg(p: argparse.ArgumentParser) -> None:
    """The speech features of a person map (train-audio2exp, person-map, fit)."""
    from nvp.app.fit import FitConfig

    p.add_argument(
        "--features", choices=("phonemes", "mel"), default=FitConfig.features, help="speech features"
    )


def add_corpus_split_args(p: argparse.ArgumentParser) -> None:
    """Validation and left-out videos of a training corpus, and copies of the training videos' audio
    (train-audio2exp, train-opening)."""
    p.add_argument(
        "--val", nargs="*", help="file names of validation videos (default: 5 spread over the list)"
    )
    p.add_argument("--exclude", nargs="*", help="file names to leave out entirely")
    p.add_argument(
        "--augment",
        nargs="*",
        default=[],
        metavar="COPY",
        help="also train on these copies of the training videos' audio: speedF (played F times as fast, "
        "e.g. speed0.9), roomT (a room of reverberation time T s, e.g. room0.5), noiseS (white noise at S "
        "dB, e.g. noise10)",
    )


def augmentations(args: argparse.Namespace) -> tuple[str, ...]:
    """``--augment``'s names, each checked (one clear error for a bad one, before any work)."""
    from nvp.augment import parse_augmentation

    return tuple(parse_augmentation(a).name for a in args.augment)


def device(name: str) -> str:
    """The torch device for ``--device`` (``auto`` picks cuda when torch sees a GPU)."""
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def nanmedian(x) -> float:
    import numpy as np

    return float(np.nanmedian(x)) if np.isfinite(x).any() else float("nan")


def run_each(
    inputs: Sequence[T], work: Callable[[int, T], None], failure: Callable[[T, Exception], str]
) -> int:
    """``work(i, input)`` for each of ``inputs`` (dub and eval of several files); returns how many failed.
    With one input its error goes up (``main()`` prints it as the one error line); with several, each
    failure is the one line ``failure(input, error)`` on stderr and the other inputs still run."""
    from nvp.errors import NvpError

    failed = 0
    for i, item in enumerate(inputs):
        try:
            work(i, item)
        except NvpError as e:
            if len(inputs) == 1:
                raise  # main() prints it as the one error line
            print(failure(item, e), file=sys.stderr)  # the others still run
            failed += 1
    return failed
