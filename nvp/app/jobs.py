"""Background jobs of ``nvp serve``: fits and dubs queued in SQLite, run one at a time as ``nvp``
subprocesses, with progress, cancelling and recovery after a restart.

Each job runs the same command line a user would type (``nvp fit``, ``nvp dub``, ``nvp say``) in a process
of its own (``python -m nvp.app.cli.job serve <job id> <nvp arguments>``), so it behaves, resumes and fails
exactly like the CLI: its one error line becomes the job's message, and SIGTERM (cancel) interrupts it
like Ctrl-C, so its temporary files go. Progress comes from the command's progress bars (stage, percent,
time left).

The state lives in ``<data>/jobs.sqlite``. One server per data folder (:class:`FolderLock`); a queued job
is claimed in one transaction (:meth:`JobStore.claim`), and a job's end is written only while it is still
``running`` (a cancel that wins the race stays a cancel). A server that stops (or is killed) leaves
running jobs ``running`` with the subprocess's pid: the next start stops that process if it is still
there *and* is that job's runner (a reused pid is left alone), then queues the job again (a fit then
resumes where it stopped). The worker thread survives any exception: the job in hand fails with it.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from nvp.errors import NvpError

logger = logging.getLogger(__name__)

STATES = ("queued", "running", "done", "failed", "cancelled")
ID_PATTERN = re.compile(r"^[a-z]{1,8}-[0-9a-f]{12}$")
"""Ids the server makes (``job-…``, ``p-…``); anything else from a client is refused."""
GRACE_S = 20.0
"""Seconds a job has to clean up after SIGTERM before its process group is killed."""
MAX_MESSAGE = 500

JOB_MODULE = "nvp.app.cli.job"
"""The module a job's process runs (by name: importing the CLI from here would make a cycle)."""
JOB_MODULES = {JOB_MODULE.encode(), b"nvp.app.jobs"}
"""Module names that mark a job's process on its command line (``nvp.app.jobs``: one started by an earlier
nvp, before the entry point moved, is still recognised and stopped on recovery)."""


def new_id(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


@dataclass
class Job:
    """One background job (a row of the ``jobs`` table)."""

    id: str
    kind: str
    """``fit``, ``dub`` or ``say``."""
    person: str
    args: list[str]
    """The ``nvp`` command line after ``nvp`` (paths inside the data folder only)."""
    output: str
    """What the job makes (a bundle folder or an mp4), inside the data folder."""
    state: str = "queued"
    stage: str = ""
    percent: float = 0.0
    left: str = ""
    """Time left of the current stage, as the progress bar says it (e.g. ``12:30``)."""
    message: str = ""
    pid: int = 0
    created: float = 0.0
    finished: float = 0.0

    def public(self) -> dict:
        """What the API shows (no command line, no pid)."""
        d = asdict(self)
        for k in ("args", "pid", "output"):
            d.pop(k)
        return d


_BAR = re.compile(
    r"^(?P<stage>[^:\r\n|]{1,60}):\s+(?P<pct>\d{1,3})%\|[^|]*\|(?P<rest>.*)$"
)  # tqdm: "train renderer (cpu):  45%|████      | 540/1200 s, 11:00 left" or "... [00:12<00:30, 8it/s]"
_LEFT = re.compile(r"(?:<(?P<a>[\d:?]+)[,\]])|(?:(?P<b>[\d:]+) left)")


def parse_progress(line: str) -> tuple[str, float, str] | None:
    """``(stage, percent, time left)`` from one progress-bar line, None for other output."""
    m = _BAR.match(line.strip())
    if not m:
        return None
    left = _LEFT.search(m.group("rest"))
    when = (left.group("a") or left.group("b") or "") if left else ""
    return m.group("stage").strip(), float(m.group("pct")), "" if "?" in when else when


class FolderLock:
    """One ``nvp serve`` per data folder: an exclusive ``flock`` on ``<folder>/serve.lock`` for as long as
    the server runs (the system drops it when the process dies, however it dies)."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / "serve.lock"
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock, or raise NvpError naming the server that has it (touching nothing)."""
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 64).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise NvpError(
                f"another nvp serve (pid {holder}) is using the data folder {self.path.parent.name}; "
                "stop it first, or give this one another --data"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None


class JobStore:
    """The ``jobs`` table (thread-safe: one connection per call; claims are transactions)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        with self._db() as db:
            db.execute(
                "CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, kind TEXT, person TEXT, args TEXT, "
                "output TEXT, state TEXT, stage TEXT, percent REAL, left TEXT, message TEXT, pid INTEGER, "
                "created REAL, finished REAL)"
            )

    def _db(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=30)
        db.row_factory = sqlite3.Row
        return db

    def add(self, job: Job) -> Job:
        job.created = job.created or time.time()
        d = asdict(job)
        d["args"] = json.dumps(d["args"])
        with self._lock, self._db() as db:
            db.execute(f"INSERT INTO jobs VALUES ({','.join(':' + k for k in d)})", d)
        return job

    def update(self, job_id: str, when: tuple[str, ...] = (), **fields) -> bool:
        """Set ``fields`` of a job (only while its state is one of ``when``, if given); True if it was."""
        if not fields:
            return False
        sets = ", ".join(f"{k} = :{k}" for k in fields)
        marks = ",".join(f":w{i}" for i in range(len(when)))
        where = f" AND state IN ({marks})" if when else ""
        params = {**fields, "id": job_id, **{f"w{i}": s for i, s in enumerate(when)}}
        with self._lock, self._db() as db:
            return db.execute(f"UPDATE jobs SET {sets} WHERE id = :id{where}", params).rowcount > 0

    def get(self, job_id: str) -> Job | None:
        with self._db() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _job(row) if row else None

    def all(self) -> list[Job]:
        with self._db() as db:
            return [_job(r) for r in db.execute("SELECT * FROM jobs ORDER BY created")]

    def active(self) -> int:
        """Jobs queued or running."""
        with self._db() as db:
            return db.execute("SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')").fetchone()[0]

    def claim(self) -> Job | None:
        """The oldest queued job, marked ``running`` in the same transaction (no job is claimed twice)."""
        with self._lock:
            db = self._db()
            try:
                db.execute("BEGIN IMMEDIATE")
                row = db.execute(
                    "SELECT * FROM jobs WHERE state = 'queued' ORDER BY created LIMIT 1"
                ).fetchone()
                if row is not None:
                    db.execute(
                        "UPDATE jobs SET state = 'running', stage = 'starting', percent = 0, left = '', "
                        "pid = 0 WHERE id = ?",
                        (row["id"],),
                    )
                db.commit()
            finally:
                db.close()
        if row is None:
            return None
        job = _job(row)
        job.state, job.stage, job.percent = "running", "starting", 0.0
        return job


def _job(row: sqlite3.Row) -> Job:
    d = dict(row)
    d["args"] = json.loads(d["args"])
    return Job(**d)


def _runs_job(pid: int, job_id: str) -> bool:
    """True if ``pid`` is alive and is the runner of ``job_id`` (a pid reused by another program is not)."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return bool(JOB_MODULES & set(cmdline)) and job_id.encode() in cmdline


def _signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


class JobRunner(threading.Thread):
    """What runs the queue's jobs (:class:`Worker` here, :class:`nvp.app.serve_cluster.ClusterWorker` on a
    cluster): ``wake`` when a job is queued, ``stopping`` to end, and ``on_done(job)`` called with every job
    that ended (done, failed, or cancelled, queued or running)."""

    def __init__(self, store: JobStore, cwd: Path, on_done: Callable[[Job], None] | None, name: str) -> None:
        super().__init__(daemon=True, name=name)
        self.store, self.cwd, self.on_done = store, cwd, on_done
        self.wake = threading.Event()
        self.stopping = threading.Event()
        self._lock = threading.Lock()

    def _ended(self, job: Job) -> None:
        if self.on_done is None:
            return
        try:
            self.on_done(job)
        except Exception:
            logger.exception("cleaning up after job %s", job.id)


class Worker(JobRunner):
    """Runs the queued jobs one after the other here (the CPU is shared: one heavy job at a time)."""

    def __init__(
        self,
        store: JobStore,
        cwd: Path,
        on_done: Callable[[Job], None] | None = None,
        grace_s: float = GRACE_S,
    ) -> None:
        super().__init__(store, cwd, on_done, "nvp-jobs")
        self.grace_s = grace_s  # self._lock guards _proc, _current, _cancelled
        self._proc: subprocess.Popen | None = None
        self._current: str | None = None
        self._cancelled: set[str] = set()

    def recover(self) -> list[str]:
        """Jobs left ``running`` by a server that stopped: stop their runner if it is still there and
        queue them again. Returns their ids. Call only while holding the data folder's lock."""
        again = []
        for job in self.store.all():
            if job.state != "running":
                continue
            if job.pid and _runs_job(job.pid, job.id):
                _signal_group(job.pid, signal.SIGTERM)
                end = time.monotonic() + self.grace_s
                while _runs_job(job.pid, job.id) and time.monotonic() < end:
                    time.sleep(0.1)
                if _runs_job(job.pid, job.id):
                    _signal_group(job.pid, signal.SIGKILL)
            if self.store.update(
                job.id, ("running",), state="queued", pid=0, message="queued again after a server restart"
            ):
                again.append(job.id)
        return again

    def cancel(self, job_id: str) -> bool:
        """Cancel a queued or running job; False when it has already ended."""
        with self._lock:
            if self.store.update(
                job_id, ("queued",), state="cancelled", message="cancelled", finished=time.time()
            ):
                ended = self.store.get(job_id)
            else:
                job = self.store.get(job_id)
                if job is None or job.state != "running":
                    return False
                self._cancelled.add(job_id)
                if self._current == job_id and self._proc is not None:
                    self._terminate(self._proc)
                return True
        self._ended(ended)
        return True

    def stop(self, wait: float = 0.0) -> None:
        """Stop after the job in hand (its process is stopped; it stays ``running``, queued again by the
        next start). ``wait``: seconds to wait for the thread to end."""
        self.stopping.set()
        self.wake.set()
        with self._lock:
            if self._proc is not None:
                self._terminate(self._proc)
        if wait and self.is_alive():
            self.join(wait)

    def _terminate(self, proc: subprocess.Popen) -> None:
        """SIGTERM to the job's process group; SIGKILL if it is still there after the grace time."""
        if proc.poll() is not None:
            return
        _signal_group(proc.pid, signal.SIGTERM)

        def kill() -> None:
            if proc.poll() is None:
                _signal_group(proc.pid, signal.SIGKILL)

        timer = threading.Timer(self.grace_s, kill)
        timer.daemon = True
        timer.start()

    def run(self) -> None:
        while not self.stopping.is_set():
            try:
                job = self.store.claim()
            except Exception:  # e.g. the database is locked or gone: try again later
                logger.exception("cannot read the job queue")
                self.wake.wait(5.0)
                continue
            if job is None:
                self.wake.wait(1.0)
                self.wake.clear()
                continue
            try:
                self._run(job)
            except Exception as e:
                logger.exception("job %s", job.id)
                self._end(
                    job.id, "failed", f"the job runner met an unexpected error: {type(e).__name__}: {e}"
                )
            finally:
                with self._lock:
                    self._proc, self._current = None, None
            ended = self.store.get(job.id)
            if ended is not None and ended.state != "running":
                self._ended(ended)

    def _end(self, job_id: str, state: str, message: str = "", **fields) -> bool:
        """Write a job's end while it is still running (a cancel or a restart's requeue wins)."""
        with self._lock:
            if job_id in self._cancelled:
                state, message = "cancelled", "cancelled"
                self._cancelled.discard(job_id)
            return self.store.update(
                job_id, ("running",), state=state, message=message[-MAX_MESSAGE:], finished=time.time(),
                pid=0, left="", **fields,
            )  # fmt: skip

    def _command(self, job: Job) -> list[str]:
        return [sys.executable, "-m", JOB_MODULE, "serve", job.id, *job.args]

    def _run(self, job: Job) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        with self._lock:
            self._current = job.id
            if job.id in self._cancelled:
                self._end_locked_cancel(job.id)
                return
            if self.stopping.is_set():  # claimed as the server stops: back in the queue, not started
                self.store.update(job.id, ("running",), state="queued", stage="", pid=0)
                return
            try:
                proc = subprocess.Popen(
                    self._command(job),
                    cwd=self.cwd,
                    stdin=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    stdout=subprocess.DEVNULL,
                    env=env,
                    start_new_session=True,
                )
            except OSError as e:
                self._proc = None
                start_error = f"cannot start: {e.strerror or e}"
            else:
                self._proc, start_error = proc, ""
        if start_error:
            self._end(job.id, "failed", start_error)
            return
        self.store.update(job.id, ("running",), pid=proc.pid)
        last_error = self._follow(job.id, proc)
        code = proc.wait()
        if code == 0:
            self._end(job.id, "done", percent=100.0)
        elif self.stopping.is_set() and job.id not in self._cancelled:
            return  # the server is stopping: left "running", queued again by the next start
        else:
            msg = last_error.split(": error: ", 1)[-1] if last_error else f"exit code {code}"
            self._end(job.id, "failed", msg)

    def _end_locked_cancel(self, job_id: str) -> None:
        self._cancelled.discard(job_id)
        self.store.update(
            job_id, ("running",), state="cancelled", message="cancelled", finished=time.time(), pid=0
        )

    def _follow(self, job_id: str, proc: subprocess.Popen) -> str:
        """Read the job's stderr to its end: progress into the store; returns the last other line."""
        assert proc.stderr is not None
        return follow_stderr(
            proc.stderr,
            lambda stage, percent, left: self.store.update(
                job_id, ("running",), stage=stage, percent=percent, left=left
            ),
        )


def follow_stderr(
    stream, on_progress: Callable[[str, float, float | None], None], every_s: float = 0.5
) -> str:
    """Read a job process's stderr ``stream`` to its end (then close it): its progress lines
    (:func:`parse_progress`) go to ``on_progress(stage, percent, left)``, at most every ``every_s``; returns
    the last other non-empty line (the error, when it failed)."""
    last_error, last_sent, buf = "", 0.0, b""
    while True:
        chunk = os.read(stream.fileno(), 4096)
        if chunk:
            buf += chunk
            *lines, buf = re.split(rb"[\r\n]", buf)
            buf = buf[-65536:]
        else:
            lines, buf = [buf], b""
        for raw in lines:
            line = raw.decode("utf-8", "replace")
            p = parse_progress(line)
            if p is not None and time.monotonic() - last_sent > every_s:
                on_progress(*p)
                last_sent = time.monotonic()
            elif p is None and line.strip():
                last_error = line.strip()
        if not chunk:
            stream.close()
            return last_error
