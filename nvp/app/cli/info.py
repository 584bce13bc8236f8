"""``nvp info`` (a person bundle's summary) and ``nvp verify`` (a video's synthetic-media mark)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_info(sub) -> None:
    p = sub.add_parser("info", help="summarise a person bundle")
    p.add_argument("person", type=Path, help="person bundle folder")
    p.set_defaults(func=run_info)


def run_info(args: argparse.Namespace) -> int:
    from nvp.app.info import bundle_summary

    for line in bundle_summary(args.person):
        print(line)
    return 0


def add_verify(sub) -> None:
    p = sub.add_parser(
        "verify", help="check whether a video carries nvp's synthetic-media mark (exit 0 = yes)"
    )
    p.add_argument("video", type=Path, help="video file")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=run_verify)


def run_verify(args: argparse.Namespace) -> int:
    import json

    from nvp.provenance import verify

    r = verify(args.video)
    if args.json:
        print(json.dumps({"path": r.path, "synthetic": r.marked, "tags": r.tags}))
    elif r.marked:
        made = f"nvp {r.tags.get('nvp_version', '?')} ({r.tags.get('nvp_kind', '?')})"
        print(f"{r.path}: SYNTHETIC — made by {made}")
    else:
        print(f"{r.path}: no nvp synthetic-media mark")
    return 0 if r.marked else 1
