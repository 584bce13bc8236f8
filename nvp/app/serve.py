"""``nvp serve``: a local web app and JSON API for fitting people and dubbing them.

    nvp serve [--host 127.0.0.1] [--port 7860] [--data nvp-data]

The page (``nvp/app/web/index.html``, plain HTML and JavaScript served from the package) and the API share
one small HTTP server from Python's standard library (enough for one user on their own machine; it binds
to localhost by default). Work runs in the background, one job at a time (:mod:`nvp.app.jobs`).

API (JSON unless said; ids are made by the server and checked against ``jobs.ID_PATTERN``):

=========================================  ==================================================================
``GET /api/people``                        people: id, name, status, the bundle's facts
``POST /api/people?name=N[&minutes=M]``    body: a video file → a person and their fit job
``GET /api/people/<id>/thumbnail.jpg``     a frame of their footage (JPEG)
``DELETE /api/people/<id>``                remove a person (not while one of their jobs runs)
``POST /api/people/<id>/dubs``             body: an audio file → a dub job
``POST /api/people/<id>/say``              body ``{"text": "...", "voice": "..."}`` → a say job
``GET /api/jobs`` / ``GET /api/jobs/<id>`` jobs: state, stage, percent, time left, message, result
``POST /api/jobs/<id>/cancel``             cancel a queued or running job
``GET /api/jobs/<id>/preview.png``         a fit's latest renderer preview (ground truth | render | final)
``GET /api/jobs/<id>/result.mp4``          a finished dub (byte ranges supported, for the player)
=========================================  ==================================================================

Safety: uploads are limited in size (``--max-upload-mb``) and must be a video with sound (fits) or audio
(dubs) that FFmpeg reads, or they are deleted and refused; client file names never become paths (uploads
are stored under server-made ids); only files the server made are ever read back; errors are one JSON
``{"error": "..."}`` with a 4xx status, like the CLI's one line.
"""

from __future__ import annotations

import json
import re
import shutil
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlparse

from nvp.app.jobs import ID_PATTERN, Job, JobStore, Worker, new_id
from nvp.errors import NvpError

WEB = Path(__file__).parent / "web"
DEFAULT_PORT = 7860
MAX_UPLOAD_MB = 1024
MAX_TEXT = 2000
VIDEO_TYPES = ("video/", "application/octet-stream")
AUDIO_TYPES = ("audio/", "video/", "application/octet-stream")


class ApiError(Exception):
    def __init__(self, status: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.status = status


class App:
    """The data folder, the job store and the worker behind the HTTP handler."""

    def __init__(self, data: Path, max_upload_mb: float = MAX_UPLOAD_MB, extra_fit_args: tuple = ()) -> None:
        self.data = data.resolve()
        for sub in ("people", "uploads", "dubs"):
            (self.data / sub).mkdir(parents=True, exist_ok=True)
        self.max_upload = int(max_upload_mb * 1024 * 1024)
        self.extra_fit_args = list(extra_fit_args)
        self.store = JobStore(self.data / "jobs.sqlite")
        self._names_path = self.data / "people.json"
        self._lock = threading.Lock()
        self._marks: dict[str, str] = {}
        self.worker = Worker(self.store, self.data, on_done=self._ended)
        self.requeued = self.worker.recover()

    @staticmethod
    def _ended(job: Job) -> None:
        """A dub that was cancelled or failed is not run again: the parts it finished (kept for resuming
        after a server restart, :mod:`nvp.app.dub`) go."""
        from nvp.app.dub import parts_folder

        if job.kind in ("dub", "say") and job.state in ("cancelled", "failed"):
            shutil.rmtree(parts_folder(Path(job.output)), ignore_errors=True)

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
                except NvpError as e:
                    entry["status"], entry["info"] = "damaged", {"error": str(e)}
            else:
                entry["status"] = job.state if job else "missing"
            out.append(entry)
        return out

    def add_person(self, name: str, upload: Path, minutes: float | None) -> tuple[str, Job]:
        pid = new_id("p")
        with self._lock:
            names = self.names()
            names[pid] = {"name": name[:80] or "person", "created": time.time(), "upload": upload.name}
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
        (self.data / "uploads" / meta.get("upload", "-")).unlink(missing_ok=True)

    def ready_person(self, pid: str) -> Path:
        folder = self.person_dir(pid)
        if not (folder / "bundle.json").exists():
            raise ApiError(HTTPStatus.CONFLICT, f"{pid} is not fitted yet")
        return folder

    def add_dub(self, pid: str, upload: Path) -> Job:
        folder = self.ready_person(pid)
        jid = new_id("job")
        out = self.data / "dubs" / f"{jid}.mp4"
        job = self.store.add(
            Job(jid, "dub", pid, ["dub", str(upload), "--person", str(folder), "-o", str(out)], str(out))
        )
        self.worker.wake.set()
        return job

    def add_say(self, pid: str, text: str, voice: str | None) -> Job:
        folder = self.ready_person(pid)
        text = text.strip()
        if not text or len(text) > MAX_TEXT:
            raise ApiError(HTTPStatus.BAD_REQUEST, f"give a text of 1 to {MAX_TEXT} characters")
        jid = new_id("job")
        out = self.data / "dubs" / f"{jid}.mp4"
        args = ["say", text, "--person", str(folder), "-o", str(out)]
        if voice:
            if not re.fullmatch(r"[A-Za-z0-9_\-]{1,40}", voice):
                raise ApiError(HTTPStatus.BAD_REQUEST, "a voice is the name of an installed voice")
            args += ["--voice", voice]
        job = self.store.add(Job(jid, "say", pid, args, str(out)))
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

            src = folder / "target.mp4"
            if not src.exists():
                src = self.data / "uploads" / self.names()[pid].get("upload", "-")
            try:
                frame = next(iter_frames(src, max_frames=1))
            except (NvpError, StopIteration) as e:
                raise ApiError(HTTPStatus.NOT_FOUND, f"no picture of {pid} yet") from e
            h, w = frame.shape[:2]
            small = cv2.resize(frame, (160, max(1, round(160 * h / w))), interpolation=cv2.INTER_AREA)
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
            thumb.write_bytes(jpg.tobytes())
        return thumb.read_bytes()

    # -- uploads

    def receive(self, handler: BaseHTTPRequestHandler, kind: str) -> Path:
        """Store the request body under a server-made name, then check it is the media it should be."""
        size = int(handler.headers.get("Content-Length") or -1)
        if size <= 0:
            raise ApiError(HTTPStatus.LENGTH_REQUIRED, "send the file as the request body (with its length)")
        if size > self.max_upload:
            raise ApiError(
                HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
                f"the file is {size / 2**20:.0f} MB; the limit is {self.max_upload / 2**20:.0f} MB",
            )
        ctype = (handler.headers.get("Content-Type") or "application/octet-stream").lower()
        allowed = VIDEO_TYPES if kind == "video" else AUDIO_TYPES
        if not ctype.startswith(allowed):
            raise ApiError(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, f"expected {kind}, got {ctype}")
        path = self.data / "uploads" / new_id("up")
        with open(path, "wb") as f:
            left = size
            while left > 0:
                chunk = handler.rfile.read(min(left, 1 << 20))
                if not chunk:
                    break
                f.write(chunk)
                left -= len(chunk)
        if left:
            path.unlink(missing_ok=True)
            raise ApiError(HTTPStatus.BAD_REQUEST, "the upload ended early")
        try:
            self._check_media(path, kind)
        except NvpError as e:
            path.unlink(missing_ok=True)
            raise ApiError(HTTPStatus.UNPROCESSABLE_ENTITY, f"not a usable {kind} file: {e}") from e
        return path

    @staticmethod
    def _check_media(path: Path, kind: str) -> None:
        from nvp.media import audio_rate, probe_video

        if kind == "video":
            info = probe_video(path)
            if not info.has_audio:
                raise NvpError("the video has no sound (a fit learns from the person's speech)")
        else:
            audio_rate(path)


def check_id(value: str) -> str:
    if not ID_PATTERN.fullmatch(value or ""):
        raise ApiError(HTTPStatus.NOT_FOUND, "no such item")
    return value


ROUTES: list[tuple[str, re.Pattern, str]] = [
    (m, re.compile(p + r"$"), name)
    for m, p, name in [
        ("GET", r"/", "index"),
        ("GET", r"/api/people", "people"),
        ("POST", r"/api/people", "new_person"),
        ("GET", r"/api/people/(?P<pid>[^/]+)/thumbnail\.jpg", "thumbnail"),
        ("DELETE", r"/api/people/(?P<pid>[^/]+)", "delete_person"),
        ("POST", r"/api/people/(?P<pid>[^/]+)/dubs", "new_dub"),
        ("POST", r"/api/people/(?P<pid>[^/]+)/say", "new_say"),
        ("GET", r"/api/jobs", "jobs"),
        ("GET", r"/api/jobs/(?P<jid>[^/]+)", "job"),
        ("POST", r"/api/jobs/(?P<jid>[^/]+)/cancel", "cancel"),
        ("GET", r"/api/jobs/(?P<jid>[^/]+)/preview\.png", "preview"),
        ("GET", r"/api/jobs/(?P<jid>[^/]+)/result\.mp4", "result"),
    ]
]


class Handler(BaseHTTPRequestHandler):
    app: App  # set by make_server
    server_version = "nvp"

    def log_message(self, fmt: str, *args) -> None:  # quiet: the page polls every second
        return None

    def do_GET(self) -> None:
        self._dispatch("GET")

    def do_POST(self) -> None:
        self._dispatch("POST")

    def do_DELETE(self) -> None:
        self._dispatch("DELETE")

    def _dispatch(self, method: str) -> None:
        url = urlparse(self.path)
        try:
            for m, pattern, name in ROUTES:
                match = pattern.match(url.path)
                if match and m == method:
                    getattr(self, "r_" + name)(parse_qs(url.query), **match.groupdict())
                    return
            raise ApiError(HTTPStatus.NOT_FOUND, "no such page")
        except ApiError as e:
            self._json({"error": str(e)}, e.status)
        except (BrokenPipeError, ConnectionResetError):
            return

    # -- responses

    def _send(
        self, body: bytes, ctype: str, status: HTTPStatus = HTTPStatus.OK, extra: dict | None = None
    ) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, data, status: HTTPStatus = HTTPStatus.OK) -> None:
        self._send(json.dumps(data).encode(), "application/json", status)

    def _file(self, path: Path, ctype: str) -> None:
        """A file the server made, with byte ranges (video players seek with them)."""
        size = path.stat().st_size
        start, end = 0, size - 1
        rng = re.fullmatch(r"bytes=(\d*)-(\d*)", self.headers.get("Range", ""))
        status = HTTPStatus.OK
        if rng and (rng.group(1) or rng.group(2)):
            if rng.group(1):
                start = int(rng.group(1))
                end = min(int(rng.group(2)), size - 1) if rng.group(2) else size - 1
            else:
                start = max(0, size - int(rng.group(2)))
            if start > end:
                self._send(
                    b"",
                    ctype,
                    HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE,
                    {"Content-Range": f"bytes */{size}"},
                )
                return
            status = HTTPStatus.PARTIAL_CONTENT
        with open(path, "rb") as f:
            f.seek(start)
            body = f.read(end - start + 1)
        extra = {"Accept-Ranges": "bytes"}
        if status == HTTPStatus.PARTIAL_CONTENT:
            extra["Content-Range"] = f"bytes {start}-{end}/{size}"
        self._send(body, ctype, status, extra)

    def _body_json(self) -> dict:
        size = int(self.headers.get("Content-Length") or 0)
        if not 0 < size <= 64 * 1024:
            raise ApiError(HTTPStatus.BAD_REQUEST, "send a small JSON body")
        try:
            data = json.loads(self.rfile.read(size))
        except (ValueError, UnicodeDecodeError) as e:
            raise ApiError(HTTPStatus.BAD_REQUEST, f"the body is not JSON: {e}") from e
        if not isinstance(data, dict):
            raise ApiError(HTTPStatus.BAD_REQUEST, "the body must be a JSON object")
        return data

    # -- routes

    def r_index(self, q) -> None:
        self._send((WEB / "index.html").read_bytes(), "text/html; charset=utf-8")

    def r_people(self, q) -> None:
        self._json(self.app.people())

    def r_new_person(self, q) -> None:
        name = (q.get("name") or ["person"])[0]
        minutes = None
        if q.get("minutes"):
            try:
                minutes = float(q["minutes"][0])
            except ValueError as e:
                raise ApiError(HTTPStatus.BAD_REQUEST, "minutes must be a number") from e
            if not 0.05 <= minutes <= 240:
                raise ApiError(HTTPStatus.BAD_REQUEST, "minutes must be between 0.05 and 240")
        upload = self.app.receive(self, "video")
        pid, job = self.app.add_person(name, upload, minutes)
        self._json({"person": pid, "job": self.app.job_view(job)}, HTTPStatus.CREATED)

    def r_thumbnail(self, q, pid) -> None:
        self._send(self.app.thumbnail(pid), "image/jpeg")

    def r_delete_person(self, q, pid) -> None:
        self.app.remove_person(pid)
        self._json({"deleted": pid})

    def r_new_dub(self, q, pid) -> None:
        self.app.ready_person(pid)
        upload = self.app.receive(self, "audio")
        self._json(self.app.job_view(self.app.add_dub(pid, upload)), HTTPStatus.CREATED)

    def r_new_say(self, q, pid) -> None:
        body = self._body_json()
        job = self.app.add_say(pid, str(body.get("text", "")), body.get("voice"))
        self._json(self.app.job_view(job), HTTPStatus.CREATED)

    def r_jobs(self, q) -> None:
        names = self.app.names()
        self._json([self.app.job_view(j, names) for j in self.app.store.all()])

    def r_job(self, q, jid) -> None:
        self._json(self.app.job_view(self.app.job(jid)))

    def r_cancel(self, q, jid) -> None:
        job = self.app.job(jid)
        if not self.app.worker.cancel(job.id):
            raise ApiError(HTTPStatus.CONFLICT, f"{jid} has already ended ({job.state})")
        self._json({"cancelled": jid})

    def r_preview(self, q, jid) -> None:
        shot = self.app.preview(self.app.job(jid))
        if shot is None:
            raise ApiError(HTTPStatus.NOT_FOUND, "no preview yet")
        self._send(shot.read_bytes(), "image/png")

    def r_result(self, q, jid) -> None:
        job = self.app.job(jid)
        if job.kind not in ("dub", "say") or job.state != "done" or not Path(job.output).is_file():
            raise ApiError(HTTPStatus.NOT_FOUND, f"{jid} has no result (yet)")
        self._file(Path(job.output), "video/mp4")


def make_server(app: App, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> ThreadingHTTPServer:
    """The HTTP server for ``app`` (not started); ``port`` 0 picks a free one."""
    handler = type("NvpHandler", (Handler,), {"app": app})
    try:
        server = ThreadingHTTPServer((host, port), handler)
    except OSError as e:
        raise NvpError(f"cannot listen on {host}:{port}: {e.strerror or e}") from e
    server.daemon_threads = True
    return server


def serve(
    data: Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT, max_upload_mb: float = MAX_UPLOAD_MB
) -> None:
    """Run the web app until interrupted."""
    import sys

    app = App(data, max_upload_mb)
    server = make_server(app, host, port)
    app.worker.start()
    where = f"http://{host}:{server.server_address[1]}/"
    print(f"nvp serve: {where} (data in {app.data}; Ctrl-C stops)", file=sys.stderr, flush=True)
    if app.requeued:
        print(f"nvp serve: {len(app.requeued)} interrupted job(s) queued again", file=sys.stderr)
    try:
        server.serve_forever()
    finally:
        server.server_close()
        app.worker.stop()
