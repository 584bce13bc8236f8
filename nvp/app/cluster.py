"""nvp's independent jobs on several machines, through Dask distributed (the optional ``cluster`` extra).

One machine needs none of this: ``nvp dub a.wav b.wav``, ``nvp eval a.mp4 b.mp4`` and ``nvp serve`` run
their jobs themselves, as before. With a cluster, one machine runs the head (``nvp cluster head``, a Dask
scheduler) and every machine that should work joins it (``nvp cluster join HEAD``, a Dask worker that
takes one job at a time). The commands that take many inputs then send one job per input to the head
(``--cluster HEAD`` or ``$NVP_CLUSTER``), ``nvp cluster run JOBS.txt`` sends any list of nvp command
lines, and ``nvp serve --cluster HEAD`` sends the web app's jobs.

A job is the nvp command line a user would type (``dub in.wav --person p/ -o out.mp4``), run on a worker
as its own process (``python -m nvp.app.cli.job cluster <worker pid> <nvp arguments>``), exactly as the CLI
runs it: its outputs are written atomically, it resumes (fit, dub) or redoes its part (say, eval) when it
runs again, and a bad input ends its job with the command's one error line. Inputs and outputs travel
through a folder every machine sees at the same path (NFS, SMB, ...): paths are made absolute before a
job is sent.

What a worker's death does: Dask's scheduler gives the worker's running job to another worker (a job
whose workers die three times fails, ``distributed.scheduler.allowed-failures``). The job's process
watches the worker that started it and stops (as on Ctrl-C: a dub keeps its finished parts) when that
worker is gone or the job was cancelled, so a job never runs twice at once on one output. Jobs have keys
made of their command line and folder: the same job sent twice while it runs is one job.

Progress travels as Dask events (topic :data:`TOPIC`): ``start`` (which worker), ``progress`` (the
job's progress bar: stage, percent, time left), shown by the CLI's bar and ``nvp serve``'s job list.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nvp.errors import NvpError

log = logging.getLogger(__name__)

DEFAULT_PORT = 8786
"""The head's port (Dask's own default)."""
ADDRESS_ENV = "NVP_CLUSTER"
"""The head's address when ``--cluster`` is not given."""
TOPIC = "nvp-jobs"
"""The Dask event topic of job starts and progress."""
INSTALL_HINT = (
    "the cluster extra is not installed: run bash scripts/setup.sh cluster (or pip install 'nvp[cluster]')"
)
GRACE_S = 20.0
"""Seconds a job's process has to clean up after SIGTERM before it is killed."""


# -- addresses, the extra, the connection


def distributed_module():
    try:
        import distributed
    except ImportError:
        raise NvpError(INSTALL_HINT) from None
    return distributed


def head_address(value: str | None = None) -> str | None:
    """The head's address as Dask takes it (``tcp://HOST:PORT``) from ``value`` or ``$NVP_CLUSTER``
    (``HOST``, ``HOST:PORT`` or ``tcp://HOST:PORT``); None when neither is set (run here)."""
    value = (value or os.environ.get(ADDRESS_ENV) or "").strip()
    if not value:
        return None
    if "://" not in value:
        value = f"tcp://{value}"
    scheme, rest = value.split("://", 1)
    if not rest or rest.startswith(":") or "/" in rest:
        raise NvpError(
            f"a cluster head's address is HOST or HOST:PORT (tcp://HOST:{DEFAULT_PORT}); got {value}"
        )
    if not re.search(r":\d+$", rest) or rest.endswith("]"):
        rest = f"{rest}:{DEFAULT_PORT}"
    return f"{scheme}://{rest}"


def add_cluster_arg(p) -> None:
    """``--cluster HEAD`` on a command (light: imports nothing)."""
    p.add_argument(
        "--cluster",
        metavar="HEAD",
        help=f"send one job per input to this nvp cluster head (HOST[:PORT]; default ${ADDRESS_ENV}); "
        "needs the cluster extra",
    )


def connect(address: str, timeout: float = 20.0):
    """A Dask client of the head at ``address``. Raises NvpError (the extra is missing; no head there)."""
    distributed = distributed_module()
    try:
        return distributed.Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError) as e:
        raise NvpError(
            f"cannot reach the nvp cluster head at {address} ({e}); start it with nvp cluster head"
        ) from None


# -- a job: what runs on a worker


@dataclass(frozen=True)
class ClusterJob:
    """One nvp command line to run on a worker."""

    name: str
    """What messages name the job by (its input)."""
    argv: tuple[str, ...]
    """The command line after ``nvp`` (absolute paths: the folder is shared)."""
    cwd: str
    """The folder it runs in (on every machine)."""
    tag: str = ""
    """Makes the key of an otherwise identical job differ (``nvp serve``: the job id and its attempt)."""

    @property
    def key(self) -> str:
        blob = json.dumps([list(self.argv), self.cwd, self.tag]).encode()
        return f"nvp-{self.argv[0] if self.argv else 'job'}-{hashlib.sha256(blob).hexdigest()[:16]}"


@dataclass
class Outcome:
    """How one job ended."""

    job: ClusterJob
    ok: bool
    error: str = ""
    """The command's error line (or why the cluster could not run it)."""
    stdout: str = ""
    worker: str = ""
    """The worker that ran it (address) and its host and pid: ``tcp://... (host, pid N)``."""
    seconds: float = 0.0
    attempts: int = 1
    """How many workers started it (more than one when a worker died)."""


def _emit(w, kind: str, key: str, **fields) -> None:
    try:
        w.log_event(TOPIC, {"kind": kind, "key": key, **fields})
    except Exception:  # progress is best effort; the job goes on
        log.debug("cannot send a %s event", kind, exc_info=True)


def _still_wanted(worker, key: str) -> bool:
    """False once the scheduler cancelled the task or forgot it (a cancel, or its client went)."""
    try:
        ts = worker.state.tasks.get(key)
    except Exception:
        return True
    return ts is not None and ts.state not in ("cancelled", "released", "forgotten")


def run_job(argv: Sequence[str], cwd: str) -> dict[str, Any]:
    """Runs on a Dask worker: ``nvp <argv>`` in ``cwd`` as its own process, its progress sent as events.
    Returns ``{"code", "error", "stdout", "worker", "seconds"}``; a job whose task is cancelled (or whose
    client went away) is stopped."""
    from distributed import get_worker
    from distributed.worker import thread_state

    from nvp.app.jobs import JOB_MODULE, follow_stderr

    worker = get_worker()
    key = getattr(thread_state, "key", "")
    where = f"{worker.address} ({socket.gethostname()}, pid {os.getpid()})"
    _emit(worker, "start", key, worker=worker.address, where=where)
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", JOB_MODULE, "cluster", str(os.getpid()), *argv],
        cwd=cwd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        start_new_session=True,
    )
    out: list[bytes] = []
    reader = threading.Thread(target=lambda: out.append(proc.stdout.read()), daemon=True)
    reader.start()
    stopped = threading.Event()

    def watch() -> None:  # a cancelled task's process is stopped (SIGTERM, then SIGKILL)
        while proc.poll() is None:
            if not _still_wanted(worker, key):
                stopped.set()
                _stop_process(proc)
                return
            time.sleep(0.5)

    threading.Thread(target=watch, daemon=True).start()
    last_error = follow_stderr(
        proc.stderr,
        lambda stage, percent, left: _emit(worker, "progress", key, stage=stage, percent=percent, left=left),
    )
    code = proc.wait()
    reader.join(5)
    if code and stopped.is_set():
        last_error = "cancelled"
    elif code < 0:
        last_error = f"its process was killed (signal {-code}) on {where}"
    elif code and not last_error:
        last_error = f"exit code {code}"
    return {
        "code": code,
        "error": last_error.split(": error: ", 1)[-1],
        "stdout": b"".join(out).decode("utf-8", "replace"),
        "worker": where,
        "seconds": time.monotonic() - t0,
    }


def _stop_process(proc: subprocess.Popen, grace_s: float = GRACE_S) -> None:
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except (ProcessLookupError, PermissionError):
        return
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


# -- a batch from the command line


@dataclass
class _Tracker:
    """What the events say about the jobs of one client (key → worker and progress)."""

    names: dict[str, str]
    starts: dict[str, list[str]] = field(default_factory=dict)
    progress: dict[str, tuple[str, float]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, event) -> None:
        _, msg = event
        key = msg.get("key")
        if key not in self.names:
            return
        with self.lock:
            if msg.get("kind") == "start":
                seen = self.starts.setdefault(key, [])
                if seen:
                    self.notes.append(
                        f"{self.names[key]}: its worker {seen[-1]} stopped; running it again on "
                        f"{msg.get('where', '?')}"
                    )
                seen.append(msg.get("where", "?"))
            elif msg.get("kind") == "progress":
                self.progress.pop(key, None)  # re-inserted last: the newest progress is at the end
                self.progress[key] = (str(msg.get("stage", "")), float(msg.get("percent", 0.0)))


def run_batch(
    jobs: Sequence[ClusterJob],
    address: str,
    progress: bool = True,
    label: str = "jobs",
    on_outcome: Callable[[Outcome], None] | None = None,
) -> list[Outcome]:
    """Runs ``jobs`` on the cluster at ``address``, one Dask task each; returns their outcomes in the
    order of ``jobs``, as they end calling ``on_outcome``. A bad input fails its job only; a job whose
    workers died :data:`allowed-failures` times fails with that reason. Progress: a bar of the jobs done,
    with the stage of one running job, and a line when a job moves to another worker."""
    from tqdm import tqdm

    if len({j.key for j in jobs}) != len(jobs):
        raise NvpError("the same job is listed twice")
    client = connect(address)
    tracker = _Tracker({j.key: j.name for j in jobs})
    outcomes: dict[str, Outcome] = {}
    try:
        client.subscribe_topic(TOPIC, tracker)
        if not client.scheduler_info().get("workers"):
            log.warning("no machine has joined the cluster at %s yet: the jobs wait for one", address)
        futures = {
            client.submit(run_job, list(j.argv), j.cwd, key=j.key, pure=False, retries=0): j for j in jobs
        }
        bar = tqdm(total=len(jobs), desc=f"{label} on the cluster", unit="job", disable=not progress)
        try:
            pending = set(futures)
            while pending:
                done = {f for f in pending if f.done()}
                pending -= done
                if not done:
                    time.sleep(0.25)
                with tracker.lock:
                    notes, tracker.notes = tracker.notes, []
                    running = dict(tracker.progress)
                for note in notes:
                    bar.write(f"nvp: {note}", file=sys.stderr)
                for fut in done:
                    job = futures.pop(fut)
                    outcome = _outcome(fut, job, len(tracker.starts.get(job.key, [])) or 1)
                    fut.release()  # the result is here: a worker dying later must not run the job again
                    outcomes[job.key] = outcome
                    if on_outcome is not None:
                        on_outcome(outcome)
                    bar.update(1)
                unfinished = [k for k in running if k not in outcomes]
                if unfinished:  # the job whose progress came last
                    stage, pct = running[unfinished[-1]]
                    name = tracker.names[unfinished[-1]]
                    name = name if len(name) <= 40 else "…" + name[-39:]
                    bar.set_postfix_str(f"{name}: {stage} {pct:.0f}%", refresh=False)
                bar.refresh()
        finally:
            bar.close()
    finally:
        client.close()
    return [outcomes[j.key] for j in jobs]


def failure_text(e: BaseException) -> str:
    """Why the cluster could not run a job (its task's exception)."""
    if type(e).__name__ == "KilledWorker":
        return "every worker that started it died"
    return f"the cluster could not run it ({type(e).__name__}: {e})"


def _outcome(fut, job: ClusterJob, attempts: int) -> Outcome:
    try:
        r = fut.result()
    except Exception as e:  # KilledWorker (its workers died too often), a lost head, a bug
        return Outcome(job, False, failure_text(e), attempts=attempts)
    return Outcome(
        job, r["code"] == 0, r["error"] if r["code"] else "", r["stdout"], r["worker"], r["seconds"], attempts
    )


def report(outcomes: Sequence[Outcome], command: str, done_word: str, output: str | Path) -> int:
    """Prints each job's own output lines, one error line per failed job (naming its input) and the
    summary line; returns the exit code (2 when any failed)."""
    failed = 0
    for i, o in enumerate(outcomes):
        if o.ok:
            for line in o.stdout.strip().splitlines()[-1:]:
                print(f"[{i + 1}/{len(outcomes)}] {line}")
        else:
            failed += 1
            print(f"nvp {command}: {o.job.name}: error: {o.error}", file=sys.stderr)
    print(
        f"{len(outcomes) - failed} of {len(outcomes)} {done_word} → {output}"
        + (f"; {failed} failed" if failed else "")
    )
    return 2 if failed else 0


def run_inputs(
    command: str,
    inputs: Sequence[Path],
    argv_of: Callable[[Path], list[str]],
    address: str,
    output: str | Path,
    done_word: str,
    progress: bool = True,
) -> tuple[int, list[Outcome]]:
    """A command's several inputs (``nvp dub a.wav b.wav --cluster HEAD``), one job each:
    ``argv_of(input)`` is that input's own command line (absolute paths). Prints as :func:`report`;
    returns the exit code and the outcomes."""
    cwd = str(Path.cwd())
    jobs = [ClusterJob(str(i), tuple(argv_of(i)), cwd) for i in inputs]
    outcomes = run_batch(jobs, address, progress=progress, label=f"nvp {command}")
    return report(outcomes, command, done_word, output), outcomes


def absolute(path: str | Path | None) -> str | None:
    """``path`` made absolute (a job runs on another machine, in the shared folder)."""
    return None if path is None else str(Path(path).resolve())


def jobs_of_file(path: Path) -> list[ClusterJob]:
    """The jobs of ``nvp cluster run``: one nvp command line per line (without ``nvp``; ``#`` comments and
    blank lines skipped), relative paths taken from the file's folder, named by their line."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise NvpError(f"cannot read the job list {path}: {e}") from e
    cwd = str(path.resolve().parent)
    jobs = []
    for n, line in enumerate(lines, start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            argv = shlex.split(line)
        except ValueError as e:
            raise NvpError(f"{path}, line {n}: {e}") from None
        if argv and argv[0] == "nvp":
            argv = argv[1:]
        if not argv or argv[0] in ("serve", "live", "cluster", "demo"):
            raise NvpError(f"{path}, line {n}: not a job for the cluster: {line.strip()}")
        jobs.append(ClusterJob(f"line {n} ({shlex.join(argv)[:60]})", tuple(argv), cwd))
    if not jobs:
        raise NvpError(f"{path} names no job (one nvp command line per line)")
    return jobs
