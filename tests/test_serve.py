"""nvp serve on tiny synthetic data: the JSON API and job lifecycle (uploads, fit, dub, cancel, recovery),
its local-app security (Host, Origin, token, headers), strict inputs and limits, the job runner's
robustness (one server per folder, claims, crashes, cancel races, SIGTERM), and a bounded fuzz run
against a live server on loopback."""

from __future__ import annotations

import hashlib
import http.client
import io
import json
import os
import random
import shlex
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from test_pipeline import speechlike

from nvp.app.jobs import FolderLock, Job, JobStore, Worker, parse_progress
from nvp.app.serve import App, Limits, make_server
from nvp.errors import NvpError

DEADLINE = 300.0


def until(predicate, what: str, timeout: float = DEADLINE, every: float = 0.05):
    """Poll ``predicate`` until it returns something true; fail after ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out waiting for {what}")


class Client:
    """A live server on 127.0.0.1 (a free port) and raw HTTP calls to it (every header under control)."""

    def __init__(self, app: App) -> None:
        self.app = app
        self.server = make_server(app, "127.0.0.1", 0)
        self.port = self.server.server_address[1]
        self.host = f"127.0.0.1:{self.port}"
        self.token = app.token
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.app.close()

    def call(
        self,
        method: str,
        path: str,
        body: bytes | None = None,
        ctype: str | None = None,
        headers=None,
        token: bool = True,
    ):
        h = {"Host": self.host}
        if token:
            h["X-NVP-Token"] = self.token
        if ctype:
            h["Content-Type"] = ctype
        h.update(headers or {})
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=120)
        try:
            conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
            for k, v in h.items():
                if v is not None:
                    conn.putheader(k, v)
            if body is not None:
                conn.putheader("Content-Length", str(len(body)))
            conn.endheaders(body)
            r = conn.getresponse()
            return r.status, r.read(), dict(r.headers)
        finally:
            conn.close()

    def json(self, method: str, path: str, body=None, ctype=None, **kw):
        status, data, _ = self.call(method, path, body, ctype, **kw)
        return status, json.loads(data)

    def wait(self, job: str, states=("done", "failed", "cancelled"), timeout: float = DEADLINE) -> dict:
        def state():
            j = self.json("GET", f"/api/jobs/{job}")[1]
            return j if j["state"] in states else None

        return until(state, f"job {job} to reach {states}", timeout, every=0.2)


@pytest.fixture
def make_client(tmp_path):
    made = []

    def make(start: bool = True, **kw) -> Client:
        app = App(tmp_path / "data", extra_fit_args=kw.pop("fit_args", ("--steps", "2")), **kw)
        c = Client(app)
        if start:
            app.worker.start()
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()


def waiting_job(flag: Path) -> list[str]:
    """A stand-in job command: waits until ``flag`` exists (at most a minute), then succeeds."""
    code = (
        "import os, sys, time\n"
        "end = time.monotonic() + 60\n"
        f"while not os.path.exists({str(flag)!r}) and time.monotonic() < end:\n"
        "    time.sleep(0.02)\n"
        f"sys.exit(0 if os.path.exists({str(flag)!r}) else 1)\n"
    )
    return [sys.executable, "-c", code]


def snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
        for p in sorted(folder.rglob("*"))
    }


def test_progress_lines_of_the_commands_are_understood():
    assert parse_progress("train renderer (cpu):  45%|████      | 540/1200 s, 11:00 left, step=10") == (
        "train renderer (cpu)",
        45.0,
        "11:00",
    )
    assert parse_progress("track:  30%|███       | 30/100 [00:03<00:07,  9.9frame/s]") == (
        "track",
        30.0,
        "00:07",
    )
    assert parse_progress("track:   0%|          | 0/100 [00:00<?, ?frame/s]") == ("track", 0.0, "")
    assert parse_progress("nvp fit: error: no speech") is None


def test_fit_then_dub_then_play_the_marked_result(make_client, demo_clip, tmp_path):
    c = make_client()
    video = demo_clip.path.read_bytes()
    status, made = c.json("POST", "/api/people?name=Ann%20%3Cb%3E", video, "video/mp4")
    assert status == 201 and made["job"]["state"] in ("queued", "running")
    pid, fit_job = made["person"], made["job"]["id"]
    assert c.wait(fit_job)["state"] == "done"
    until(
        lambda: not any((c.app.data / "uploads").iterdir()), "the upload to go"
    )  # the bundle has the footage
    _, people = c.json("GET", "/api/people")
    assert [p["status"] for p in people] == ["ready"] and people[0][
        "name"
    ] == "Ann <b>"  # escaped by the page
    assert people[0]["info"]["size"] == "256x256"
    status, jpg, headers = c.call("GET", f"/api/people/{pid}/thumbnail.jpg")
    assert status == 200 and jpg[:2] == b"\xff\xd8" and headers["Content-Type"] == "image/jpeg"
    wav = tmp_path / "s.wav"
    sf.write(wav, speechlike(1.0), 22050)
    status, job = c.json("POST", f"/api/people/{pid}/dubs", wav.read_bytes(), "audio/wav")
    assert status == 201
    done = c.wait(job["id"])
    assert done["state"] == "done" and "SYNTHETIC MEDIA" in done["mark"], done["message"]
    until(lambda: not any((c.app.data / "uploads").iterdir()), "the dub's upload to go")
    status, mp4, headers = c.call("GET", done["result"])
    assert status == 200 and mp4[4:8] == b"ftyp" and headers["Accept-Ranges"] == "bytes"
    status, part, headers = c.call("GET", done["result"], headers={"Range": "bytes=4-7"})
    assert status == 206 and part == b"ftyp" and headers["Content-Range"] == f"bytes 4-7/{len(mp4)}"
    status, tail, headers = c.call("GET", done["result"], headers={"Range": "bytes=-3"})
    assert status == 206 and tail == mp4[-3:]
    status, err, headers = c.call("GET", done["result"], headers={"Range": f"bytes={len(mp4)}-"})
    assert status == 416 and headers["Content-Range"] == f"bytes */{len(mp4)}" and b"error" in err
    status, empty, headers = c.call("HEAD", done["result"])
    assert status == 200 and empty == b"" and headers["Content-Length"] == str(len(mp4))
    status, mp4_by_query, _ = c.call("GET", f"{done['result']}?token={c.token}", token=False)  # <video src>
    assert status == 200 and mp4_by_query == mp4
    # a dub cancelled while it runs leaves nothing but its record
    sf.write(wav, speechlike(8.0), 22050)
    status, job = c.json("POST", f"/api/people/{pid}/dubs", wav.read_bytes(), "audio/wav")
    c.wait(job["id"], states=("running", "done", "failed"))
    c.json("POST", f"/api/jobs/{job['id']}/cancel")
    assert c.wait(job["id"])["state"] == "cancelled"
    dubs = c.app.data / "dubs"
    until(
        lambda: sorted(p.name for p in dubs.iterdir()) == [f"{done['id']}.mp4"], "only the first dub to stay"
    )
    until(lambda: not any((c.app.data / "uploads").iterdir()), "the cancelled dub's upload to go")
    # a finished person can be removed, with their files
    status, _ = c.json("DELETE", f"/api/people/{pid}")
    assert status == 200 and not (c.app.data / "people" / pid).exists()
    assert not (c.app.data / "people" / f"{pid}.jpg").exists()
    assert c.json("GET", "/api/people")[1] == []


def test_cancel_and_recovery_after_a_restart(make_client, demo_clip):
    c = make_client(fit_args=("--budget-minutes", "10"))
    video = demo_clip.path.read_bytes()
    _, first = c.json("POST", "/api/people?name=a", video, "video/mp4")
    _, second = c.json("POST", "/api/people?name=b", video, "video/mp4")
    j1, j2 = first["job"]["id"], second["job"]["id"]
    assert c.json("GET", f"/api/jobs/{j2}")[1]["state"] == "queued"  # one job at a time
    c.wait(j1, states=("running",))
    pid = until(lambda: c.app.store.get(j1).pid, "the fit's process")
    assert c.json("POST", f"/api/jobs/{j2}/cancel")[0] == 200  # queued: never starts
    assert c.json("GET", f"/api/jobs/{j2}")[1]["state"] == "cancelled"
    assert c.json("POST", f"/api/jobs/{j2}/cancel")[0] == 409  # already ended
    assert len(list((c.app.data / "uploads").iterdir())) == 1  # the cancelled job's upload went
    # the server stops while the fit runs: the job stays "running"; a new server queues it again
    c.close()
    assert c.app.store.get(j1).state == "running"
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # close() waited for the fit's process to end
    app = App(c.app.data, extra_fit_args=("--steps", "2"))
    assert app.requeued == [j1] and app.store.get(j1).state == "queued"
    c2 = Client(app)
    app.worker.start()
    try:
        c2.wait(j1, states=("running",))
        until(lambda: (app.data / "people" / f"{first['person']}.partial").exists(), "the fit's folder")
        assert c2.json("POST", f"/api/jobs/{j1}/cancel")[0] == 200
        assert c2.wait(j1)["state"] == "cancelled"
        # a cancelled fit leaves only its record: no half-built folder, no upload
        until(lambda: not any((app.data / "people").iterdir()), "the half-built person to go")
        until(lambda: not any((app.data / "uploads").iterdir()), "the upload to go")
        assert {p["status"] for p in c2.json("GET", "/api/people")[1]} == {"cancelled"}
    finally:
        c2.close()


def test_bad_uploads_and_path_traversal_are_refused(make_client, tmp_path):
    c = make_client(start=False, limits=Limits(max_upload_mb=0.01))
    uploads = c.app.data / "uploads"
    status, err = c.json("POST", "/api/people?name=x", b"not a video at all" * 10, "video/mp4")
    assert status == 422 and "not a video file" in err["error"]
    status, err = c.json("POST", "/api/people?name=x", b"x" * 20000, "video/mp4")
    assert status == 413 and "limit" in err["error"]
    assert list(uploads.iterdir()) == []
    for ctype in (None, "text/plain", "application/x-www-form-urlencoded", "multipart/form-data; boundary=x"):
        status, err = c.json("POST", "/api/people?name=x", b"<html>", ctype)  # what a cross-site form sends
        assert status == 415 and err["error"], ctype
    status, err = c.json(
        "POST", "/api/people?name=x", b"x" * 100, "video/mp4", headers={"Content-Encoding": "gzip"}
    )
    assert status == 415
    wav = tmp_path / "mute.wav"
    sf.write(wav, np.zeros(800, np.float32), 16000)
    status, err = c.json("POST", "/api/people?name=x", wav.read_bytes(), "video/mp4")  # a silent "video"
    assert status == 422 and str(c.app.data) not in json.dumps(err)
    assert list(uploads.iterdir()) == []
    for path in [
        "/api/people/../../etc/passwd/thumbnail.jpg",
        "/api/people/..%2F..%2Fetc/thumbnail.jpg",
        "/api/jobs/..%2fjobs.sqlite/result.mp4",
        "/api/jobs/job-000000000000/result.mp4",
        "/api/jobs/../jobs.sqlite",
        "/etc/passwd",
        "/jobs.sqlite",
        "/serve-token",
    ]:
        status, data, _ = c.call("GET", path)
        assert status == 404 and json.loads(data).keys() == {"error"}, path
    status, err = c.json("POST", "/api/people/p-000000000000/say", b'{"text": "hi"}', "application/json")
    assert status == 404
    status, err = c.json("DELETE", "/api/people/..")
    assert status == 404
    status, err = c.json("PUT", "/api/people")
    assert status == 405 and "GET" in err["error"]


def test_foreign_hosts_other_sites_and_calls_without_the_token_are_refused(make_client, demo_clip):
    c = make_client(start=False)
    for host in (
        "evil.example.com",
        f"evil.example.com:{c.port}",
        "127.0.0.1.evil.example",
        "localhost.:1",
        "",
    ):
        status, err = c.json("GET", "/api/people", headers={"Host": host})
        assert 400 <= status < 500 and err["error"], host
        assert 400 <= c.call("GET", "/", headers={"Host": host})[0] < 500  # the page holds the token
    for host in (f"localhost:{c.port}", f"LOCALHOST:{c.port}", f"[::1]:{c.port}", "127.0.0.1"):
        assert c.json("GET", "/api/people", headers={"Host": host})[0] == 200, host
    evil = {"Origin": "http://evil.example.com"}
    video = demo_clip.path.read_bytes()
    assert c.json("POST", "/api/people?name=x", video, "video/mp4", headers=evil)[0] == 403
    assert c.json("POST", "/api/people?name=x", video, "video/mp4", headers={"Origin": "null"})[0] == 403
    assert c.json("DELETE", "/api/people/p-000000000000", headers=evil)[0] == 403
    assert c.json("POST", "/api/jobs/job-000000000000/cancel", headers=evil)[0] == 403
    assert c.json("GET", "/api/people", headers=evil)[0] == 403
    other_port = {"Origin": f"http://127.0.0.1:{c.port + 1}", "Sec-Fetch-Site": "same-site"}
    assert c.json("GET", "/api/people", headers=other_port)[0] == 403
    assert c.json("GET", "/api/people", headers={"Sec-Fetch-Site": "cross-site"})[0] == 403
    assert c.json("GET", "/api/people", headers={"Origin": f"http://{c.host}"})[0] == 200  # the page itself
    assert list((c.app.data / "uploads").iterdir()) == []
    # the token: missing → 401, wrong → 403, on every /api/ call; the query form only for GET/HEAD
    for method, path in [
        ("GET", "/api/people"),
        ("GET", "/api/jobs"),
        ("POST", "/api/people"),
        ("DELETE", "/api/people/p-000000000000"),
        ("GET", "/api/jobs/job-000000000000/result.mp4"),
        ("HEAD", "/api/people"),
        ("GET", "/api/nothing"),
    ]:
        assert c.call(method, path, token=False)[0] == 401, path
        assert c.call(method, path, token=False, headers={"X-NVP-Token": "x" * 43})[0] == 403, path
    assert c.call("GET", "/api/people", token=False, headers={"Authorization": f"Bearer {c.token}"})[0] == 200
    assert c.call("GET", f"/api/people?token={c.token}", token=False)[0] == 200
    assert c.call("DELETE", f"/api/people/p-000000000000?token={c.token}", token=False)[0] == 401
    # the page: carries the token (loopback), strict headers, HEAD answered
    status, page, headers = c.call("GET", "/", token=False)
    assert status == 200 and f'content="{c.token}"'.encode() in page
    csp = headers["Content-Security-Policy"]
    assert "frame-ancestors 'none'" in csp and "script-src 'nonce-" in csp and "unsafe-inline" not in csp
    nonce = csp.split("'nonce-")[1].split("'")[0]
    assert page.count(f'nonce="{nonce}"'.encode()) == 2 and b"style=" not in page
    assert headers["X-Frame-Options"] == "DENY" and headers["X-Content-Type-Options"] == "nosniff"
    status, empty, head = c.call("HEAD", "/", token=False)
    assert status == 200 and empty == b"" and int(head["Content-Length"]) == len(page)
    # curl users read the token from a file only this user can read
    token_file = c.app.data / "serve-token"
    assert token_file.read_text().strip() == c.token and stat.S_IMODE(token_file.stat().st_mode) == 0o600


def test_a_non_loopback_server_needs_an_explicit_token(tmp_path, monkeypatch):
    from nvp.app.serve import serve

    monkeypatch.delenv("NVP_SERVE_TOKEN", raising=False)
    with pytest.raises(NvpError, match="NVP_SERVE_TOKEN"):
        serve(tmp_path / "data", host="0.0.0.0", port=0)
    with pytest.raises(NvpError, match="at least 16"):
        serve(tmp_path / "data", host="0.0.0.0", port=0, token="short")
    assert not (tmp_path / "data").exists()  # refused before touching anything
    from nvp.app.serve_security import Guard

    lan = Guard.for_address("0.0.0.0", "t" * 20)
    assert not lan.embed_token and lan.any_ip and "localhost" in lan.hosts


def test_playlists_uploaded_as_media_are_refused_without_opening_what_they_name(make_client, demo_clip):
    c = make_client(start=False)
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(4)
    listener.setblocking(False)
    url = f"http://127.0.0.1:{listener.getsockname()[1]}/segment.ts"
    hls = f"#EXTM3U\n#EXT-X-TARGETDURATION:2\n#EXTINF:2,\n{url}\n#EXTINF:2,\nfile://{demo_clip.path}\n#EXT-X-ENDLIST\n"
    concat = f"ffconcat version 1.0\nfile '{demo_clip.path}'\nfile 'up-000000000000'\nfile '{url}'\n"
    try:
        for body in (hls, concat):
            for path, ctype in (
                ("/api/people?name=x", "video/mp4"),
                ("/api/people?name=x", "video/x-matroska"),
            ):
                status, err = c.json("POST", path, body.encode(), ctype)
                assert status == 422 and "not a video file" in err["error"]
        with pytest.raises(BlockingIOError):
            listener.accept()  # FFmpeg never connected
    finally:
        listener.close()
    assert list((c.app.data / "uploads").iterdir()) == [] and c.app.names() == {}


def test_a_second_server_on_the_same_folder_refuses_and_the_first_job_finishes(
    make_client, demo_clip, tmp_path
):
    flag = tmp_path / "finish"
    c = make_client(start=False)
    c.app.worker._command = lambda job: waiting_job(flag)
    c.app.worker.start()
    _, made = c.json("POST", "/api/people?name=a", demo_clip.path.read_bytes(), "video/mp4")
    jid = made["job"]["id"]
    pid = until(lambda: c.app.store.get(jid).pid, "the job's process")
    with pytest.raises(NvpError, match="another nvp serve"):
        App(c.app.data)
    proc = subprocess.run(
        [sys.executable, "-m", "nvp.app.cli", "serve", "--data", str(c.app.data), "--port", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith("nvp serve: error: another nvp serve (pid ")
    job = c.app.store.get(jid)
    assert job.state == "running" and job.pid == pid and not job.message
    os.kill(pid, 0)  # still there
    assert (c.app.data / "serve-token").read_text().strip() == c.token
    flag.touch()
    assert c.wait(jid)["state"] == "done"


def test_the_worker_survives_an_unexpected_exception_and_runs_the_next_job(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite")
    ended = []

    class Flaky(Worker):
        def _command(self, job):
            if job.person == "boom":
                raise RuntimeError("surprise")
            return [
                sys.executable,
                "-c",
                "import sys; sys.stderr.write('nvp x: error: it broke\\n'); sys.exit(2)"
                if job.person == "bad"
                else "pass",
            ]

    def on_done(job):
        ended.append(job.id)
        if job.person == "bad":
            raise ValueError("clean-up failed too")

    w = Flaky(store, tmp_path, on_done=on_done)
    jobs = [
        store.add(Job(f"job-{i:012x}", "dub", person, [], "out", created=i + 1))
        for i, person in enumerate(["boom", "bad", "fine"])
    ]
    w.start()
    try:
        until(lambda: len(ended) == 3, "three jobs to end", 60)
    finally:
        w.stop(wait=30)
    boom, bad, fine = (store.get(j.id) for j in jobs)
    assert boom.state == "failed" and "RuntimeError: surprise" in boom.message
    assert bad.state == "failed" and bad.message == "it broke"
    assert fine.state == "done" and ended == [j.id for j in jobs]


def test_claims_are_atomic_and_cancelling_races_are_settled(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite")
    for i in range(20):
        store.add(Job(f"job-{i:012x}", "dub", "p", [], "out", created=i + 1))
    claimed: list[str] = []

    def claim_all():
        while (job := JobStore(store.path).claim()) is not None:
            claimed.append(job.id)

    threads = [threading.Thread(target=claim_all) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(claimed) == [f"job-{i:012x}" for i in range(20)]  # each once
    # a cancel between the claim and the start: the job never starts and ends cancelled
    store2 = JobStore(tmp_path / "two.sqlite")
    started = []

    class Recording(Worker):
        def _command(self, job):
            started.append(job.id)
            return [sys.executable, "-c", "pass"]

    w = Recording(store2, tmp_path, on_done=lambda job: None)
    job = store2.add(Job("job-000000000001", "dub", "p", [], "out"))
    claimed_job = store2.claim()
    assert w.cancel(job.id)  # running in the store, not started yet
    w._run(claimed_job)
    assert store2.get(job.id).state == "cancelled" and started == []
    assert not w.cancel(job.id)  # ended: nothing to cancel
    # a job that ended is never overwritten by a late end
    assert not w._end(job.id, "done")
    assert store2.get(job.id).state == "cancelled"
    # a job claimed as the server stops goes back to the queue unstarted
    w.stopping.set()
    late = store2.add(Job("job-000000000002", "dub", "p", [], "out"))
    w._run(store2.claim())
    assert store2.get(late.id).state == "queued" and started == []


@pytest.mark.parametrize("entry", ["nvp.app.cli.job", "nvp.app.jobs"])  # the entry and its former name
def test_recovery_stops_only_the_jobs_own_leftover_process(tmp_path, entry):
    store = JobStore(tmp_path / "jobs.sqlite")
    stranger = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True
    )
    mine = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; time.sleep(120)", entry, "job-000000000002"],
        start_new_session=True,
    )
    try:
        store.add(Job("job-000000000001", "fit", "p", [], "out", state="running", pid=stranger.pid))
        store.add(Job("job-000000000002", "fit", "p", [], "out", state="running", pid=mine.pid))
        w = Worker(store, tmp_path, grace_s=10)
        assert w.recover() == ["job-000000000001", "job-000000000002"]
        assert stranger.poll() is None  # a reused pid is not ours to stop
        assert mine.wait(timeout=30) is not None
        assert {j.state for j in store.all()} == {"queued"}
    finally:
        for p in (stranger, mine):
            p.kill()
            p.wait()


def test_a_job_process_cleans_up_after_sigterm(tmp_path):
    ready = tmp_path / "ready"
    code = f"""
import sys, tempfile, time
from pathlib import Path
from nvp.app.cli.job import run_command

def main(argv):
    try:
        with tempfile.TemporaryDirectory(dir={str(tmp_path)!r}) as tmp:
            (Path(tmp) / "half-written.mp4").write_bytes(b"x")
            Path({str(ready)!r}).write_text(tmp)
            time.sleep(120)
    except KeyboardInterrupt:
        print("nvp say: interrupted", file=sys.stderr)
        return 130
    return 0

sys.exit(run_command([], main))
"""
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True)
    try:
        tmp = Path(until(lambda: ready.exists() and ready.read_text(), "the job to start", 60))
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 130 and "interrupted" in proc.stderr.read()
        assert not tmp.exists()
    finally:
        proc.kill()
        proc.wait()


def test_a_cluster_job_process_stops_when_its_worker_is_gone(tmp_path):
    """``python -m nvp.app.cli.job cluster <pid> ...`` outlives no worker: a stand-in worker (a shell)
    starts a job process and exits; the job is interrupted as on Ctrl-C and cleans up. Wrong usage of the
    entry is one line and exit 2."""
    bad = subprocess.run([sys.executable, "-m", "nvp.app.cli.job", "job"], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.startswith("usage:") and len(bad.stderr.splitlines()) == 1
    done = tmp_path / "interrupted"
    job = f"""
import os, sys, time
from pathlib import Path
from nvp.app.cli.job import run_command, stop_without

def main(argv):
    try:
        time.sleep(120)
    except KeyboardInterrupt:
        Path({str(done)!r}).write_text("cleaned up")
        return 130
    return 0

stop_without(os.getppid())
sys.exit(run_command([], main))
"""
    worker = f"{shlex.quote(sys.executable)} -c {shlex.quote(job)} & sleep 2"
    subprocess.run(["sh", "-c", worker], check=True, timeout=60)
    assert until(lambda: done.exists() and done.read_text(), "the job to stop", 30) == "cleaned up"


def test_say_text_is_never_an_option_and_limits_are_clear(make_client, demo_clip, tmp_path):
    c = make_client(start=False, limits=Limits(max_queue=1, max_video_minutes=0.01, min_free_mb=1e9))
    pid = "p-00000000000a"
    (c.app.data / "people" / pid).mkdir()
    (c.app.data / "people" / pid / "bundle.json").write_text("{}")
    c.app._save_names({pid: {"name": "a", "created": 0.0}})
    status, job = c.json("POST", f"/api/people/{pid}/say", b'{"text": "--help me"}', "application/json")
    assert status == 201
    args = c.app.store.get(job["id"]).args
    assert args[0] == "say" and args[-2:] == ["--", "--help me"]
    assert c.json("POST", f"/api/people/{pid}/say", b'{"text": "hi"}', "text/plain")[0] == 415
    status, err = c.json("POST", f"/api/people/{pid}/say", b'{"text": "again"}', "application/json")
    assert status == 429 and "limit" in err["error"]  # one job queued: the queue is full
    c.app.worker.cancel(job["id"])
    status, err = c.json("POST", "/api/people?name=x", demo_clip.path.read_bytes(), "video/mp4")
    assert status == 413 and "disk" in err["error"]
    c.app.limits = replace(c.app.limits, min_free_mb=0)
    status, err = c.json("POST", "/api/people?name=x", demo_clip.path.read_bytes(), "video/mp4")
    assert status == 413 and "minutes" in err["error"]  # 1.2 s > 0.6 s
    assert list((c.app.data / "uploads").iterdir()) == []


def test_a_dub_or_say_with_eye_contact_asks_for_it_and_nothing_else(make_client):
    c = make_client(start=False)
    pid = "p-00000000000b"
    (c.app.data / "people" / pid).mkdir()
    (c.app.data / "people" / pid / "bundle.json").write_text("{}")
    c.app._save_names({pid: {"name": "b", "created": 0.0}})
    body = b'{"text": "hello", "gaze": "camera"}'
    status, job = c.json("POST", f"/api/people/{pid}/say", body, "application/json")
    assert status == 201 and c.app.store.get(job["id"]).args[-4:-2] == ["--gaze", "camera"]
    c.app.worker.cancel(job["id"])
    wav = io.BytesIO()
    sf.write(wav, np.zeros(8000, np.float32), 16000, format="WAV")
    status, job = c.json("POST", f"/api/people/{pid}/dubs?gaze=camera", wav.getvalue(), "audio/wav")
    assert status == 201, job
    assert c.app.store.get(job["id"]).args[-2:] == ["--gaze", "camera"]
    c.app.worker.cancel(job["id"])
    # a gaze file would name a file on the server: only footage or camera, refused before any upload
    for bad in ("%2Fetc%2Fpasswd", "left"):
        status, err = c.json("POST", f"/api/people/{pid}/dubs?gaze={bad}", b"RIFF....", "audio/wav")
        assert status == 400 and "footage or camera" in err["error"]
    status, err = c.json(
        "POST", f"/api/people/{pid}/say", b'{"text": "hi", "gaze": "/x.csv"}', "application/json"
    )
    assert status == 400 and "footage or camera" in err["error"]
    assert list((c.app.data / "uploads").iterdir()) == []


def test_idle_and_surplus_connections_are_closed(make_client):
    """A connection beyond ``max_connections`` is answered 503 at once; an idle one is closed after the
    server's timeout. No margin of wall time: the slots are held by connections whose timeout cannot pass
    during the check, and the closing is awaited (the read returns when the server closes)."""
    c = make_client(start=False, limits=Limits(request_timeout_s=DEADLINE, max_connections=2))
    idle = [socket.create_connection(("127.0.0.1", c.port), timeout=30) for _ in range(2)]
    try:
        idle[0].sendall(b"GET / HTTP/1.0\r\nHost: ")  # half a request, then nothing
        until(lambda: c.server._slots._value == 0, "both connections to be taken", 30)
        with socket.create_connection(("127.0.0.1", c.port), timeout=30) as third:
            answer = third.recv(4096)
        assert answer.startswith(b"HTTP/1.0 503") and b'"error"' in answer
    finally:
        for s in idle:
            s.close()
    until(lambda: c.server._slots._value == 2, "the slots to be given back", 30)
    c.server.RequestHandlerClass.timeout = 0.2  # connections from now on: a short timeout
    idle = [socket.create_connection(("127.0.0.1", c.port), timeout=30) for _ in range(2)]
    try:
        idle[0].sendall(b"GET / HTTP/1.0\r\nHost: ")
        for s in idle:  # the server closes them after its timeout
            assert s.recv(4096) == b""
    finally:
        for s in idle:
            s.close()
    assert c.json("GET", "/api/people")[0] == 200


def _pick(rng: random.Random, good: list, odd: list, p_odd: float = 0.2):
    """Mostly one of ``good``, sometimes one of ``odd``."""
    return rng.choice(odd if rng.random() < p_odd else good)


def _fuzz_requests(c: Client, rng: random.Random, n: int) -> list[bytes]:
    """``n`` raw requests, each mostly well-formed with a few odd parts: methods, targets, versions,
    headers (Host, token, Origin, types, lengths, encodings, ranges), bodies."""
    pid, jid = "p-000000000000", "job-000000000000"
    methods = (
        ["GET", "POST", "DELETE", "HEAD"],
        ["PUT", "PATCH", "OPTIONS", "TRACE", "get", "G\x00T", "A" * 300],
    )
    targets = (
        [
            "/",
            "/api/people",
            "/api/jobs",
            "/api/people?name=x",
            "/api/people?name=%ff%fe%00&minutes=nan",
            "/api/people?minutes=1e308",
            f"/api/people/{pid}",
            f"/api/people/{pid}/say",
            f"/api/people/{pid}/dubs",
            f"/api/people/{pid}/thumbnail.jpg",
            f"/api/jobs/{jid}",
            f"/api/jobs/{jid}/cancel",
            f"/api/jobs/{jid}/result.mp4",
            f"/api/jobs/{jid}/preview.png",
        ],
        [
            "/api/people?" + "&".join(f"a{i}=1" for i in range(50)),
            "/api/people/%2e%2e/thumbnail.jpg",
            "/api/people/../../x",
            "//etc/passwd",
            "http://evil.example/api/people",
            "*",
            "/%00",
            "/\u00e9\u4e2d",
            "/api/" + "a" * 9000,
            "/api",
            "/api/people/\\..\\..",
            "/index.html",
            "/?token=x",
            "/api/jobs?token=",
            "/serve-token",
            "/jobs.sqlite",
        ],
    )
    versions = (["HTTP/1.0", "HTTP/1.1"], ["HTTP/2.0", "HTTP/0.9", "HTTP/1.1x", "", "FOO/1.0"])
    hosts = (
        [c.host, f"localhost:{c.port}", f"[::1]:{c.port}"],
        ["evil.example", None, "", "127.0.0.1:99999999", "a b", "localhost:abc", "\u00e9.example"],
    )
    tokens = ([c.token], [None, "wrong", "", c.token + "x", "\u00e9" * 40])
    odd_origins = ["http://evil.example", "null", "\x01", "http://127.0.0.1:1"]
    ctypes = (
        ["video/mp4", "audio/wav", "application/json", "video/x-matroska"],
        [
            None,
            "text/plain",
            "multipart/form-data; boundary=--",
            "video/mp4; charset=\u00ff",
            "",
            "application/x-mpegurl",
            "application/octet-stream",
        ],
    )
    bodies = (
        [
            b"",
            b"{}",
            b'{"text": "hi"}',
            b'{"text": "-rf /", "voice": "../x"}',
            bytes(rng.getrandbits(8) for _ in range(3000)),
            b"RIFF\x24\x00\x00\x00WAVEfmt ",
            b"\x00\x00\x00\x18ftypmp42" + b"\x00" * 64,
        ],
        [
            b"[" * 5000,
            b"\xff\xfe\x00garbage",
            b'{"text": "' + b"x" * 3000 + b'"}',
            b'{"text": 5}',
            b"null",
            b"#EXTM3U\n#EXT-X-TARGETDURATION:1\n#EXTINF:1,\nhttp://127.0.0.1:9/x.ts\n",
            b"ffconcat version 1.0\nfile '/etc/passwd'\n",
            b"\x1f\x8b\x08\x00" + b"\x00" * 50,
            b"\x1a\x45\xdf\xa3" * 9,
        ],
    )
    extras = [
        "Transfer-Encoding: chunked",
        "Content-Encoding: gzip",
        "Range: bytes=5-1",
        "Range: bytes=-0",
        "Range: bytes=99999999999999999999-",
        "Range: items=0-1",
        "Range: bytes=0-1,3-4",
        "Expect: 100-continue",
        "Sec-Fetch-Site: cross-site",
        "Sec-Fetch-Site: same-site",
        "Authorization: Bearer " + "x" * 100,
        "X-Long: " + "y" * 70000,
        "Bad Header Line",
        "\u00e9: \u00e9",
        "Connection: keep-alive",
        "Upgrade: websocket",
        f"Host: {c.host}",
        "Origin: http://evil.example",
        f"X-NVP-Token: {c.token}",
    ]
    out = []
    for _ in range(n):
        body = _pick(rng, *bodies)
        method, target = _pick(rng, *methods), _pick(rng, *targets)
        if rng.random() < 0.35:  # a third are uploads or texts, to reach the body checks
            method, target = (
                "POST",
                rng.choice(["/api/people?name=x", "/api/people", f"/api/people/{pid}/say"]),
            )
        lines = [f"{method} {target} {_pick(rng, *versions, 0.1)}".rstrip()]
        host = _pick(rng, *hosts, 0.1)
        origin = _pick(rng, [None, None, f"http://{host}"], odd_origins, 0.1)
        for name, value in (
            ("Host", host),
            ("X-NVP-Token", _pick(rng, *tokens, 0.15)),
            ("Origin", origin),
            ("Content-Type", _pick(rng, *ctypes)),
        ):
            if value is not None:
                lines.append(f"{name}: {value}")
        length = _pick(
            rng,
            [str(len(body))],
            [
                None,
                str(len(body) + 100),
                "-1",
                "abc",
                "99999999999999",
                "0x10",
                f"{len(body)}, {len(body)}",
                " 1",
            ],
        )
        if length is not None:
            lines.append(f"Content-Length: {length}")
        lines += rng.sample(extras, k=rng.choice([0, 0, 0, 1, 2]))
        raw = ("\r\n".join(lines) + "\r\n\r\n").encode("utf-8", "surrogateescape")
        if rng.random() < 0.05:
            raw = raw.replace(b"\r\n", b"\n")
        if rng.random() < 0.05:
            raw = raw[: rng.randrange(1, len(raw))]  # cut short
        out.append(raw + body)
    return out


def _exchange(port: int, raw: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        try:
            s.sendall(raw)
            s.shutdown(socket.SHUT_WR)
        except OSError:
            pass  # the server may answer and close before reading everything
        chunks = []
        while True:
            try:
                chunk = s.recv(65536)
            except ConnectionResetError:
                break
            if not chunk:
                break
            chunks.append(chunk)
    return b"".join(chunks)


def test_fuzzing_a_live_server_gets_well_formed_answers_and_changes_nothing(make_client):
    c = make_client(start=False, limits=Limits(max_upload_mb=1, request_timeout_s=5))
    before = snapshot(c.app.data)
    requests = _fuzz_requests(c, random.Random(47), 360)
    start = time.monotonic()
    statuses: dict[int, int] = {}
    for raw in requests:
        answer = _exchange(c.port, raw)
        if not answer:
            continue  # the connection was closed without an answer (a request that never ended)
        head, _, body = answer.partition(b"\r\n\r\n")
        status_line = head.split(b"\r\n", 1)[0]
        assert status_line[:9] in (b"HTTP/1.0 ", b"HTTP/1.1 ") and status_line[9:12].isdigit(), (
            raw[:200],
            answer[:200],
        )
        status = int(status_line[9:12])
        statuses[status] = statuses.get(status, 0) + 1
        assert status < 500 or status in (501, 503, 505), (raw[:200], answer[:300])
        if status >= 400 and body:
            message = json.loads(body)["error"]
            assert isinstance(message, str) and message and str(c.app.data) not in message
        assert b"Traceback" not in answer
    assert time.monotonic() - start < 240
    assert sum(statuses.values()) > 300 and set(statuses) - {200}, statuses
    assert c.call("GET", "/")[0] == 200 and c.json("GET", "/api/people")[0] == 200  # still up
    assert snapshot(c.app.data) == before  # nothing added, changed or removed
    assert c.app.store.all() == []


def test_the_parts_of_a_cancelled_or_failed_dub_are_removed(make_client):
    from nvp.app.dub import parts_folder

    app = make_client(start=False).app
    out = app.data / "dubs" / "job-x.mp4"
    for kind, state, kept in [("dub", "cancelled", False), ("say", "failed", False), ("dub", "done", True)]:
        parts_folder(out).mkdir(parents=True, exist_ok=True)
        (parts_folder(out) / "part-00000.mp4").write_bytes(b"x")
        (out.parent / ".job-x.nvp-123-abcd.tmp.mp4").write_bytes(b"x")
        upload = app.data / "uploads" / "up-000000000000"
        upload.write_bytes(b"x")
        app._ended(Job("job-x", kind, "p-1", ["dub", str(upload)], str(out), state=state))
        assert parts_folder(out).exists() == kept and not upload.exists()
        assert (out.parent / ".job-x.nvp-123-abcd.tmp.mp4").exists() == kept


def test_the_folder_lock_is_exclusive_and_released(tmp_path):
    first = FolderLock(tmp_path)
    first.acquire()
    second = FolderLock(tmp_path)
    with pytest.raises(NvpError, match=f"pid {os.getpid()}"):
        second.acquire()
    first.release()
    second.acquire()
    second.release()
