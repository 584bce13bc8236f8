"""``nvp cluster``: start a head, join a machine, run a list of nvp command lines on the cluster
(:mod:`nvp.app.cluster`; needs the ``cluster`` extra)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
    from nvp.app.cluster import DEFAULT_PORT

    p = sub.add_parser("cluster", help="run nvp's jobs on several machines (needs the cluster extra)")
    cs = p.add_subparsers(dest="cluster_command", required=True)
    h = cs.add_parser("head", help="start the cluster's head on this machine (Ctrl-C stops it)")
    h.add_argument("--host", default="0.0.0.0", help="address to listen on (default: every interface)")
    h.add_argument("--port", type=int, default=DEFAULT_PORT, help="port")
    h.set_defaults(func=run_head)
    j = cs.add_parser("join", help="make this machine a worker of the cluster at HEAD (Ctrl-C leaves)")
    j.add_argument("head", help="the head's address: HOST or HOST:PORT")
    j.add_argument("--name", help="this worker's name (default: Dask's)")
    j.add_argument("--host", help="the address other machines reach this one at (default: Dask's choice)")
    j.set_defaults(func=run_join)
    r = cs.add_parser("run", help="run a file of nvp command lines, one job each, on the cluster")
    r.add_argument("jobs", type=Path, help="a text file: one nvp command line per line (fit, dub, say, eval)")
    r.add_argument("--cluster", metavar="HEAD", help="the head's address (default: $NVP_CLUSTER)")
    r.set_defaults(func=run_jobs)


def run_head(args: argparse.Namespace) -> int:
    from nvp.app.cluster_nodes import run_head

    return run_head(args.host, args.port)


def run_join(args: argparse.Namespace) -> int:
    from nvp.app.cluster import head_address
    from nvp.app.cluster_nodes import run_worker

    return run_worker(head_address(args.head), args.name, args.host)


def run_jobs(args: argparse.Namespace) -> int:
    from nvp.app.cluster import head_address, jobs_of_file, report, run_batch
    from nvp.errors import NvpError

    address = head_address(args.cluster)
    if address is None:
        raise NvpError("give the head's address: --cluster HOST[:PORT] (or set NVP_CLUSTER)")
    jobs = jobs_of_file(args.jobs)
    outcomes = run_batch(jobs, address, progress=not args.quiet, label="nvp cluster run")
    return report(outcomes, "cluster run", "done", args.jobs)
