"""nvp.app.cluster: nvp's jobs on a local Dask cluster on loopback (a head and workers started here, as
``nvp cluster head`` and ``nvp cluster join`` start them). Skipped without the ``cluster`` extra."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from test_pipeline import speechlike

from nvp.app import cluster, cluster_nodes
from nvp.errors import NvpError

ENV = {**os.environ, "NVP_THREADS": "1"}
"""One thread per job: two workers share the 2 cores. (These 256² dubs encode identically run to run;
``MALLOC_PERTURB_=165`` would make sure of it, docs/experiments/resume-encoding.md, but slowed them several
times here.)"""
DEADLINE = 240.0


def until(predicate, what: str, timeout: float = DEADLINE, every: float = 0.1):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = predicate()
        if got:
            return got
        time.sleep(every)
    raise AssertionError(f"timed out waiting for {what}")


def test_head_addresses_and_job_lists(tmp_path, monkeypatch):
    monkeypatch.delenv(cluster.ADDRESS_ENV, raising=False)
    assert cluster.head_address(None) is None
    assert cluster.head_address("head") == "tcp://head:8786"
    assert cluster.head_address("10.0.0.5:9000") == "tcp://10.0.0.5:9000"
    monkeypatch.setenv(cluster.ADDRESS_ENV, "tcp://h:1")
    assert cluster.head_address(None) == "tcp://h:1"
    with pytest.raises(NvpError, match="HOST or HOST:PORT"):
        cluster.head_address("tcp://h:1/x")
    jobs = tmp_path / "jobs.txt"
    jobs.write_text(
        "# a comment\n\nnvp dub 'a b.wav' --person p/ -o out/a.mp4\nsay Hi --person p/ -o s.mp4\n"
    )
    got = cluster.jobs_of_file(jobs)
    assert [j.argv for j in got] == [
        ("dub", "a b.wav", "--person", "p/", "-o", "out/a.mp4"),
        ("say", "Hi", "--person", "p/", "-o", "s.mp4"),
    ]
    assert got[0].cwd == str(tmp_path) and got[0].name.startswith("line 3") and got[0].key != got[1].key
    jobs.write_text("serve --port 1\n")
    with pytest.raises(NvpError, match="line 1: not a job"):
        cluster.jobs_of_file(jobs)


needs_extra = pytest.mark.skipif(
    importlib.util.find_spec("distributed") is None,
    reason="the cluster extra is not installed (bash scripts/setup.sh installs it)",
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalCluster:
    """A head and workers on loopback, each its own process (as on other machines)."""

    def __init__(self, folder: Path) -> None:
        self.folder, port = folder, free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        self.procs: list[subprocess.Popen] = []
        self.head = self._start(cluster_nodes.head_command("127.0.0.1", port), "head")
        self.workers: list[subprocess.Popen] = []

    def _start(self, cmd: list[str], name: str) -> subprocess.Popen:
        log = open(self.folder / f"{name}-{len(self.procs)}.log", "wb")
        p = subprocess.Popen(cmd, env=ENV, stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        self.procs.append(p)
        return p

    def join(self, n: int = 1) -> list[subprocess.Popen]:
        new = [
            self._start(cluster_nodes.join_command(self.address, host="127.0.0.1"), "worker")
            for _ in range(n)
        ]
        self.workers += new
        want = len([w for w in self.workers if w.poll() is None])
        client = cluster.connect(self.address, timeout=60)
        try:
            client.wait_for_workers(want, timeout=60)
        finally:
            client.close()
        return new

    def close(self) -> None:
        """Workers first, then the head (a worker whose head is gone retries it for half a minute); what
        has not exited 5 s after SIGTERM is killed: nothing of the test's depends on a clean exit."""
        for p in [*self.workers, self.head]:
            if p.poll() is None:
                p.terminate()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.fixture
def local_cluster(tmp_path):
    made = []

    def make() -> LocalCluster:
        c = LocalCluster(tmp_path)
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()


@pytest.fixture(scope="module")
def person(demo_clip, tmp_path_factory):
    out = tmp_path_factory.mktemp("cluster_fit") / "person"
    proc = subprocess.run(
        [sys.executable, "-m", "nvp.app.cli", "-q", "fit", str(demo_clip.path), "-o", str(out),
         "--steps", "2"],
        capture_output=True, text=True, env=ENV,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out


def children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


def decoded(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Every frame (RGB) and every audio sample of an mp4."""
    import av

    with av.open(str(path)) as c:
        frames = np.stack([f.to_ndarray(format="rgb24") for f in c.decode(video=0)])
    with av.open(str(path)) as c:
        audio = np.concatenate([f.to_ndarray().reshape(-1) for f in c.decode(audio=0)])
    return frames, audio


@needs_extra
def test_a_batch_of_dubs_survives_a_killed_worker_and_a_bad_input(person, local_cluster, tmp_path):
    audio = tmp_path / "audio"
    audio.mkdir()
    names = [f"line{i}" for i in range(6)]  # the worker is killed after two are done
    for i, name in enumerate(names):
        if i == 3:
            (audio / f"{name}.wav").write_bytes(b"RIFF, but not audio at all")
        else:
            sf.write(audio / f"{name}.wav", speechlike(1.0, seed=i), 22050)
    (audio / "lines.txt").write_text("".join(f"{n}.wav\n" for n in names))
    # one machine, as today: nvp dub --list
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "nvp.app.cli", "-q", "dub", "--list", str(audio / "lines.txt"), "--person",
         str(person), "-o", str(tmp_path / "here")],
        capture_output=True, text=True, env=ENV,
    )  # fmt: skip
    embedded_s = time.perf_counter() - t0
    assert proc.returncode == 2 and "5 of 6 dubbed" in proc.stdout, proc.stderr
    # the same on a 2-worker cluster, one worker killed (SIGKILL: its machine died) while it runs a job
    c = local_cluster()
    w0, _ = c.join(2)
    out = tmp_path / "there"
    jobs = [
        cluster.ClusterJob(
            str(audio / f"{n}.wav"),
            ("dub", str(audio / f"{n}.wav"), "--person", str(person), "-o", str(out / f"{n}.mp4")),
            str(tmp_path),
        )
        for n in names
    ]
    killed = threading.Event()

    def kill_mid_batch() -> None:
        until(lambda: out.exists() and len(list(out.glob("*.mp4"))) >= 2, "two dubs", every=0.05)
        until(lambda: children(w0.pid), "the worker to run a job", every=0.02)
        w0.send_signal(signal.SIGKILL)
        killed.set()

    killer = threading.Thread(target=kill_mid_batch, daemon=True)
    killer.start()
    t0 = time.perf_counter()
    outcomes = cluster.run_batch(jobs, c.address, progress=False)
    cluster_s = time.perf_counter() - t0
    killer.join(5)
    assert killed.is_set() and w0.wait(5) == -signal.SIGKILL
    failed = [o for o in outcomes if not o.ok]
    assert len(failed) == 1 and failed[0].job.name.endswith("line3.wav"), [o.error for o in failed]
    assert "line3.wav" in failed[0].error and "\n" not in failed[0].error
    assert any(o.attempts == 2 for o in outcomes), "the killed worker's job ran again elsewhere"
    # 9 outputs, nothing else (no duplicate, no partial or temporary file, no parts left)
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{n}.mp4" for n in names if n != "line3")
    for n in names:
        if n == "line3":
            continue
        here, there = decoded(tmp_path / "here" / f"{n}.mp4"), decoded(out / f"{n}.mp4")
        assert np.array_equal(here[0], there[0]) and np.array_equal(here[1], there[1]), n
    print(f"\n{len(names)} tiny dubs: one machine {embedded_s:.1f} s, 2 local workers {cluster_s:.1f} s")


@needs_extra
def test_serve_sends_its_dub_to_a_worker_it_did_not_start_and_requeues_it_when_that_worker_stops(
    person, local_cluster, tmp_path
):
    from test_serve import Client

    from nvp.app.serve import App

    c = local_cluster()
    (first,) = c.join(1)
    data = tmp_path / "data"
    (data / "people").mkdir(parents=True)
    shutil.copytree(person, data / "people" / "p-000000000001")
    (data / "people.json").write_text(json.dumps({"p-000000000001": {"name": "Ann", "created": 1.0}}))
    app = App(data, cluster=c.address)
    client = Client(app)
    app.worker.start()
    try:
        wav = tmp_path / "s.wav"
        sf.write(wav, speechlike(2.0), 22050)
        status, job = client.json("POST", "/api/people/p-000000000001/dubs", wav.read_bytes(), "audio/wav")
        assert status == 201 and job["state"] == "queued"
        running = client.wait(job["id"], states=("running", "done", "failed"))
        assert running["state"] == "running" and f"pid {first.pid})" in running["message"], running
        until(lambda: children(first.pid), "the job's process on the worker")
        first.send_signal(signal.SIGTERM)  # the worker stops: the job goes back to the queue
        again = client.wait(job["id"], states=("queued", "done", "failed"))
        assert again["state"] == "queued" and "queued again" in again["message"], again
        assert first.wait(60) is not None
        (second,) = c.join(1)
        done = client.wait(job["id"], timeout=DEADLINE)
        assert done["state"] == "done" and f"pid {second.pid})" in done["message"], done
        status, mp4, headers = client.call("GET", done["result"])
        assert status == 200 and mp4[4:8] == b"ftyp" and headers["Content-Type"] == "video/mp4"
        (tmp_path / "got.mp4").write_bytes(mp4)
        frames, audio = decoded(tmp_path / "got.mp4")
        assert len(frames) == 50 and len(audio) > 0  # 2 s at 25 frames/s, with its sound
        assert sorted(p.name for p in (data / "dubs").iterdir()) == [f"{job['id']}.mp4"]
        until(lambda: not any((data / "uploads").iterdir()), "the upload to go")
    finally:
        client.close()
