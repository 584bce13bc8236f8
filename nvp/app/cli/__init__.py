"""The one nvp command line: ``main`` and the parser; one module per command (or small group).

Each command module has ``add_parser(sub)`` (its options; defaults from the config dataclasses) and the
handler it sets as ``func``, which calls into the application modules. Building the parser is light (no
torch, mediapipe, PyAV or OpenCV): heavy modules are imported inside the handler that needs them.
"""

from __future__ import annotations

import argparse
import logging
import sys

from nvp import __version__
from nvp.app.cli import (
    cluster,
    demo,
    dub,
    evaluate,
    fit,
    info,
    live,
    person_map,
    predict,
    render,
    say,
    serve,
    track,
    train,
)

COMMANDS = (
    track.add_parser,
    train.add_train_audio2exp,
    train.add_train_opening,
    train.add_pretrain_renderer,
    person_map.add_parser,
    predict.add_parser,
    train.add_train_renderer,
    render.add_parser,
    fit.add_parser,
    dub.add_parser,
    say.add_parser,
    live.add_parser,
    serve.add_parser,
    cluster.add_parser,
    info.add_info,
    info.add_verify,
    evaluate.add_parser,
    demo.add_parser,
)
"""Each command's ``add_parser``, in the order ``nvp --help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    """The parser; option defaults come from the config dataclasses (light modules: no torch)."""
    ap = argparse.ArgumentParser(
        prog="nvp", description="Neural Voice Puppetry: audio-driven facial reenactment."
    )
    ap.add_argument("--version", action="version", version=f"nvp {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="log details")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = ap.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )
    from nvp.allocator import keep_freed_memory
    from nvp.errors import NvpError
    from nvp.threads import fix_openmp_threads

    keep_freed_memory()
    fix_openmp_threads()  # before anything imports PyTorch
    try:
        return args.func(args)
    except NvpError as e:
        return _fail(args.command, f"error: {e}", 2)
    except KeyboardInterrupt:
        return _fail(args.command, "interrupted", 130)
    except OSError as e:  # permissions, a vanished file, a full disk outside nvp's own writers, ...
        from nvp.artifact import is_disk_full

        where = e.filename or "a file"
        what = f"disk full while writing {where}" if is_disk_full(e) else f"{e.strerror or e}: {where}"
        return _fail(args.command, f"error: {what}", 2)


def _fail(command: str, message: str, code: int) -> int:
    """Print the one error line on a line of its own (closing any progress bar first)."""
    tqdm = sys.modules.get("tqdm")
    if tqdm is not None:
        for bar in list(getattr(tqdm.tqdm, "_instances", ())):
            bar.close()
    print(f"nvp {command}: {message}", file=sys.stderr)
    return code
