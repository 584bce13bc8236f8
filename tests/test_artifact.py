"""The artifact format: one commit point, flushed to the disk; a save killed anywhere leaves a whole pair."""

from __future__ import annotations

import os

import numpy as np
import pytest

from nvp import artifact
from nvp.artifact import load_artifact, save_artifact, write_json


class Killed(BaseException):
    pass


def test_a_save_killed_at_any_point_leaves_the_old_pair_or_the_new_one(tmp_path, monkeypatch):
    old, new = {"x": np.arange(5)}, {"x": np.arange(7) * 2}
    real_replace, real_link = os.replace, os.link
    for point in range(20):  # before and after each rename and link of a save
        folder = tmp_path / f"k{point}"
        save_artifact(folder / "a", "thing", 1, old, {"n": 1})
        calls = []

        def step(real, *args, point=point, calls=calls):
            calls.append(1)
            if len(calls) == point // 2 + 1 and point % 2 == 0:
                raise Killed
            real(*args)
            if len(calls) == point // 2 + 1:
                raise Killed

        monkeypatch.setattr(artifact.os, "replace", lambda *a: step(real_replace, *a))
        monkeypatch.setattr(artifact.os, "link", lambda *a: step(real_link, *a))
        try:
            save_artifact(folder / "a", "thing", 1, new, {"n": 2})
            killed = False
        except Killed:
            killed = True
        monkeypatch.undo()
        got = load_artifact(folder / "a.json", "thing", 1)  # never a mismatched pair
        expected = new if got.manifest["n"] == 2 else old
        np.testing.assert_array_equal(got.arrays["x"], expected["x"])
        if not killed:
            assert point >= 2 * len(calls)
            break
        save_artifact(folder / "a", "thing", 1, new, {"n": 3})  # the next save cleans up after the killed one
        assert sorted(p.name for p in folder.iterdir() if not p.name.endswith(".tmp.json")) == [
            "a.json",
            "a.npz",
        ]
    else:
        pytest.fail("the save never finished")


def test_writes_are_flushed_to_the_disk_before_and_after_the_rename(tmp_path, monkeypatch):
    flushed = []
    real = artifact.fsync_path
    monkeypatch.setattr(artifact, "fsync_path", lambda p: (flushed.append(p), real(p)))
    write_json(tmp_path / "m.json", {"a": 1})
    assert flushed[0].name.startswith(".m.json") and flushed[1] == tmp_path  # the file, then its folder
