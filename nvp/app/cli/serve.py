"""``nvp serve``: the local web app and JSON API."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser("serve", help="a local web app and JSON API: fit people and dub them in a browser")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")
    p.add_argument("--port", type=int, default=7860, help="port")
    p.add_argument(
        "--data", type=Path, default=Path("nvp-data"), help="folder for people, uploads, dubs, jobs"
    )
    p.add_argument("--max-upload-mb", type=float, default=1024, help="largest upload accepted")
    p.add_argument(
        "--cluster",
        metavar="HEAD",
        help="run the jobs on this nvp cluster's workers (HOST[:PORT]; default $NVP_CLUSTER; they must see "
        "--data at the same path); needs the cluster extra",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from nvp.app.cluster import head_address
    from nvp.app.serve import serve

    serve(Path(args.data), args.host, args.port, args.max_upload_mb, cluster=head_address(args.cluster))
    return 0
