"""Shared fixtures: tiny synthetic data made in code."""

from __future__ import annotations

import pytest

from nvp.face_model import default_face_model
from tracking.synthetic import synthetic_sequence


@pytest.fixture(scope="session")
def face_model():
    return default_face_model()


@pytest.fixture(scope="session")
def synthetic():
    return synthetic_sequence


@pytest.fixture(scope="session")
def demo_clip(tmp_path_factory):
    """A 1.2 s, 256x256 talking clip (mp4 with audio) animated from the astronaut photo."""
    from nvp.app.demo_clip import make_demo_clip

    path = tmp_path_factory.mktemp("demo") / "clip.mp4"
    return make_demo_clip(path, seconds=1.2, size=256)


@pytest.fixture
def torchrun(tmp_path):
    """``torchrun(script, *args)``: the script run as two local processes under torchrun, one thread each,
    the repository importable; it must exit 0, else the failure shows each rank's own output (torchrun's
    summary of a rank killed by a signal names no cause). Returns the ranks' stdout, rank 0 first."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    def run(script, *args) -> list[str]:
        logs = tmp_path / "ranks"
        cmd = [Path(sys.executable).with_name("torchrun"), "--standalone", "--nproc_per_node", "2"]
        cmd += ["--log-dir", logs, "--redirects", "3", script, *args]
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parents[1])}
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
        ranks = [f"{p}:\n{p.read_text()[-1500:]}" for p in sorted(logs.rglob("*.log"))]
        assert proc.returncode == 0, f"torchrun: {proc.stderr[-1500:]}\n" + "\n".join(ranks)
        return [p.read_text() for p in sorted(logs.rglob("stdout.log"), key=lambda p: p.parent.name)]

    return run
