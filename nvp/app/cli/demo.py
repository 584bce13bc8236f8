"""``nvp demo``: a talking person from a photo that ships with nvp, fitted and dubbed."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="make a talking person from a photo that ships with nvp, fit and dub it")
    p.add_argument("-o", "--output", type=Path, default=Path("nvp-demo"), help="output directory")
    p.add_argument(
        "--budget-minutes", type=float, default=8.0, help="renderer training time for the demo person"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.app.demo import run_demo

    result = run_demo(Path(args.output), progress=not args.quiet, budget_minutes=args.budget_minutes)
    print(result)
    return 0
