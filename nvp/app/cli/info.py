"""``nvp info`` (a person bundle's summary) and ``nvp verify`` (a video's synthetic-media mark)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_info(sub) -> None:
    p = sub.add_parser("info", help="summarise a person bundle")
    p.add_argument("person", type=Path, help="person bundle folder")
    p.set_defaults(func=run_info)


def run_info(args: argparse.Namespace) -> int:
    from nvp.bundle import PersonBundle
    from nvp.person import PersonStyle

    b = PersonBundle.load(args.person, verify=False)
    checked = b.check()  # every file the bundle lists, at the size and sha256 the fit wrote
    m = b.manifest
    t = m["target"]
    print(f"person bundle {b.root} (format {m['format']} v{m['version']}, made by nvp {m['nvp_version']})")
    print(
        f"  target: {Path(t['source']).name}, {t['width']}x{t['height']}, {t['fps']:.3f} fps, "
        f"{t['frames']} frames ({t['duration_s']:.1f} s)"
    )
    print(f"  speech features: {m['feature_kind']}; renderer preset: {m['preset']}")
    style = PersonStyle.load(b.path("style"))
    opening = style.info.get("opening", "none (fitted before nvp's opening model)")
    opening = "calibrated" if style.opening else opening
    print(f"  talking style: rest mouth from {style.info.get('rest', '?')}; mouth-opening model: {opening}")
    for name, facts in m["stages"].items():
        extra = ", ".join(f"{k} {v}" for k, v in facts.items() if k != "seconds")
        print(f"  {name}: {facts.get('seconds', 0):.1f} s" + (f" ({extra})" if extra else ""))
    print(f"  files: {checked} checked, each at the size and sha256 the fit wrote")
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
