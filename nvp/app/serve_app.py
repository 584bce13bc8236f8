"""The data folder behind ``nvp serve``: people, jobs, uploads, and what is removed when a job ends.

One :class:`App` owns one data folder (``people/``, ``uploads/``, ``dubs/``, ``jobs.sqlite``,
``people.json``, ``serve-token``) while it holds the folder's lock. It raises :class:`ApiError` with the
status a request should get; the HTTP side is :mod:`nvp.app.serve`.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import threading
import time
from http import HTTPStatus
from pathlib import Path

from nvp.app.jobs import ID_PATTERN, FolderLock, Job, JobStore, Worker, new_id
from nvp.app.serve_limits import Limits, inspect_media
from nvp.app.serve_security import ApiError, new_token, remove_token_file, write_token_file
from nvp.errors import NvpError

_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")


class App:
    """The data folder (locked: one server per folder), the job store and the worker behind the handler.

    ``token``: the API token (None: a new random one); ``cluster``: a cluster head's address, whose
    workers then run the jobs (:class:`nvp.app.serve_cluster.ClusterWorker`; the data folder must be
    shared with them, at the same path). ``close()`` releases everything."""

    def __init__(
        self,
        data: Path,
        limits: Limits | None = None,
        extra_fit_args: tuple = (),
        token: str | None = None,
        cluster: str | None = None,
    ) -> None:
        self.data = data.resolve()
        self.data.mkdir(parents=True, exist_ok=True)
        self._folder_lock = FolderLock(self.data)
        self._folder_lock.acquire()  # before anything else is read or written
        try:
            for sub in ("people", "uploads", "dubs"):
                (self.data / sub).mkdir(exist_ok=True)
            self.limits = limits or Limits()
            self.extra_fit_args = list(extra_fit_args)
            self.token = token or new_token()
            self.store = JobStore(self.data / "jobs.sqlite")
            self._names_path = self.data / "people.json"
            self._lock = threading.Lock()
            self._marks: dict[str, str] = {}
            if cluster:
                from nvp.app.serve_cluster import ClusterWorker

                self.worker = ClusterWorker(self.store, self.data, cluster, on_done=self._ended)
            else:
                self.worker = Worker(self.store, self.data, on_done=self._ended)
            self.requeued = self.worker.recover()
            self._sweep_uploads()
            write_token_file(self.data, self.token)
        except BaseException:
            self._folder_lock.release()
            raise
        self._closed = False

    def close(self, wait: float = 60.0) -> None:
        """Stop the worker (its running job stays ``running``, queued again by the next start), remove the
        token file and release the folder."""
        if self._closed:
            return
        self._closed = True
        self.worker.stop(wait if self.worker.is_alive() else 0.0)
        remove_token_file(self.data, self.token)
        self._folder_lock.release()

    def public(self, text: str) -> str:
        """``text`` without the server's data path (messages that reach a client)."""
        return text.replace(str(self.data) + os.sep, "").replace(str(self.data), "the data folder")

    def _inside(self, path: Path) -> bool:
        return path.resolve().is_relative_to(self.data)

    # -- uploads and clean-up

    def _uploads_of(self, job: Job) -> list[Path]:
        folder = self.data / "uploads"
        return [Path(a) for a in job.args if Path(a).parent == folder]

    def _sweep_uploads(self) -> None:
        """Uploads no queued or running job needs (partial ones of a killed server, finished jobs')."""
        needed = {
            p.name for j in self.store.all() if j.state in ("queued", "running") for p in self._uploads_of(j)
        }
        for f in (self.data / "uploads").iterdir():
            if f.name not in needed and f.is_file():
                f.unlink(missing_ok=True)

    def _ended(self, job: Job) -> None:
        """A job ended: its upload goes; a cancelled or failed job's outputs go too (its record stays)."""
        from nvp.app.dub import parts_folder

        for upload in self._uploads_of(job):
            upload.unlink(missing_ok=True)
        out = Path(job.output)
        if job.state == "done" or not self._inside(out):
            return
        if job.kind == "fit":
            for folder in (out, out.with_name(out.name + ".partial")):
                shutil.rmtree(folder, ignore_errors=True)
            out.with_name(out.name + ".jpg").unlink(missing_ok=True)
        else:
            out.unlink(missing_ok=True)
            shutil.rmtree(parts_folder(out), ignore_errors=True)
            for tmp in out.parent.glob(f".{out.stem}.nvp-*.tmp*"):
                tmp.unlink(missing_ok=True)

    def new_upload(self) -> Path:
        return self.data / "uploads" / new_id("up")

    def inspect(self, path: Path, kind: str) -> float:
        return inspect_media(path, kind, self.limits)

    def check_queue(self) -> None:
        if self.store.active() >= self.limits.max_queue:
            raise ApiError(
                HTTPStatus.TOO_MANY_REQUESTS,
                f"{self.limits.max_queue} jobs are queued or running, the limit; wait for one to end",
            )

    # -- people

    def names(self) -> dict[str, dict]:
        if not self._names_path.exists():
            return {}
        return json.loads(self._names_path.read_text())

    def _save_names(self, names: dict) -> None:
        tmp = self._names_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(names, indent=1))
        tmp.replace(self._names_path)

    def person_dir(self, pid: str) -> Path:
        check_id(pid)
        if pid not in self.names():
            raise ApiError(HTTPStatus.NOT_FOUND, f"no person {pid}")
        return self.data / "people" / pid

    def people(self) -> list[dict]:
        from nvp.bundle import PersonBundle

        jobs = {j.person: j for j in self.store.all() if j.kind == "fit"}
        out = []
        for pid, meta in self.names().items():
            job = jobs.get(pid)
            entry = {
                "id": pid,
                "name": meta["name"],
                "created": meta["created"],
                "fit_job": job.id if job else None,
            }
            folder = self.data / "people" / pid
            if (folder / "bundle.json").exists():
                try:
                    m = PersonBundle.load(folder, verify=False).manifest
                    t = m["target"]
                    entry["status"] = "ready"
                    entry["info"] = {
                        "size": f"{t['width']}x{t['height']}",
                        "fps": round(t["fps"], 3),
                        "seconds": round(t["duration_s"], 1),
                        "preset": m["preset"],
                        "stages": {k: round(v.get("seconds", 0), 1) for k, v in m["stages"].items()},
                    }
                except (NvpError, KeyError, TypeError) as e:
                    entry["status"], entry["info"] = "damaged", {"error": self.public(str(e))}
            else:
                entry["status"] = job.state if job else "missing"
            out.append(entry)
        return out

    def add_person(self, name: str, upload: Path, minutes: float | None) -> tuple[str, Job]:
        pid = new_id("p")
        with self._lock:
            names = self.names()
            names[pid] = {"name": _CONTROL.sub("", name)[:80] or "person", "created": time.time()}
            self._save_names(names)
        out = self.data / "people" / pid
        args = ["fit", str(upload), "-o", str(out), *self.extra_fit_args]
        if minutes is not None:
            args += ["--budget-minutes", str(minutes)]
        job = self.store.add(Job(new_id("job"), "fit", pid, args, str(out)))
        self.worker.wake.set()
        return pid, job

    def remove_person(self, pid: str) -> None:
        folder = self.person_dir(pid)
        if any(j.person == pid and j.state in ("queued", "running") for j in self.store.all()):
            raise ApiError(HTTPStatus.CONFLICT, f"{pid} has a job in progress; cancel it first")
        with self._lock:
            names = self.names()
            meta = names.pop(pid)
            self._save_names(names)
        shutil.rmtree(folder, ignore_errors=True)
        shutil.rmtree(folder.with_name(folder.name + ".partial"), ignore_errors=True)
        folder.with_name(pid + ".jpg").unlink(missing_ok=True)
        if meta.get("upload"):  # folders of earlier versions kept the upload with the person
            (self.data / "uploads" / Path(meta["upload"]).name).unlink(missing_ok=True)

    def ready_person(self, pid: str) -> Path:
        folder = self.person_dir(pid)
        if not (folder / "bundle.json").exists():
            raise ApiError(HTTPStatus.CONFLICT, f"{pid} is not fitted yet")
        return folder

    def add_dub(self, pid: str, upload: Path, gaze: str = "footage") -> Job:
        folder = self.ready_person(pid)
        jid = new_id("job")
        out = self.data / "dubs" / f"{jid}.mp4"
        args = ["dub", str(upload), "--person", str(folder), "-o", str(out), *gaze_args(gaze)]
        job = self.store.add(Job(jid, "dub", pid, args, str(out)))
        self.worker.wake.set()
        return job

    def add_say(self, pid: str, text: str, voice: str | None, gaze: str = "footage") -> Job:
        folder = self.ready_person(pid)
        eyes = gaze_args(gaze)
        text = _CONTROL.sub(" ", text).strip()
        if not text or len(text) > self.limits.max_text_chars:
            raise ApiError(
                HTTPStatus.BAD_REQUEST, f"give a text of 1 to {self.limits.max_text_chars} characters"
            )
        jid = new_id("job")
        out = self.data / "dubs" / f"{jid}.mp4"
        args = ["say", "--person", str(folder), "-o", str(out), *eyes]
        if voice:
            if not isinstance(voice, str) or not re.fullmatch(r"[A-Za-z0-9_\-]{1,40}", voice):
                raise ApiError(HTTPStatus.BAD_REQUEST, "a voice is the name of an installed voice")
            args += ["--voice", voice]
        job = self.store.add(
            Job(jid, "say", pid, [*args, "--", text], str(out))
        )  # "--": text is never an option
        self.worker.wake.set()
        return job

    # -- jobs

    def job(self, jid: str) -> Job:
        check_id(jid)
        job = self.store.get(jid)
        if job is None:
            raise ApiError(HTTPStatus.NOT_FOUND, f"no job {jid}")
        return job

    def job_view(self, job: Job, names: dict | None = None) -> dict:
        d = job.public()
        d["message"] = self.public(d["message"])
        d["person_name"] = (self.names() if names is None else names).get(job.person, {}).get("name", "")
        if job.kind in ("dub", "say") and job.state == "done":
            d["result"] = f"/api/jobs/{job.id}/result.mp4"
            d["mark"] = self.mark(job)
        if job.kind == "fit" and self.preview(job) is not None:
            d["preview"] = f"/api/jobs/{job.id}/preview.png"
        return d

    def mark(self, job: Job) -> str:
        """The synthetic-media mark of a finished dub (read once: the page asks every second or so)."""
        if job.id not in self._marks:
            from nvp.provenance import verify

            try:
                self._marks[job.id] = verify(job.output).tags.get("comment", "")
            except NvpError:
                self._marks[job.id] = ""
        return self._marks[job.id]

    def preview(self, job: Job) -> Path | None:
        """The newest renderer preview of a fit (in its partial folder while it runs)."""
        out = Path(job.output)
        for folder in (out.with_name(out.name + ".partial") / "renderer", out / "renderer"):
            shots = sorted(folder.glob("preview_*.png")) if folder.is_dir() else []
            if shots:
                return shots[-1]
        return None

    def thumbnail(self, pid: str) -> bytes:
        folder = self.person_dir(pid)
        thumb = folder.with_name(pid + ".jpg")
        if not thumb.exists():
            import cv2

            from nvp.media import iter_frames

            sources = [folder / "target.mp4"]
            job = next((j for j in self.store.all() if j.kind == "fit" and j.person == pid), None)
            sources += self._uploads_of(job) if job else []
            src = next((s for s in sources if s.is_file()), None)
            try:
                frame = next(iter_frames(src, max_frames=1)) if src else None
            except (NvpError, StopIteration):
                frame = None
            if frame is None:
                raise ApiError(HTTPStatus.NOT_FOUND, f"no picture of {pid}")
            h, w = frame.shape[:2]
            small = cv2.resize(frame, (160, max(1, round(160 * h / w))), interpolation=cv2.INTER_AREA)
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
            tmp = thumb.with_name(f".{thumb.name}.{threading.get_ident()}.tmp")
            tmp.write_bytes(jpg.tobytes())
            tmp.replace(thumb)
        return thumb.read_bytes()


def gaze_args(gaze: object) -> list[str]:
    """The command-line option of a job's ``gaze``: ``"footage"`` (none: the footage's eyes) or
    ``"camera"`` (eye contact). A gaze file is not taken from the web (it would name a file on the
    server)."""
    if gaze not in ("footage", "camera"):
        raise ApiError(HTTPStatus.BAD_REQUEST, "gaze is footage or camera")
    return [] if gaze == "footage" else ["--gaze", "camera"]


def check_id(value: str) -> str:
    if not ID_PATTERN.fullmatch(value or ""):
        raise ApiError(HTTPStatus.NOT_FOUND, "no such item")
    return value
