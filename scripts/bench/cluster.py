"""Benchmark ``nvp dub`` of a batch on one machine vs through the cluster (issue 49, docs/cluster.md).

    python -m scripts.bench.cluster --person PERSON_DIR [--jobs 10] [--seconds 1] [--workers 2]

Writes ``--jobs`` clips of ``--seconds`` of the demo's synthetic voice, dubs them with ``nvp dub --list``
(one process: the embedded default), then starts a head and ``--workers`` workers on loopback (as
``nvp cluster head`` / ``join`` start them) and sends the same dubs as one job each. Prints the wall
times, each job's process time and the dub's own time inside it (the difference: starting nvp and loading
the networks per job), and the load average before and after each run.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import soundfile as sf


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--person", type=Path, required=True, help="a person bundle (nvp fit)")
    ap.add_argument("--jobs", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=1.0, help="audio per dub")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    from nvp.app import cluster, cluster_nodes
    from nvp.app.demo_voice import speech_script, synth_voice

    tmp = Path(tempfile.mkdtemp(prefix="nvp-bench-cluster-"))
    for i in range(args.jobs):
        rng = np.random.default_rng(i)
        sf.write(
            tmp / f"d{i}.wav", synth_voice(speech_script(args.seconds, rng), args.seconds, rng, 22050), 22050
        )
    (tmp / "list.txt").write_text("".join(f"d{i}.wav\n" for i in range(args.jobs)))
    person = str(args.person.resolve())
    found = lambda text: [float(x) for x in re.findall(r"in ([\d.]+) s \(", text)]  # noqa: E731

    load0, t = os.getloadavg()[0], time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "nvp.app.cli", "-q", "dub", "--list", str(tmp / "list.txt"),
         "--person", person, "-o", str(tmp / "here")],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    embedded = {
        "wall_s": time.perf_counter() - t,
        "dub_s": found(r.stdout),
        "load": [load0, os.getloadavg()[0]],
    }

    port = 8700 + os.getpid() % 1000
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen(cluster_nodes.head_command("127.0.0.1", port), **quiet)]
    try:
        procs += [
            subprocess.Popen(cluster_nodes.join_command(address, host="127.0.0.1"), **quiet)
            for _ in range(args.workers)
        ]
        client = cluster.connect(address, timeout=60)
        client.wait_for_workers(args.workers, timeout=60)
        client.close()
        jobs = [
            cluster.ClusterJob(
                f"d{i}",
                ("dub", str(tmp / f"d{i}.wav"), "--person", person, "-o", str(tmp / "there" / f"d{i}.mp4")),
                str(tmp),
            )
            for i in range(args.jobs)
        ]
        load0, t = os.getloadavg()[0], time.perf_counter()
        outcomes = cluster.run_batch(jobs, address, progress=False)
        wall = time.perf_counter() - t
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(40)
            except subprocess.TimeoutExpired:
                p.kill()
    dubs = [found(o.stdout)[0] for o in outcomes if o.ok]
    jobs_s = [o.seconds for o in outcomes if o.ok]
    print(
        json.dumps(
            {
                "cpu": next(
                    (ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if "model name" in ln), "?"
                ),
                "cores": os.cpu_count(),
                "embedded": {**embedded, "dub_s_sum": sum(embedded["dub_s"])},
                "cluster": {
                    "workers": args.workers,
                    "wall_s": wall,
                    "ok": len(dubs),
                    "job_process_s_mean": float(np.mean(jobs_s)),
                    "dub_s_mean": float(np.mean(dubs)),
                    "start_per_job_s": float(np.mean(jobs_s) - np.mean(dubs)),
                    "load": [load0, os.getloadavg()[0]],
                },
                "extra_wall_per_job_s": (wall - embedded["wall_s"]) / args.jobs,
                "folder": str(tmp),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
