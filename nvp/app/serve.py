"""``nvp serve``: a local web app and JSON API for fitting people and dubbing them.

    nvp serve [--host 127.0.0.1] [--port 7860] [--data nvp-data]

The page (``nvp/app/web/index.html``, plain HTML and JavaScript served from the package) and the API share
one small HTTP server from Python's standard library (enough for one user on their own machine; it binds
to localhost by default). Work runs in the background, one job at a time (:mod:`nvp.app.jobs`). Which
requests are answered at all (Host, Origin, the per-launch token) is :mod:`nvp.app.serve_security`; what
is accepted (media types, formats, sizes, durations, queue, disk, time) is :mod:`nvp.app.serve_limits`;
``docs/serve.md`` explains both to users.

API (JSON unless said; every ``/api/`` call carries the token; ids are made by the server):

=========================================  ==================================================================
``GET /api/people``                        people: id, name, status, the bundle's facts
``POST /api/people?name=N[&minutes=M]``    body: a video file → a person and their fit job
``GET /api/people/<id>/thumbnail.jpg``     a frame of their footage (JPEG)
``DELETE /api/people/<id>``                remove a person (not while one of their jobs runs)
``POST /api/people/<id>/dubs``             body: an audio file → a dub job (``?gaze=camera``: eye contact)
``POST /api/people/<id>/say``              body ``{"text": "...", "voice": "..."}`` → a say job (``"gaze"``)
``GET /api/jobs`` / ``GET /api/jobs/<id>`` jobs: state, stage, percent, time left, message, result
``POST /api/jobs/<id>/cancel``             cancel a queued or running job
``GET /api/jobs/<id>/preview.png``         a fit's latest renderer preview (ground truth | render | final)
``GET /api/jobs/<id>/result.mp4``          a finished dub (byte ranges supported, for the player)
=========================================  ==================================================================

Errors are one JSON ``{"error": "..."}`` (4xx, or 500 for a bug, whose details go to the log), like the
CLI's one line, and never show the server's paths. Client file names never become paths (uploads are
stored under server-made ids); only files the server made are read back. A job's upload goes when the job
ends (a fitted bundle keeps its own copy of the footage); a cancelled or failed job leaves only its record.
"""

from __future__ import annotations

import html
import json
import logging
import os
import re
import secrets
import shlex
import signal
import socket
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from nvp.app.serve_app import App, gaze_args
from nvp.app.serve_limits import LimitedServer, Limits, body_length, check_free_disk, media_type
from nvp.app.serve_security import (
    MIN_TOKEN_CHARS,
    TOKEN_ENV,
    TOKEN_FILE,
    ApiError,
    Guard,
    is_loopback,
    page_csp,
    security_headers,
)
from nvp.errors import NvpError

logger = logging.getLogger(__name__)

WEB = Path(__file__).parent / "web"
DEFAULT_PORT = 7860

__all__ = ["ApiError", "App", "Limits", "make_server", "serve"]


ROUTES: list[tuple[str, re.Pattern, str]] = [
    (m, re.compile(p), name)
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
    """One request: the checks of :mod:`nvp.app.serve_security`, then a route. HTTP/1.0: one request per
    connection. A body left unread (a refused upload) is drained briefly after the answer so the client
    reads the answer instead of a reset connection."""

    app: App  # set by make_server
    guard: Guard
    default_request_version = "HTTP/1.0"  # even an answer to a garbled request line has a status line

    def log_message(self, fmt: str, *args) -> None:  # quiet: the page polls every second
        return None

    def version_string(self) -> str:
        return "nvp"

    def send_response_only(self, code: int, message: str | None = None) -> None:
        if self.request_version == "HTTP/0.9":  # "GET / HTTP/0.9" too gets a status line and headers
            self.request_version = "HTTP/1.0"
        super().send_response_only(code, message)

    def do_GET(self) -> None:
        self._dispatch()

    do_HEAD = do_POST = do_DELETE = do_PUT = do_PATCH = do_OPTIONS = do_GET

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """Answers of the standard library's request parsing (a garbled request, too long a line or
        header, an unknown method): JSON like every other error."""
        try:
            phrase = HTTPStatus(code).phrase
        except ValueError:
            phrase = "error"
        self.close_connection = True
        if not getattr(self, "_responded", False):
            self._json({"error": message or phrase}, code)

    def _dispatch(self) -> None:
        self._responded = False
        self._extra: dict[str, str] = {}
        length = (self.headers.get("Content-Length") or "").strip()
        self._body_left = int(length) if length.isdigit() and len(length) < 16 else 0
        try:
            self._route()
        except ApiError as e:
            self._error(e.status, str(e))
        except TimeoutError:
            self._error(HTTPStatus.REQUEST_TIMEOUT, "the request took too long")
        except (BrokenPipeError, ConnectionResetError):
            self.close_connection = True
            self._body_left = 0
        except Exception:
            logger.exception("nvp serve: %s %s", self.command, urlsplit(self.path).path[:200])
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, "internal error (the server's log has the details)")
        finally:
            if self._body_left > 0:
                self._drain()

    def _route(self) -> None:
        if not self.path.startswith("/"):
            raise ApiError(HTTPStatus.BAD_REQUEST, "the request target must be a path")
        url = urlsplit(self.path)
        method = self.command
        host = self.guard.check_host(self.headers)
        self.guard.check_origin(self.headers, host, page=url.path == "/" and method in ("GET", "HEAD"))
        try:
            query = parse_qs(url.query, max_num_fields=20)
        except ValueError as e:
            raise ApiError(HTTPStatus.BAD_REQUEST, "too many query fields") from e
        if url.path == "/api" or url.path.startswith("/api/"):
            self.guard.check_token(self.headers, query, method)
        wanted = "GET" if method == "HEAD" else method
        allowed = []
        for m, pattern, name in ROUTES:
            match = pattern.fullmatch(url.path)
            if match and m == wanted:
                getattr(self, "r_" + name)(query, **match.groupdict())
                return
            if match:
                allowed += [m, "HEAD"] if m == "GET" else [m]
        if allowed:
            self._extra["Allow"] = ", ".join(allowed)
            raise ApiError(HTTPStatus.METHOD_NOT_ALLOWED, f"use {' or '.join(allowed)} here")
        raise ApiError(HTTPStatus.NOT_FOUND, "no such page")

    # -- responses

    def _start(self, status: int, ctype: str, length: int, extra: dict | None = None, csp: str | None = None):
        self._responded = True
        self.send_response(status)
        headers = {**security_headers(), **(extra or {})}
        if csp:
            headers["Content-Security-Policy"] = csp
        headers.update({"Content-Type": ctype, "Content-Length": str(length), "Connection": "close"})
        for k, v in headers.items():
            self.send_header(k, v)
        self.end_headers()

    def _send(self, body: bytes, ctype: str, status: int = HTTPStatus.OK, extra=None, csp=None) -> None:
        self._start(status, ctype, len(body), extra, csp)
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, data, status: int = HTTPStatus.OK, extra: dict | None = None) -> None:
        self._send(json.dumps(data).encode(), "application/json", status, extra)

    def _error(self, status: int, message: str) -> None:
        self.close_connection = True
        if self._responded:  # the answer had begun (a streamed file): the connection just ends
            return
        try:
            self._json({"error": self.app.public(message)}, status, self._extra)
        except OSError:
            pass

    def _drain(self, budget: int = 16 << 20, seconds: float = 2.0) -> None:
        try:
            self.connection.shutdown(socket.SHUT_WR)
            self.connection.settimeout(0.5)
            end = time.monotonic() + seconds
            left = min(self._body_left, budget)
            while left > 0 and time.monotonic() < end:
                chunk = self.rfile.read1(min(left, 1 << 16))
                if not chunk:
                    break
                left -= len(chunk)
        except OSError:
            pass
        self._body_left = 0

    def _file(self, path: Path, ctype: str) -> None:
        """A file the server made, streamed, with byte ranges (video players seek with them)."""
        size = path.stat().st_size
        start, end, status = 0, size - 1, HTTPStatus.OK
        rng = re.fullmatch(r"bytes=(\d{0,18})-(\d{0,18})", (self.headers.get("Range") or "").strip())
        if rng and (rng[1] or rng[2]):
            if rng[1]:
                start = int(rng[1])
                end = min(int(rng[2]), size - 1) if rng[2] else size - 1
            else:
                start = size - int(rng[2]) if int(rng[2]) else size
                start = max(0, start)
            if start > end or start >= size:
                self._extra["Content-Range"] = f"bytes */{size}"
                raise ApiError(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE, f"the file has {size} bytes")
            status = HTTPStatus.PARTIAL_CONTENT
        extra = {"Accept-Ranges": "bytes"}
        if status == HTTPStatus.PARTIAL_CONTENT:
            extra["Content-Range"] = f"bytes {start}-{end}/{size}"
        with open(path, "rb") as f:
            self._start(status, ctype, end - start + 1, extra)
            if self.command == "HEAD":
                return
            f.seek(start)
            left = end - start + 1
            while left > 0:
                chunk = f.read(min(left, 256 * 1024))
                if not chunk:
                    break
                self.wfile.write(chunk)
                left -= len(chunk)

    # -- request bodies

    def _read(self, n: int) -> bytes:
        chunk = self.rfile.read1(n)
        self._body_left -= len(chunk)
        return chunk

    def _receive(self, kind: str) -> Path:
        """Store the request body under a server-made name (``.part`` until whole), then check it is the
        media it should be; nothing is left on disk when anything fails."""
        limits = self.app.limits
        media_type(self.headers, kind)
        size = body_length(self.headers, limits.max_upload)
        check_free_disk(self.app.data, size, limits)
        path = self.app.new_upload()
        part = path.with_name(path.name + ".part")
        deadline = time.monotonic() + limits.request_timeout_s + size / (limits.min_upload_kib_per_s * 1024)
        try:
            with open(part, "xb") as f:
                left = size
                while left > 0:
                    chunk = self._read(min(left, 1 << 20))
                    if not chunk:
                        raise ApiError(HTTPStatus.BAD_REQUEST, "the upload ended early")
                    f.write(chunk)
                    left -= len(chunk)
                    if time.monotonic() > deadline:
                        raise ApiError(HTTPStatus.REQUEST_TIMEOUT, "the upload is too slow")
            part.rename(path)
            self.app.inspect(path, kind)
        except OSError as e:
            part.unlink(missing_ok=True)
            path.unlink(missing_ok=True)
            from nvp.artifact import is_disk_full

            if is_disk_full(e):
                raise ApiError(HTTPStatus.INSUFFICIENT_STORAGE, "the disk is full") from e
            raise
        except BaseException:
            part.unlink(missing_ok=True)
            path.unlink(missing_ok=True)
            raise
        return path

    def _body_json(self) -> dict:
        ctype = (self.headers.get("Content-Type") or "").split(";", 1)[0].strip().lower()
        if ctype != "application/json":
            raise ApiError(
                HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "send a JSON body (Content-Type: application/json)"
            )
        size = body_length(self.headers, self.app.limits.max_json_bytes)
        raw = b""
        while len(raw) < size:
            chunk = self._read(size - len(raw))
            if not chunk:
                raise ApiError(HTTPStatus.BAD_REQUEST, "the body ended early")
            raw += chunk
        try:
            data = json.loads(raw)
        except (ValueError, RecursionError) as e:
            raise ApiError(HTTPStatus.BAD_REQUEST, "the body is not JSON") from e
        if not isinstance(data, dict):
            raise ApiError(HTTPStatus.BAD_REQUEST, "the body must be a JSON object")
        return data

    # -- routes

    def r_index(self, q) -> None:
        nonce = secrets.token_urlsafe(16)
        token = html.escape(self.app.token, quote=True) if self.guard.embed_token else ""
        page = (
            (WEB / "index.html").read_text().replace("__NVP_NONCE__", nonce).replace("__NVP_TOKEN__", token)
        )
        self._send(page.encode(), "text/html; charset=utf-8", csp=page_csp(nonce))

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
        self.app.check_queue()
        upload = self._receive("video")
        try:
            pid, job = self.app.add_person(name, upload, minutes)
        except BaseException:
            upload.unlink(missing_ok=True)
            raise
        self._json({"person": pid, "job": self.app.job_view(job)}, HTTPStatus.CREATED)

    def r_thumbnail(self, q, pid) -> None:
        self._send(self.app.thumbnail(pid), "image/jpeg")

    def r_delete_person(self, q, pid) -> None:
        self.app.remove_person(pid)
        self._json({"deleted": pid})

    def r_new_dub(self, q, pid) -> None:
        gaze = q.get("gaze", ["footage"])[0]
        gaze_args(gaze)  # a bad request is refused before its upload is read
        self.app.ready_person(pid)
        self.app.check_queue()
        upload = self._receive("audio")
        try:
            job = self.app.add_dub(pid, upload, gaze)
        except BaseException:
            upload.unlink(missing_ok=True)
            raise
        self._json(self.app.job_view(job), HTTPStatus.CREATED)

    def r_new_say(self, q, pid) -> None:
        body = self._body_json()
        self.app.ready_person(pid)
        self.app.check_queue()
        job = self.app.add_say(pid, str(body.get("text", "")), body.get("voice"), body.get("gaze", "footage"))
        self._json(self.app.job_view(job), HTTPStatus.CREATED)

    def r_jobs(self, q) -> None:
        names = self.app.names()
        self._json([self.app.job_view(j, names) for j in self.app.store.all()])

    def r_job(self, q, jid) -> None:
        self._json(self.app.job_view(self.app.job(jid)))

    def r_cancel(self, q, jid) -> None:
        job = self.app.job(jid)
        if not self.app.worker.cancel(job.id):
            raise ApiError(HTTPStatus.CONFLICT, f"{jid} has already ended ({self.app.job(jid).state})")
        self._json({"cancelled": jid})

    def r_preview(self, q, jid) -> None:
        shot = self.app.preview(self.app.job(jid))
        if shot is None:
            raise ApiError(HTTPStatus.NOT_FOUND, "no preview yet")
        self._send(shot.read_bytes(), "image/png")

    def r_result(self, q, jid) -> None:
        job = self.app.job(jid)
        out = Path(job.output)
        if (
            job.kind not in ("dub", "say")
            or job.state != "done"
            or not out.is_file()
            or not self.app._inside(out)
        ):
            raise ApiError(HTTPStatus.NOT_FOUND, f"{jid} has no result (yet)")
        self._file(out, "video/mp4")


def make_server(app: App, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> ThreadingHTTPServer:
    """The HTTP server for ``app`` (not started); ``port`` 0 picks a free one. ``server.guard`` holds the
    checks (and the token)."""
    guard = Guard.for_address(host, app.token)
    handler = type(
        "NvpHandler", (Handler,), {"app": app, "guard": guard, "timeout": app.limits.request_timeout_s}
    )
    server_class = LimitedServer
    if ":" in host.strip("[]"):
        server_class = type("LimitedServer6", (LimitedServer,), {"address_family": socket.AF_INET6})
    try:
        server = server_class((host.strip("[]"), port), handler, app.limits.max_connections)
    except OSError as e:
        raise NvpError(f"cannot listen on {host}:{port}: {e.strerror or e}") from e
    server.guard = guard
    return server


def _sigterm_as_interrupt() -> None:
    if threading.current_thread() is threading.main_thread():

        def interrupt(signum, frame) -> None:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            raise KeyboardInterrupt

        signal.signal(signal.SIGTERM, interrupt)


def serve(
    data: Path,
    host: str = "127.0.0.1",
    port: int = DEFAULT_PORT,
    max_upload_mb: float = Limits.max_upload_mb,
    token: str | None = None,
    limits: Limits | None = None,
    cluster: str | None = None,
) -> None:
    """Run the web app until interrupted (Ctrl-C or SIGTERM: the running job is stopped and queued again).

    ``token``: the API token; default ``$NVP_SERVE_TOKEN``, else a new one per launch. A ``host`` other
    than loopback needs an explicit one (the page then asks for it instead of carrying it). ``cluster``: a
    cluster head's address (:mod:`nvp.app.cluster`): its workers run the jobs instead of this process.

    Raises:
        NvpError: another server uses ``data``; a non-loopback host without a token; a token too short;
            the address cannot be listened on.
    """
    token = token or os.environ.get(TOKEN_ENV) or None
    if token is not None and len(token) < MIN_TOKEN_CHARS:
        raise NvpError(f"the token must have at least {MIN_TOKEN_CHARS} characters")
    if not is_loopback(host) and token is None:
        raise NvpError(
            f"--host {host} can be reached from other machines: set {TOKEN_ENV} to a secret of at least "
            f"{MIN_TOKEN_CHARS} characters first (the page asks for it; the traffic is plain HTTP)"
        )
    app = App(data, limits or Limits(max_upload_mb=max_upload_mb), token=token, cluster=cluster)
    server = None
    try:
        server = make_server(app, host, port)
        shown = f"[{host.strip('[]')}]" if ":" in host.strip("[]") else host
        where = f"http://{shown}:{server.server_address[1]}/"
        say = lambda text: print(f"nvp serve: {text}", file=sys.stderr, flush=True)  # noqa: E731
        say(f"{where} (data in {app.data}; Ctrl-C stops)")
        token_file = shlex.quote(str(Path(data) / TOKEN_FILE))
        shown_token = f"the one in {TOKEN_ENV}" if token else app.token
        say(f"API token {shown_token} (also in {token_file}): curl -H \"X-NVP-Token: $(cat {token_file})\" "
            f"{where}api/people")  # fmt: skip
        if not is_loopback(host):
            say(
                f"warning: listening on {host}: other machines can reach this server over plain HTTP (not "
                "encrypted); every API call needs the token, and the page asks for it"
            )
        if cluster:
            say(f"jobs run on the workers of the cluster at {cluster}; they must see {app.data} there")
        if app.requeued:
            say(f"{len(app.requeued)} interrupted job(s) queued again")
        _sigterm_as_interrupt()
        app.worker.start()
        server.serve_forever()
    finally:
        if server is not None:
            server.server_close()
        app.close()
