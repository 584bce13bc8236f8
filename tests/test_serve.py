"""nvp serve: the JSON API on tiny synthetic data — uploads, the job lifecycle, cancelling, recovery after a
restart, bad uploads and path-traversal attempts."""

from __future__ import annotations

import json
import os
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
import soundfile as sf
from test_pipeline import speechlike

from nvp.app.jobs import parse_progress
from nvp.app.serve import App, make_server


class Client:
    def __init__(self, app: App) -> None:
        self.app = app
        self.server = make_server(app, "127.0.0.1", 0)
        self.base = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.app.worker.stop()

    def call(self, method: str, path: str, body: bytes | None = None, ctype: str | None = None, headers=None):
        req = urllib.request.Request(self.base + path, data=body, method=method, headers=headers or {})
        if ctype:
            req.add_header("Content-Type", ctype)
        try:
            with urllib.request.urlopen(req, timeout=60) as r:
                return r.status, r.read(), dict(r.headers)
        except urllib.error.HTTPError as e:
            return e.code, e.read(), dict(e.headers)

    def json(self, method: str, path: str, body=None, ctype=None):
        status, data, _ = self.call(method, path, body, ctype)
        return status, json.loads(data)

    def wait(self, job: str, states=("done", "failed", "cancelled"), timeout: float = 300) -> dict:
        end = time.time() + timeout
        while time.time() < end:
            _, j = self.json("GET", f"/api/jobs/{job}")
            if j["state"] in states:
                return j
            time.sleep(0.3)
        raise AssertionError(f"job {job} still {j['state']} after {timeout} s")


@pytest.fixture
def make_client(tmp_path):
    made = []

    def make(**kw) -> Client:
        app = App(tmp_path / "data", extra_fit_args=kw.pop("fit_args", ("--steps", "2")), **kw)
        c = Client(app)
        app.worker.start()
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()


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
    _, people = c.json("GET", "/api/people")
    assert [p["status"] for p in people] == ["ready"] and people[0][
        "name"
    ] == "Ann <b>"  # stored, escaped by the page
    assert people[0]["info"]["size"] == "256x256"
    status, jpg, headers = c.call("GET", f"/api/people/{pid}/thumbnail.jpg")
    assert status == 200 and jpg[:2] == b"\xff\xd8" and headers["Content-Type"] == "image/jpeg"
    wav = tmp_path / "s.wav"
    sf.write(wav, speechlike(1.0), 22050)
    status, job = c.json("POST", f"/api/people/{pid}/dubs", wav.read_bytes(), "audio/wav")
    assert status == 201
    done = c.wait(job["id"])
    assert done["state"] == "done" and "SYNTHETIC MEDIA" in done["mark"]
    status, mp4, headers = c.call("GET", done["result"])
    assert status == 200 and mp4[4:8] == b"ftyp" and headers["Accept-Ranges"] == "bytes"
    status, part, headers = c.call("GET", done["result"], headers={"Range": "bytes=4-7"})
    assert status == 206 and part == b"ftyp" and headers["Content-Range"] == f"bytes 4-7/{len(mp4)}"
    status, page, _ = c.call("GET", "/")
    assert status == 200 and b"<title>nvp" in page
    # a person with a job in progress cannot be removed; a finished one can, with their files
    status, _ = c.json("DELETE", f"/api/people/{pid}")
    assert status == 200 and not (c.app.data / "people" / pid).exists()
    assert c.json("GET", "/api/people")[1] == []


def test_cancel_and_recovery_after_a_restart(make_client, demo_clip):
    c = make_client(fit_args=("--budget-minutes", "10"))
    video = demo_clip.path.read_bytes()
    _, first = c.json("POST", "/api/people?name=a", video, "video/mp4")
    _, second = c.json("POST", "/api/people?name=b", video, "video/mp4")
    j1, j2 = first["job"]["id"], second["job"]["id"]
    assert c.json("GET", f"/api/jobs/{j2}")[1]["state"] == "queued"  # one job at a time
    running = c.wait(j1, states=("running",))
    pid = c.app.store.get(j1).pid
    assert running["state"] == "running" and pid > 0
    assert c.json("POST", f"/api/jobs/{j2}/cancel")[0] == 200  # queued: never starts
    assert c.json("GET", f"/api/jobs/{j2}")[1]["state"] == "cancelled"
    assert c.json("POST", f"/api/jobs/{j2}/cancel")[0] == 409  # already ended
    # the server stops while the fit runs: the job stays "running"; a new server queues it again
    c.close()
    assert c.app.store.get(j1).state == "running"
    app = App(c.app.data, extra_fit_args=("--steps", "2"))
    assert app.requeued == [j1] and app.store.get(j1).state == "queued"
    with pytest.raises(ProcessLookupError):
        for _ in range(50):  # the old subprocess is gone
            os.kill(pid, 0)
            time.sleep(0.1)
    c2 = Client(app)
    app.worker.start()
    try:
        assert c2.wait(j1, states=("running",))["state"] == "running"
        assert c2.json("POST", f"/api/jobs/{j1}/cancel")[0] == 200
        assert c2.wait(j1)["state"] == "cancelled"
    finally:
        c2.close()


def test_bad_uploads_and_path_traversal_are_refused(make_client, tmp_path):
    c = make_client(max_upload_mb=0.01)
    status, err = c.json("POST", "/api/people?name=x", b"not a video at all" * 10, "video/mp4")
    assert status == 422 and "not a usable video" in err["error"]
    status, err = c.json("POST", "/api/people?name=x", b"x" * 20000, "video/mp4")
    assert status == 413 and "limit" in err["error"]
    status, err = c.json("POST", "/api/people?name=x", b"<html>", "text/html")
    assert status == 415
    wav = tmp_path / "mute.wav"
    sf.write(wav, np.zeros(800, np.float32), 16000)
    # a silent "video" (an audio file) for a fit: refused, nothing kept
    status, err = c.json("POST", "/api/people?name=x", wav.read_bytes(), "video/mp4")
    assert status == 422
    assert list((c.app.data / "uploads").iterdir()) == []
    for path in [
        "/api/people/../../etc/passwd/thumbnail.jpg",
        "/api/people/..%2F..%2Fetc/thumbnail.jpg",
        "/api/jobs/..%2fjobs.sqlite/result.mp4",
        "/api/jobs/job-000000000000/result.mp4",
        "/api/jobs/../jobs.sqlite",
        "/etc/passwd",
        "/jobs.sqlite",
    ]:
        status, data, _ = c.call("GET", path)
        assert status == 404 and json.loads(data).keys() == {"error"}, path
    status, err = c.json("POST", "/api/people/p-000000000000/say", b'{"text": "hi"}', "application/json")
    assert status == 404
    status, err = c.json("DELETE", "/api/people/..")
    assert status == 404


def test_the_parts_of_a_cancelled_or_failed_dub_are_removed(tmp_path):
    from nvp.app.dub import parts_folder
    from nvp.app.jobs import Job

    out = tmp_path / "dubs" / "job-x.mp4"
    for kind, state, kept in [("dub", "cancelled", False), ("say", "failed", False), ("dub", "done", True)]:
        parts_folder(out).mkdir(parents=True, exist_ok=True)
        (parts_folder(out) / "part-00000.mp4").write_bytes(b"x")
        App._ended(Job("job-x", kind, "p-1", ["dub"], str(out), state=state))
        assert parts_folder(out).exists() == kept
