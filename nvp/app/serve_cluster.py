"""``nvp serve --cluster HEAD``: the web app's job queue run on a Dask cluster (:mod:`nvp.app.cluster`)
instead of in the server's own worker thread."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from nvp.app.cluster import TOPIC, ClusterJob, connect, failure_text, run_job
from nvp.app.jobs import JobRunner

if TYPE_CHECKING:
    from nvp.app.jobs import Job, JobStore

log = logging.getLogger(__name__)


class ClusterWorker(JobRunner):
    """``nvp serve --cluster HEAD``: the job queue's runner that sends each queued job to the cluster
    instead of running it here (same interface as :class:`nvp.app.jobs.Worker`).

    A job stays ``queued`` until a worker starts it (``running``, its message names the worker); when that
    worker leaves the cluster (stopped, or its machine died) the job is ``queued`` again ("queued again:
    its worker ... stopped") and the scheduler gives it to another worker. A cancel cancels the task (the
    worker stops the job's process). When the server stops, its tasks are released (the workers stop
    them) and the jobs stay ``running`` until the next start queues them again."""

    def __init__(
        self,
        store: JobStore,
        cwd: Path,
        address: str,
        on_done: Callable[[Job], None] | None = None,
    ) -> None:
        super().__init__(store, cwd, on_done, "nvp-cluster-jobs")
        self.address = address
        self._futures: dict[str, Any] = {}  # job id → future
        self._keys: dict[str, str] = {}  # task key → job id
        self._where: dict[str, tuple[str, str]] = {}  # job id → (worker address, description)
        self._client = None

    def recover(self) -> list[str]:
        """Jobs left ``running`` by a server that stopped: queued again (their tasks went with it)."""
        again = []
        for job in self.store.all():
            if job.state == "running" and self.store.update(
                job.id, ("running",), state="queued", pid=0, message="queued again after a server restart"
            ):
                again.append(job.id)
        return again

    def cancel(self, job_id: str) -> bool:
        """Cancel a queued or running job; False when it has already ended."""
        with self._lock:
            if not self.store.update(
                job_id, ("queued", "running"), state="cancelled", message="cancelled", finished=time.time(),
                left="", pid=0,
            ):  # fmt: skip
                return False
            fut = self._futures.pop(job_id, None)
        if fut is not None:
            fut.cancel()
        ended = self.store.get(job_id)
        if ended is not None:
            self._ended(ended)
        return True

    def stop(self, wait: float = 0.0) -> None:
        """Stop sending jobs; the cluster's running ones are released (their workers stop them)."""
        self.stopping.set()
        self.wake.set()
        if wait and self.is_alive():
            self.join(wait)

    def _event(self, event) -> None:
        _, msg = event
        jid = self._keys.get(msg.get("key", ""))
        if jid is None:
            return
        if msg.get("kind") == "start":
            self._where[jid] = (str(msg.get("worker", "")), str(msg.get("where", "")))
            self.store.update(
                jid, ("queued", "running"), state="running", stage="starting", percent=0.0, left="",
                message=f"on {msg.get('where', '?')}",
            )  # fmt: skip
        elif msg.get("kind") == "progress":
            self.store.update(
                jid, ("running",), stage=str(msg.get("stage", ""))[:60],
                percent=float(msg.get("percent", 0.0)), left=str(msg.get("left", ""))[:20],
            )  # fmt: skip

    def _connect(self) -> bool:
        try:
            self._client = connect(self.address, timeout=5.0)
            self._client.subscribe_topic(TOPIC, self._event)
            return True
        except Exception as e:
            log.warning("cannot reach the cluster head %s (%s); trying again", self.address, e)
            self._client = None
            return False

    def run(self) -> None:
        try:
            while not self.stopping.is_set():
                if self._client is None and not self._connect():
                    self.wake.wait(5.0)
                    continue
                try:
                    self._step()
                except Exception:
                    log.exception("the cluster job runner met an error; going on")
                self.wake.wait(0.5)
                self.wake.clear()
        finally:
            if self._client is not None:
                try:
                    self._client.close()
                except Exception:
                    log.debug("closing the cluster client", exc_info=True)

    def _step(self) -> None:
        client = self._client
        for job in self.store.all():
            if job.state == "queued" and job.id not in self._futures and not self.stopping.is_set():
                cj = ClusterJob(job.id, tuple(job.args), str(self.cwd), tag=f"{job.id}@{time.time()}")
                with self._lock:
                    if self.store.get(job.id).state != "queued":
                        continue
                    self._keys[cj.key] = job.id
                    self._futures[job.id] = client.submit(
                        run_job, list(cj.argv), cj.cwd, key=cj.key, pure=False, retries=0
                    )
                self.store.update(job.id, ("queued",), stage="waiting for a cluster worker")
        workers = set(client.scheduler_info(n_workers=-1).get("workers", {}))
        for jid, fut in list(self._futures.items()):
            if fut.done():
                self._settle(jid, fut)
                continue
            where = self._where.get(jid)
            if where and where[0] not in workers:
                self._where.pop(jid, None)
                self.store.update(
                    jid, ("running",), state="queued", stage="waiting for a cluster worker", percent=0.0,
                    left="", message=f"queued again: its worker {where[1]} stopped",
                )  # fmt: skip

    def _settle(self, jid: str, fut) -> None:
        with self._lock:
            self._futures.pop(jid, None)
        self._where.pop(jid, None)
        try:
            r = fut.result()
        except Exception as e:
            fut.release()
            if type(e).__name__ == "CancelledError":
                return
            state, fields = "failed", {"message": failure_text(e)}
        else:
            fut.release()  # the result is here: a worker dying later must not run the job again
            ok = r["code"] == 0
            state = "done" if ok else "failed"
            fields = {"message": f"ran on {r['worker']}" if ok else r["error"][-500:]}
            if ok:
                fields["percent"] = 100.0
        if self.store.update(
            jid, ("queued", "running"), state=state, finished=time.time(), left="", pid=0, **fields
        ):
            ended = self.store.get(jid)
            if ended is not None:
                self._ended(ended)
