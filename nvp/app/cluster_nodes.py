"""``nvp cluster head`` and ``nvp cluster join``: a machine becomes the cluster's head (the Dask scheduler)
or one of its workers (:mod:`nvp.app.cluster`)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys

from nvp.app.cluster import DEFAULT_PORT, distributed_module


def head_command(host: str = "0.0.0.0", port: int = DEFAULT_PORT) -> list[str]:
    """The Dask scheduler that ``nvp cluster head`` runs."""
    return [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", host, "--port", str(port),
            "--no-dashboard"]  # fmt: skip


def join_command(address: str, name: str | None = None, host: str | None = None) -> list[str]:
    """The Dask worker that ``nvp cluster join`` runs: one job at a time (a job uses every core), no
    nanny (a dead worker is replaced by joining again, not behind the scheduler's back), no memory limit
    (a fit takes what it needs)."""
    cmd = [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1", "--nworkers", "1",
           "--no-nanny", "--no-dashboard", "--memory-limit", "0"]  # fmt: skip
    if name:
        cmd += ["--name", name]
    if host:
        cmd += ["--host", host]
    return cmd


def run_head(host: str, port: int) -> int:
    """``nvp cluster head``: the Dask scheduler in the foreground (Ctrl-C stops it)."""
    distributed_module()
    print(
        f"nvp cluster: head on {host}:{port}; join a machine with: nvp cluster join "
        f"{socket.gethostname() if host in ('0.0.0.0', '::') else host}:{port}",
        file=sys.stderr,
        flush=True,
    )
    return _foreground(head_command(host, port))


def run_worker(address: str, name: str | None = None, host: str | None = None) -> int:
    """``nvp cluster join HEAD``: a Dask worker in the foreground (Ctrl-C leaves the cluster; its running
    job goes to another worker)."""
    distributed_module()
    print(f"nvp cluster: joining {address} (one job at a time; Ctrl-C leaves)", file=sys.stderr, flush=True)
    return _foreground(join_command(address, name, host))


def _foreground(cmd: list[str]) -> int:
    proc = subprocess.Popen(cmd)
    try:
        return proc.wait()
    except KeyboardInterrupt:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            return 130
