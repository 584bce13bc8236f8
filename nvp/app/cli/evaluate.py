"""``nvp eval``: self-reenactment of one video or several (a summary table for several)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nvp.app.cli.common import add_device_arg, add_renderer_training_args, renderer_training_options, run_each
from nvp.app.cluster import add_cluster_arg

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
    add_cluster_arg(p)
    p.set_defaults(func=run)


def _rows(r: dict) -> list[dict]:
    """The summary table's rows of one video's result (``eval.json``)."""
    return [
        {
            "video": r["video"],
            "driven by": kind,
            "test frames": r["frames"]["test"],
            "fit min": r["fit_minutes"],
            **{k: r[kind][k] for k in SUMMARY_METRICS if k in r[kind]},
        }
        for kind in ("visual", "audio")
    ]


def _on_cluster(args: argparse.Namespace, root: Path, rows: list[dict], address: str) -> int:
    """Each video's ``nvp eval`` as a job on the cluster; the summary's rows from their ``eval.json``."""
    import json

    from nvp.app.cluster import absolute, run_inputs

    options = ["--train-fraction", str(args.train_fraction), "--preset", args.preset, "--init", args.init]
    options += ["--device", args.device] + (["--side-by-side"] if args.side_by_side else [])
    for flag, value in (("--steps", args.steps), ("--budget-minutes", args.budget_minutes)):
        options += [] if value is None else [flag, str(value)]

    def argv_of(video: Path) -> list[str]:
        return ["eval", absolute(video), "-o", absolute(root / Path(video).stem), *options]

    _, outcomes = run_inputs("eval", args.video, argv_of, address, root, "evaluated", not args.quiet)
    for o in outcomes:
        if o.ok:
            rows.extend(_rows(json.loads((root / Path(o.job.name).stem / "eval.json").read_text())))
    return sum(not o.ok for o in outcomes)


def run(args: argparse.Namespace) -> int:
    from nvp.app.cluster import head_address
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
        rows.extend(_rows(r))

    if several and head_address(args.cluster):  # one job per video on the cluster's workers
        failed = _on_cluster(args, root, rows, head_address(args.cluster))
    else:
        failed = run_each(args.video, evaluate_one, lambda video, e: f"nvp eval: {video}: {e}")
    if several and rows:
        print(write_results(rows, root))
    return 2 if failed else 0
