"""``nvp eval``: self-reenactment of one video or several (a summary table for several)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import add_device_arg, add_renderer_training_args, renderer_training_options, run_each

SUMMARY_METRICS = (
    "psnr_full",
    "ssim_full",
    "psnr_crop",
    "ssim_crop",
    "mouth_landmark_error_iod",
    "closure_f1",
    "av_offset_frames",
    "mouth_jitter_ratio",
)
"""The ``nvp eval`` metrics in the summary table of a multi-video run (every number is in eval.json)."""


def add_parser(sub) -> None:
    from nvp.app.evaluate import EvalConfig

    p = sub.add_parser("eval", help="self-reenactment: fit on the first part of a video, re-create the rest")
    p.add_argument(
        "video", type=Path, nargs="+", help="talking-head videos with audio (≥ 5 s each; 1-3 min is best)"
    )
    p.add_argument(
        "-o", "--output", type=Path, help="output folder (one subfolder per video when given several)"
    )
    p.add_argument(
        "--train-fraction", type=float, default=EvalConfig.train_fraction, help="part used for fitting"
    )
    add_renderer_training_args(p, budget_minutes=EvalConfig.budget_minutes)
    p.add_argument("--side-by-side", action="store_true", help="also write real | visual | audio video")
    add_device_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.app.evaluate import EvalConfig, evaluate_video
    from nvp.app.report import write_results

    cfg = EvalConfig(
        train_fraction=args.train_fraction,
        side_by_side=args.side_by_side,
        **renderer_training_options(args),
    )
    several = len(args.video) > 1
    if args.output:
        root = Path(args.output)
    else:
        root = Path("nvp-eval") if several else Path(args.video[0]).with_suffix("") / "nvp-eval"
    rows = []

    def evaluate_one(_: int, video: Path) -> None:
        out = root / Path(video).stem if several else root
        r = evaluate_video(video, out, cfg, progress=not args.quiet)
        print((out / "eval.md").read_text())
        print(f"eval.json, eval.md, eval.png → {out} ({r['frames']['test']} held-out frames)")
        for kind in ("visual", "audio"):
            rows.append(
                {
                    "video": r["video"],
                    "driven by": kind,
                    "test frames": r["frames"]["test"],
                    "fit min": r["fit_minutes"],
                    **{k: r[kind][k] for k in SUMMARY_METRICS if k in r[kind]},
                }
            )

    failed = run_each(args.video, evaluate_one, lambda video, e: f"nvp eval: {video}: {e}")
    if several and rows:
        print(write_results(rows, root))
    return 2 if failed else 0
