"""The person's own mouth interiors (renderer.mouths): which frames a bank keeps, which entry a frame gets."""

from __future__ import annotations

import numpy as np

from renderer.mouths import (
    LIGHT_CM,
    LIGHT_TOLERANCE,
    EntryChooser,
    MouthBank,
    bank_frames,
    best_path,
    light_colour,
    light_costs,
)


def test_a_bank_keeps_open_mouths_spread_over_their_shapes():
    rng = np.random.default_rng(0)
    t = 400
    gaps = np.abs(rng.normal(0, 0.2, t))
    gaps[:200] = 0.02  # half the time closed
    shapes = rng.normal(0, 0.01, (t, 20, 3)) + gaps[:, None, None] * np.linspace(-1, 1, 20)[None, :, None]
    valid = np.ones(t, bool)
    valid[250:260] = False
    chosen = bank_frames(shapes, gaps, valid, entries=16)
    assert len(chosen) == 16 and (np.diff(chosen) > 0).all()
    lo, hi = np.percentile(gaps[valid], [5, 95])
    assert (gaps[chosen] > lo + 0.25 * (hi - lo)).all() and valid[chosen].all()
    assert int(np.argmax(gaps * valid)) in chosen  # the widest-open frame, then the farthest shapes
    assert np.ptp(gaps[chosen]) > 0.5 * np.ptp(gaps[valid & (gaps > lo + 0.25 * (hi - lo))])
    assert len(bank_frames(shapes, np.full(t, 0.1), valid)) == 0  # the mouth never opens
    assert len(bank_frames(shapes, gaps, np.zeros(t, bool))) == 0


def test_entries_follow_the_nearest_shape_without_flicker():
    # two entries nearly equally near for 20 frames (noise decides), then entry 2 clearly nearest
    rng = np.random.default_rng(1)
    d = np.full((30, 3), 1.0)
    d[:20, 0] = 0.10 + rng.normal(0, 0.005, 20)
    d[:20, 1] = 0.10 + rng.normal(0, 0.005, 20)
    d[20:, 2] = 0.0
    nearest = d.argmin(1)
    assert (np.diff(nearest[:20]) != 0).sum() >= 5  # per-frame nearest flickers
    path = best_path(d, switch=0.05)
    assert len(set(path[:20])) == 1 and (path[20:] == 2).all()
    np.testing.assert_array_equal(best_path(d, switch=0.0), nearest)
    # a stream that fixes each frame's entry 6 frames later, from the entry before it, chooses the same
    for lag in (6, 40):
        chooser = EntryChooser(lag, switch=0.05)
        streamed = [e for row in d for e in chooser.push(row)]
        assert len(streamed) == max(0, len(d) - lag)
        np.testing.assert_array_equal(streamed + chooser.flush(), path)
    # the switch before the first frame counts from the entry a stream is on
    assert best_path(np.array([[0.03, 1.0, 0.0]]), start=0, switch=0.05)[0] == 0
    assert best_path(np.array([[0.03, 1.0, 0.0]]), start=None, switch=0.05)[0] == 2


def test_a_bank_saves_and_loads(tmp_path):
    rng = np.random.default_rng(3)
    bank = MouthBank(
        frames=np.array([3, 9]),
        patches=rng.integers(0, 255, (2, 8, 8, 3), dtype=np.uint8),
        pixels=rng.normal(size=(2, 468, 2)).astype(np.float32),
        shapes=rng.normal(size=(2, 20, 3)).astype(np.float32),
    )
    bank.save(tmp_path / "mouths")
    back = MouthBank.load(tmp_path / "mouths.json")
    for k in ("frames", "patches", "pixels", "shapes"):
        np.testing.assert_array_equal(getattr(back, k), getattr(bank, k))
    d = back.distances(bank.shapes)
    assert d.shape == (2, 2) and np.allclose(np.diag(d), 0) and d[0, 1] == d[1, 0] > 0


def test_a_stream_without_lookahead_keeps_its_entry_until_another_is_clearly_nearer():
    chooser = EntryChooser(0, switch=0.05)
    assert chooser.push(np.array([0.3, 0.2, 0.1])) == [2]
    assert chooser.push(np.array([0.3, 0.1, 0.12])) == [2]  # within the switch cost: kept
    assert chooser.push(np.array([0.3, 0.1, 0.2])) == [1]
    assert chooser.push(np.array([np.inf, 0.3, np.inf])) == [1]  # entries not compared cost infinity
    assert chooser.flush() == []


def test_an_entry_shot_in_other_light_is_used_only_when_no_other_shape_comes_near(tmp_path):
    # a footage cut from a daylight take (frames 0-99) and a magenta-lit one (100-199); entries at 10, 40
    # (daylight) and 110, 140 (magenta); the lips' colour recorded every 5th frame
    daylight, magenta = np.array([180.0, 110.0, 110.0]), np.array([175.0, 105.0, 170.0])
    light = np.arange(0, 200, 5)
    bank = MouthBank(
        frames=np.array([10, 40, 110, 140]),
        patches=np.zeros((4, 8, 8, 3), np.uint8),
        pixels=np.zeros((4, 6, 2), np.float32),
        shapes=np.zeros((4, 2, 3), np.float32),
        light_frames=light,
        light_colours=np.where(light[:, None] < 100, daylight, magenta).astype(np.float32),
    )
    back = MouthBank.load(bank.save(tmp_path / "mouths"))
    np.testing.assert_array_equal(back.light_frames, light)
    np.testing.assert_allclose(
        back.light_at(np.array([0, 97, 103, 199, 500])), [daylight] * 2 + [magenta] * 3
    )
    entries = bank.light_at(bank.frames)
    costs = light_costs(entries, bank.light_at(np.array([0, 45, 100, 200])))
    blue = LIGHT_CM * (np.log(170 / 110) - np.log1p(LIGHT_TOLERANCE))
    np.testing.assert_allclose(costs[:2], [[0, 0, blue, blue]] * 2)  # a daylight frame: magenta costs
    np.testing.assert_allclose(costs[2:], [[blue, blue, 0, 0]] * 2)  # and the other way round
    # within the tolerance the light costs nothing (the networks' own colour error)
    close = np.array([daylight, daylight * (1 + 0.9 * LIGHT_TOLERANCE)])
    np.testing.assert_array_equal(light_costs(close, close), 0)
    # a daylight frame whose nearest shape is a magenta entry takes the nearest daylight one instead,
    # unless the daylight shapes are far off
    here = bank.light_at(np.array([20]))
    assert np.argmin(np.array([[0.10, 0.12, 0.08, 0.20]]) + light_costs(entries, here)) == 0
    assert np.argmin(np.array([[0.60, 0.70, 0.08, 0.20]]) + light_costs(entries, here)) == 2
    # a frame's light is the median colour at the skin's vertices: a hair or a highlight does not count
    image = np.zeros((10, 10, 3), np.uint8)
    image[:] = daylight
    image[2, 3] = 255
    pixels = np.array([[3.5, 2.5], [5.2, 5.9], [7.0, 1.0]])
    np.testing.assert_array_equal(light_colour(image, pixels), daylight)
    # a bank of the first format has no light: it loads, and nothing is charged for it (FrameRenderer)
    assert len(MouthBank(bank.frames, bank.patches, bank.pixels, bank.shapes).light_frames) == 0
