"""renderer.register: the tracked head moved to where the renderer sees it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_lipflow import _shifted, _texture

from renderer.register import MAX_SHIFT, frame_offset, registered
from tracking.synthetic import synthetic_tracked


def test_frame_offset_measures_how_far_the_render_lies_from_the_footage():
    crop = _texture(192)
    render = _shifted(crop, -0.6, 0.35)  # the render shows everything 0.6 px left of and 0.35 px below it
    region = np.zeros((192, 192), bool)
    region[30:160, 30:160] = True
    np.testing.assert_allclose(frame_offset(crop, render, region), [0.6, -0.35], atol=0.1)
    # a far one is shortened to the longest taken
    far = frame_offset(crop, _shifted(crop, -6.0, 0.0), region)
    np.testing.assert_allclose(far, [MAX_SHIFT * 192, 0.0], atol=0.05)
    # too little to measure: no offset
    tiny = np.zeros_like(region)
    tiny[:5, :5] = True
    assert np.isnan(frame_offset(crop, render, tiny)).all()


def test_registered_moves_the_projected_face_by_the_offsets(face_model):
    seq = replace(synthetic_tracked(face_model, frames=4), info={"tracker": "test"})  # a turned, posed face
    offsets = np.array([[0.5, -0.25], [0.0, 0.0], [np.nan, np.nan], [-1.5, 1.0]])
    out = registered(seq, face_model, offsets)
    frames = np.arange(seq.num_frames)
    before, after = (s.pixels(s.camera_vertices(face_model, frames)) for s in (seq, out))
    moved = after - before
    # on average exactly; the face's nearest and farthest points within 20 % of it (perspective)
    np.testing.assert_allclose(moved.mean(1), np.nan_to_num(offsets), atol=0.01)
    spread = np.abs(moved - np.nan_to_num(offsets)[:, None]).max(1)
    assert (spread <= 0.2 * np.abs(np.nan_to_num(offsets)) + 1e-3).all()
    np.testing.assert_array_equal(out.translation[1:3], seq.translation[1:3])  # zero, unmeasured: as tracked
    np.testing.assert_array_equal(out.expression, seq.expression)
    assert out.info["tracker"] == "test" and out.info["registration"]["frames"] == 2
    with pytest.raises(ValueError, match="offsets"):
        registered(seq, face_model, offsets[:2])
