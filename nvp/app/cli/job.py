"""One background job's process: nvp's command line run for ``nvp serve``'s worker or a cluster worker.

    python -m nvp.app.cli.job serve <job id> <nvp arguments>       (the id names the process, see
                                                                    nvp.app.jobs: a restarted server
                                                                    finds its leftover jobs by it)
    python -m nvp.app.cli.job cluster <worker pid> <nvp arguments> (stopped when that worker is gone)

Nothing imports this module: it is the entry point that joins the roof's job runners (:mod:`nvp.app.jobs`,
:mod:`nvp.app.cluster`) to the CLI without either importing the CLI, which imports them.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable

MODULE = "nvp.app.cli.job"
"""This module's name, as job runners put it on a job's command line."""


def run_command(argv: list[str], main: Callable[[list[str]], int] | None = None) -> int:
    """A job's process: nvp's CLI (``main``), with SIGTERM turned into the interrupt the CLI cleans up
    after (temporary files, writers); a second SIGTERM during that clean-up is ignored."""

    def interrupt(signum, frame) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
    if main is None:
        from nvp.app.cli import main
    return main(argv)


def stop_without(parent: int) -> None:
    """Stop this process as on Ctrl-C (SIGTERM: its clean-up runs) once ``parent`` is gone, so a job never
    outlives the worker that started it."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) >= 2 and argv[0] == "serve":
        return run_command(argv[2:])
    if len(argv) >= 2 and argv[0] == "cluster" and argv[1].isdigit():
        stop_without(int(argv[1]))
        return run_command(argv[2:])
    print(f"usage: python -m {MODULE} serve <job id> | cluster <worker pid> <nvp arguments>", file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
