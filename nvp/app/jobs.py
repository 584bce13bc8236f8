"""Background jobs of ``nvp serve``: fits and dubs queued in SQLite, run one at a time as ``nvp``
subprocesses, with progress, cancelling and recovery after a restart.

Each job runs the same command line a user would type (``nvp fit``, ``nvp dub``, ``nvp say``), so it
behaves, resumes and fails exactly like the CLI: its one error line becomes the job's message. Progress
comes from the command's progress bars (stage, percent, time left). The state lives in
``<data>/jobs.sqlite``; a server that stops (or is killed) leaves running jobs ``running`` with the
subprocess's pid: the next start stops that process if it is still there and queues the job again (a fit
then resumes where it stopped).
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

STATES = ("queued", "running", "done", "failed", "cancelled")
ID_PATTERN = re.compile(r"^[a-z]{1,8}-[0-9a-f]{12}$")
"""Ids the server makes (``job-…``, ``p-…``); anything else from a client is refused."""


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


class JobStore:
    """The ``jobs`` table (thread-safe: one connection per call)."""

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

    def update(self, job_id: str, **fields) -> None:
        if not fields:
            return
        with self._lock, self._db() as db:
            sets = ", ".join(f"{k} = :{k}" for k in fields)
            db.execute(f"UPDATE jobs SET {sets} WHERE id = :id", {**fields, "id": job_id})

    def get(self, job_id: str) -> Job | None:
        with self._db() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _job(row) if row else None

    def all(self) -> list[Job]:
        with self._db() as db:
            return [_job(r) for r in db.execute("SELECT * FROM jobs ORDER BY created")]

    def next_queued(self) -> Job | None:
        with self._db() as db:
            row = db.execute("SELECT * FROM jobs WHERE state = 'queued' ORDER BY created LIMIT 1").fetchone()
        return _job(row) if row else None


def _job(row: sqlite3.Row) -> Job:
    d = dict(row)
    d["args"] = json.loads(d["args"])
    return Job(**d)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class Worker(threading.Thread):
    """Runs the queued jobs one after the other (the CPU is shared: one heavy job at a time)."""

    def __init__(self, store: JobStore, cwd: Path, on_done=None) -> None:
        super().__init__(daemon=True)
        self.store, self.cwd, self.on_done = store, cwd, on_done
        self.wake = threading.Event()
        self.stopping = threading.Event()
        self._proc: subprocess.Popen | None = None
        self._current: str | None = None
        self._cancelled: set[str] = set()

    def recover(self) -> list[str]:
        """Jobs left ``running`` by a server that stopped: stop their process if it is still there and
        queue them again. Returns their ids."""
        again = []
        for job in self.store.all():
            if job.state == "running":
                if job.pid and _alive(job.pid):
                    try:
                        os.killpg(job.pid, signal.SIGTERM)
                    except (ProcessLookupError, PermissionError):
                        pass
                self.store.update(job.id, state="queued", pid=0, message="requeued after a server restart")
                again.append(job.id)
        return again

    def cancel(self, job_id: str) -> bool:
        """Cancel a queued or running job; False when it has already ended."""
        job = self.store.get(job_id)
        if job is None or job.state not in ("queued", "running"):
            return False
        self._cancelled.add(job_id)
        if job.state == "queued":
            self.store.update(job_id, state="cancelled", finished=time.time(), message="cancelled")
        elif self._current == job_id and self._proc is not None:
            os.killpg(self._proc.pid, signal.SIGTERM)
        return True

    def stop(self) -> None:
        self.stopping.set()
        self.wake.set()
        if self._proc is not None and self._proc.poll() is None:
            os.killpg(self._proc.pid, signal.SIGTERM)

    def run(self) -> None:
        while not self.stopping.is_set():
            job = self.store.next_queued()
            if job is None:
                self.wake.wait(1.0)
                self.wake.clear()
                continue
            self._run(job)

    def _run(self, job: Job) -> None:
        cmd = [sys.executable, "-m", "nvp.app.cli", *job.args]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self._current = job.id
        try:
            self._proc = subprocess.Popen(
                cmd,
                cwd=self.cwd,
                stderr=subprocess.PIPE,
                stdout=subprocess.DEVNULL,
                env=env,
                start_new_session=True,
            )
        except OSError as e:
            self.store.update(job.id, state="failed", message=f"cannot start: {e}", finished=time.time())
            return
        self.store.update(job.id, state="running", pid=self._proc.pid, stage="starting", percent=0.0)
        last_error, last_write = "", 0.0
        buf = b""
        assert self._proc.stderr is not None
        while True:
            chunk = os.read(self._proc.stderr.fileno(), 4096)
            if not chunk:
                lines, buf = [buf], b""
            else:
                buf += chunk
                *lines, buf = re.split(rb"[\r\n]", buf)
            for raw in lines:
                line = raw.decode("utf-8", "replace")
                p = parse_progress(line)
                if p is not None and time.time() - last_write > 0.5:
                    self.store.update(job.id, stage=p[0], percent=p[1], left=p[2])
                    last_write = time.time()
                elif p is None and line.strip():
                    last_error = line.strip()
            if not chunk:
                break
        code = self._proc.wait()
        self._proc = None
        self._current = None
        if job.id in self._cancelled:
            self.store.update(job.id, state="cancelled", message="cancelled", finished=time.time(), pid=0)
        elif code == 0:
            self.store.update(
                job.id, state="done", percent=100.0, left="", message="", finished=time.time(), pid=0
            )
        elif self.stopping.is_set():
            return  # the server is stopping: left "running", requeued by the next start
        else:
            msg = last_error.split(": error: ", 1)[-1] if last_error else f"exit code {code}"
            self.store.update(job.id, state="failed", message=msg, finished=time.time(), pid=0)
        if self.on_done is not None:
            self.on_done(self.store.get(job.id))
