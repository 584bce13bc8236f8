"""Neural renderer: crops, texture, U-Nets, training with resume, rendering into frames (synthetic data)."""

from __future__ import annotations

import re
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nvp.media import VideoWriter, iter_frames
from renderer.crop import crop_boxes, crop_camera, cut, feather, paste, region_weight
from renderer.inputs import face_region
from renderer.networks import (
    NeuralRenderer,
    NeuralTexture,
    UNet,
    UNetConfig,
    count_parameters,
    inner_weight,
    load_renderer,
)
from renderer.preset import Preset
from renderer.train import RendererTrainConfig, train_renderer
from renderer.train_data import build_cache
from tracking.synthetic import synthetic_tracked

TINY = Preset("tiny", crop=32, base=4, dilated=False, texture_size=32, steps=2, batch=2, source_input=True)
SIZE = 96


def face_video(path, seq, face_model, colour) -> None:
    """``seq``'s frames of the face model on a grey background, the mesh coloured by ``colour(uv)``
    (``(H, W, 2)`` texture coordinates → ``(H, W, 3)`` in [0, 1])."""
    from renderer.gl import GLRasterizer

    with GLRasterizer(SIZE, SIZE) as gl, VideoWriter(path, 25.0, SIZE, SIZE) as w:
        for i in range(seq.num_frames):
            v = seq.camera_vertices(face_model, np.array([i]))[0]
            r = gl.rasterize(v, face_model.triangles, face_model.uvs, seq.focal, seq.center)
            img = np.full((SIZE, SIZE, 3), 90, np.uint8)
            col = colour(r.uv).numpy() * 255
            img[r.mask.numpy()] = col[r.mask.numpy()].astype(np.uint8)
            w.write(img)


@pytest.fixture(scope="module")
def footage(tmp_path_factory, face_model):
    """A 12-frame 96x96 video of the face model with a UV-coloured texture, and its exact tracking."""
    seq = synthetic_tracked(face_model, frames=12, size=SIZE, focal=200.0)
    path = tmp_path_factory.mktemp("footage") / "face.mp4"
    face_video(path, seq, face_model, lambda uv: torch.cat([uv, 1 - uv[..., :1]], -1))
    return path, seq


def test_crop_boxes_follow_points_and_are_smooth():
    t = np.arange(50)
    pts = np.stack([np.stack([100 + 2 * t, 80 + 0 * t], 1), np.stack([160 + 2 * t, 150 + 0 * t], 1)], 1)
    pts = pts + np.random.default_rng(0).normal(0, 2, pts.shape)
    boxes = crop_boxes(pts.astype(np.float64))
    assert boxes.shape == (50, 3)
    assert np.abs(boxes[25, 0] - (130 + 50)) < 3 and np.abs(boxes[:, 2] - 70 * 1.6).max() < 12
    assert np.abs(np.diff(boxes[:, 2])).max() < np.abs(np.diff(pts[:, 1, 0] - pts[:, 0, 0])).max()


def test_cut_and_paste_round_trip():
    frame = torch.rand(3, 120, 160) * 255
    box = np.array([70.0, 60.0, 64.0])
    crop = cut(frame[None], torch.from_numpy(box[None]).float(), 64)[0]
    # an axis-aligned 1:1 crop is an exact copy
    torch.testing.assert_close(crop, frame[:, 28:92, 38:102], atol=1e-3, rtol=0)
    back = paste(frame, crop, box, torch.ones(1, 1, 64, 64))
    torch.testing.assert_close(back, frame, atol=1e-3, rtol=0)
    other = paste(frame, torch.zeros_like(crop), box, feather(64))
    assert other[:, 60, 70].abs().max() < 1e-3  # centre replaced
    torch.testing.assert_close(other[:, :20], frame[:, :20])  # outside the box untouched


def test_a_cut_larger_than_the_crop_averages_the_footage_instead_of_point_sampling_it():
    """A box three times the crop over one-pixel stripes (stubble, lip lines at 1080p): each crop pixel is the
    mean of the three footage pixels it covers (85 or 170), not one read of them (0 or 255) that flips
    with a sub-pixel shift of the box; smooth footage is cut as before."""
    stripes = torch.zeros(1, 3, 600, 600)
    stripes[..., ::2] = 255
    crops = [cut(stripes, torch.tensor([[300.0 + dx, 300.7, 576.0]]), 192) for dx in (0.0, 0.25, 0.5)]
    for crop in crops:
        assert abs(float(crop.mean()) - 127.5) < 1 and float(crop.std()) < 43
    assert float((crops[0] - crops[2]).abs().mean()) < 43  # a single read: 127.5
    ramp = torch.linspace(0, 255, 600).expand(1, 3, 600, 600).contiguous()
    box = torch.tensor([[300.0, 300.0, 576.0]])
    exact = (torch.arange(192) + 0.5) * 3 + 12 - 0.5  # the crop pixels' centres in footage pixels
    torch.testing.assert_close(cut(ramp, box, 192)[0, 0, 5], exact * 255 / 599, atol=0.05, rtol=0)


def test_paste_region_is_the_frame_paste_under_the_box():
    from renderer.crop import paste_region

    frame = torch.rand(3, 120, 160) * 255
    crop = torch.rand(3, 64, 64) * 255
    for box in (np.array([70.0, 60.0, 64.0]), np.array([150.0, 10.0, 80.0])):  # inside / over the corner
        full, weight = paste(frame, crop, box, feather(64), with_weight=True)
        pixels, alpha, (rows, cols) = paste_region(frame, crop, box, feather(64))
        torch.testing.assert_close(full[:, rows, cols], pixels)
        torch.testing.assert_close(weight[rows, cols], alpha)
        outside = torch.ones(120, 160, dtype=torch.bool)
        outside[rows, cols] = False
        assert torch.equal(full[:, outside], frame[:, outside]) and not weight[outside].any()
    assert paste_region(frame, crop, np.array([500.0, 500.0, 64.0]), feather(64)) is None
    assert torch.equal(paste(frame, crop, np.array([500.0, 500.0, 64.0]), feather(64)), frame)


def test_paste_region_covers_exactly_the_pixels_its_weight_reaches():
    """The paste works only on the frame pixels the weight reaches (a lower face is a fraction of its
    box): the same pixels as blending the whole box, none left out."""
    import torch.nn.functional as F

    from renderer.crop import paste_region

    frame = torch.rand(3, 200, 240) * 255
    crop = torch.rand(3, 48, 48) * 255
    weight = torch.zeros(1, 1, 48, 48)
    weight[..., 30:41, 12:29] = torch.rand(11, 17)
    for box in (np.array([120.3, 95.7, 150.0]), np.array([20.0, 140.0, 97.0])):  # inside / over the edge
        pixels, alpha, (rows, cols) = paste_region(frame, crop, box, weight)
        assert rows.stop - rows.start < 80 and cols.stop - cols.start < 80  # not the whole box
        # the whole frame blended the plain way: crop and weight sampled at every pixel centre
        xs = ((torch.arange(240, dtype=torch.float32) + 0.5 - box[0]) / box[2]) * 2
        ys = ((torch.arange(200, dtype=torch.float32) + 0.5 - box[1]) / box[2]) * 2
        grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)[None]
        sampled = F.grid_sample(torch.cat([crop[None], weight], 1), grid, align_corners=False)[0]
        a = sampled[3:]
        whole = a * sampled[:3] + (1 - a) * frame
        outside = torch.ones(200, 240, dtype=torch.bool)
        outside[rows, cols] = False
        assert not a[0][outside].any()  # every pixel the weight reaches was pasted
        torch.testing.assert_close(pixels, whole[:, rows, cols])
        torch.testing.assert_close(alpha, a[0, rows, cols])
    assert paste_region(frame, crop, np.array([120.0, 95.0, 150.0]), torch.zeros(1, 1, 48, 48)) is None


def test_a_pasted_mouth_interior_meets_the_lips_over_a_footage_pixel_not_a_crop_pixel():
    """On footage four times finer than the crop, the bank's interior (here white) takes over from the render
    (black) over about one footage pixel, where the crop's mask enlarged as it is ramped over four, and the
    edge stays where that mask puts it (a little inside: ``INTERIOR_EDGE_LEVEL``); on footage as fine as the
    crop the ramp stays a crop pixel wide."""
    from renderer.crop import INTERIOR_EDGE_LEVEL, INTERIOR_EDGE_SLOPE, paste_region

    s, radius = 48, 10.3  # a disc of mouth interior in a 48² crop, centred on crop pixel 24
    centres = torch.arange(s, dtype=torch.float32) + 0.5
    yy, xx = torch.meshgrid(centres, centres, indexing="ij")
    disc = (((xx - 24) ** 2 + (yy - 24) ** 2) < radius**2).float()
    interior = (torch.full((3, 16, 16), 200.0), torch.full((32, 32, 2), 8.0), disc[8:40, 8:40], (8, 8))
    for step in (4, 1):
        side = s * step
        frame = torch.zeros(3, side + 20, side + 20)
        box = np.array([side / 2 + 10, side / 2 + 10, side])
        crop = torch.zeros(3, s, s)
        pixels, _, (rows, cols) = paste_region(frame, crop, box, torch.ones(1, 1, s, s), interior=interior)
        row = pixels[0, (side + 20) // 2 - rows.start, : (side + 20) // 2 - cols.start]  # the left half
        ramp = int(((row > 20) & (row < 180)).sum())
        # the binary mask's edge lies between the last crop pixel centre outside the disc (13.5) and the first
        # inside (14.5), at crop x = 14; the bank takes over a little inside it, at frame x = 10 + x * step
        edge = 14 + (INTERIOR_EDGE_LEVEL - 0.5) / INTERIOR_EDGE_SLOPE
        crossing = float(torch.nonzero(row >= 100)[0, 0]) + 0.5 + cols.start
        assert abs(crossing - (10 + edge * step)) <= 0.5 * step, (step, crossing)
        assert ramp <= 2, (step, ramp)  # at step 4: 3-4 pixels between 20 and 180 before


def test_paste_keeps_the_footage_detail_outside_the_replaced_region():
    torch.manual_seed(0)
    frame = torch.rand(3, 200, 200) * 255  # fine detail that a 48 px crop of a 160 px box cannot hold
    box = np.array([100.0, 100.0, 160.0])
    low = cut(frame[None], torch.from_numpy(box[None]).float(), 48)[0]
    weight = torch.ones(1, 1, 48, 48)
    region = torch.zeros(1, 1, 48, 48)
    region[..., 16:32, 16:32] = 1
    rendered = low.clone()
    rendered[:, 16:32, 16:32] = 128.0
    plain = paste(frame, rendered, box, weight)
    out = paste(frame, rendered, box, weight, detail=(low, 1 - region))
    outside = (slice(None), slice(25, 60), slice(25, 175))
    inside = (slice(None), slice(95, 105), slice(95, 105))
    err = (plain[outside] - frame[outside]).abs().mean()
    assert err > 20  # the crop-resolution copy lost the detail ...
    torch.testing.assert_close(out[outside], frame[outside], atol=1e-3, rtol=0)  # ... which comes back
    torch.testing.assert_close(out[inside], torch.full_like(out[inside], 128.0))  # nothing leaks inside


def test_crop_camera_maps_points_into_the_crop():
    f, c = crop_camera(500.0, np.array([320.0, 240.0]), np.array([300.0, 200.0, 100.0]), 50)
    x = np.array([0.02, -0.01, 1.0])  # a camera point
    full = 500.0 * x[:2] / x[2] + [320.0, 240.0]
    crop = f * x[:2] / x[2] + c
    np.testing.assert_allclose(crop, (full - [250.0, 150.0]) * 0.5, atol=1e-4)


def test_texture_sampling_is_zero_outside_the_mesh():
    tex = NeuralTexture(16, 8)
    torch.nn.init.normal_(tex.texture)
    uv = torch.rand(2, 10, 12, 2)
    mask = (torch.rand(2, 1, 10, 12) > 0.5).float()
    out = tex(uv, mask)
    assert out.shape == (2, 16, 10, 12)
    assert (out * (1 - mask)).abs().max() == 0 and (out * mask).abs().max() > 0


@pytest.mark.parametrize("dilated", [False, True])
def test_unet_shapes_and_range(dilated):
    net = UNet(7, 3, UNetConfig(base=4, dilated=dilated))
    y = net(torch.randn(2, 7, 48, 48))
    assert y.shape == (2, 3, 48, 48) and 0 <= y.min() and y.max() <= 1


def test_paper_unet_size():
    # the paper's networks: depth 5, 32 base features, about 2.35 M parameters (ours: 2.74 M)
    n = count_parameters(UNet(18, 3, UNetConfig(base=32, dilated=True)))
    assert 2.0e6 < n < 3.0e6


def test_face_region_grows_the_mask():
    mask = torch.zeros(1, 1, 50, 50)
    mask[..., 20:30, 20:30] = 1
    region = face_region(mask, grow=0.1)
    assert region[..., 15:35, 15:35].min() == 1 and region[..., :10].max() == 0


def test_region_weight_covers_the_region_and_leaves_the_rest():
    region = torch.zeros(1, 1, 100, 100)
    region[..., 40:60, 40:60] = 1
    w = region_weight(region, grow=0.03)  # 3 px: 1 within 3 px of the region, 0 from 9 px away
    assert w[..., 37:63, 37:63].min() == pytest.approx(1.0)
    assert w[..., :31, :].max() == 0 and w[..., 70:, :].max() == 0


def test_inner_weight_is_zero_on_the_silhouette_and_one_deep_inside():
    mask = torch.zeros(1, 1, 100, 100)
    mask[..., 20:80, 20:80] = 1
    w = inner_weight(mask, erode=0.02)  # 2 px: 0 on the silhouette, 1 from 5 px inside
    assert w[..., :21, :].max() == 0 and w[..., 21, 50] < 0.25
    assert w[..., 25:75, 25:75].min() == pytest.approx(1.0)
    row = w[0, 0, 50, 15:30]
    assert (row[1:] >= row[:-1]).all()  # rises monotonically into the mesh


def test_final_image_keeps_the_interior_inside_and_the_footage_outside():
    torch.manual_seed(0)
    net = NeuralRenderer(UNetConfig(base=4), texture_channels=4, texture_size=16)
    mask = torch.zeros(1, 1, 64, 64)
    mask[..., 16:48, 16:48] = 1
    uv = torch.rand(1, 64, 64, 2)
    region = face_region(mask, 0.06)
    background = torch.rand(1, 3, 64, 64) * (1 - region)
    interior, final = net(uv, mask, torch.zeros_like(mask), background, region)
    inside = (slice(None), slice(None), slice(24, 40), slice(24, 40))
    assert torch.allclose(final[inside], interior[inside])
    far = (slice(None), slice(None), slice(0, 4), slice(None))  # untouched footage (opacity starts ~0.02)
    assert (final[far] - background[far]).abs().max() < 0.05
    blanked = (region > 0) & (mask == 0)  # the ring the compositing network paints: never black
    assert final.mean(1, keepdim=True)[blanked].min() > 0.2


def test_the_frame_cache_keeps_to_its_memory_budget(footage, face_model):
    from renderer.train_data import cache_frame_bytes

    path, seq = footage
    per_frame = cache_frame_bytes(TINY.crop, face_model.num_vertices)
    cache = build_cache(
        path, seq, face_model, TINY, np.arange(10), progress=False, budget_mb=4.5 * per_frame / 2**20
    )
    np.testing.assert_array_equal(cache.frames, [0, 3, 6, 9])  # 4 frames fit, evenly spread over the video
    assert cache.crops.shape[0] == cache.uv.shape[0] == 4
    nbytes = sum(getattr(cache, k).nbytes for k in ("crops", "uv", "mask", "mouth", "region", "vertices"))
    assert nbytes <= 4.5 * per_frame


def test_frames_in_a_passing_light_are_told_from_another_take():
    from renderer.train_data import transient_light

    light = np.tile(np.float32([180, 140, 120]), (400, 1))
    light[100:110] = [230, 215, 210]  # a 0.4 s fade towards white
    light[300:] *= [1.0, 0.8, 1.6]  # from 12 s on another take, magenta-lit: 4 s, kept
    light[200:205] *= 1.1  # within the tolerance
    off = transient_light(np.arange(400), light, 25.0)
    np.testing.assert_array_equal(np.flatnonzero(off), np.arange(100, 110))
    # the length of a run is counted in the footage's time, also when the cache kept every 40th frame
    frames = np.arange(400) * 40
    assert not transient_light(frames, light, 25.0)[100:110].any()
    assert not transient_light(np.arange(3), np.full((3, 3), np.nan), 25.0).any()  # no face: nothing known


def test_footage_in_several_lights_is_told_from_one_take(footage, face_model):
    from renderer.train_data import VARIED_LIGHT_SHARE, varied_light

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(12), progress=False)
    assert varied_light(cache) == 0.0  # one take
    crops = cache.crops.astype(np.float32)
    crops[8:] *= [1.0, 0.7, 1.3]  # the last third in a magenta light: another take
    other = replace(cache, crops=np.clip(crops, 0, 255).astype(np.uint8))
    assert varied_light(other) == pytest.approx(4 / 12)
    assert varied_light(other) >= VARIED_LIGHT_SHARE
    crops[8:] = cache.crops[8:] * 1.05  # a little brighter: the same light
    assert varied_light(replace(cache, crops=crops.astype(np.uint8))) == 0.0
    assert varied_light(replace(cache, frames=cache.frames[:0], crops=cache.crops[:0])) == 0.0


def test_frames_of_a_fade_are_left_out_of_the_training_frames(footage, face_model, tmp_path):
    path, seq = footage
    faded = tmp_path / "faded.mp4"
    with VideoWriter(faded, 25.0, SIZE, SIZE) as w:
        for t, img in enumerate(iter_frames(path)):
            w.write((img * 0.4 + 255 * 0.6).astype(np.uint8) if 4 <= t <= 6 else img)
    plain = build_cache(path, seq, face_model, TINY, np.arange(12), progress=False)
    cache = build_cache(faded, seq, face_model, TINY, np.arange(12), progress=False)
    kept = [0, 1, 2, 3, 7, 8, 9, 10, 11]
    np.testing.assert_array_equal(cache.frames, kept)
    for name in ("uv", "mask", "mouth", "region", "boxes", "vertices"):  # moved down with their frame
        np.testing.assert_array_equal(getattr(cache, name), getattr(plain, name)[kept], err_msg=name)
    # the crops too (the faded video was encoded again, so its kept frames differ by the codec's error)
    diff = np.abs(cache.crops.astype(int) - plain.crops[kept]).mean((1, 2, 3))
    assert diff.max() < 3


def test_training_resumes_exactly_and_renders(footage, face_model, tmp_path):
    from renderer.render import FrameRenderer

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    assert cache.crops.shape == (10, 32, 32, 3) and cache.mask.mean() > 0.2
    assert cache.mouth.any() and (cache.region >= cache.mask).all()
    # a constant learning rate, so that stopping after 2 of 4 steps is the same as being interrupted there
    cfg = RendererTrainConfig(steps=4, checkpoint_every=2, preview_every=2, lr_final=1.0)
    full = train_renderer(cache, cfg, tmp_path / "a", progress=False, preset=TINY)
    part = replace(cfg, steps=2)
    train_renderer(cache, part, tmp_path / "b", progress=False, preset=TINY)
    resumed = train_renderer(cache, cfg, tmp_path / "b", progress=False, preset=TINY)
    assert full["steps"] == resumed["steps"] == 4
    a, _, _ = load_renderer(tmp_path / "a")
    b, _, m = load_renderer(tmp_path / "b")
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        torch.testing.assert_close(va, vb, msg=k)
    assert m["preset"]["name"] == "tiny" and (tmp_path / "a" / "preview_000002.png").exists()
    from nvp.errors import FormatError

    with pytest.raises(FormatError, match="cannot be resumed"):  # a checkpoint of another network size
        train_renderer(cache, cfg, tmp_path / "a", progress=False, preset=replace(TINY, base=8))

    from nvp.media import iter_frames

    frame = next(iter_frames(path, start_frame=11))
    with FrameRenderer(tmp_path / "a", face_model, seq) as fr:
        v = seq.camera_vertices(face_model, np.array([11]))[0]
        img = fr.render(frame, 11, v, original_cam=v)
    assert img.shape == frame.shape and img.dtype == np.uint8
    box = fr.boxes[11]
    far = int(box[1] + box[2] / 2) + 2  # rows below the crop are untouched
    if far < SIZE:
        np.testing.assert_array_equal(img[far:], frame[far:])


def test_patch_critic_learns_texture_from_blur_and_adversarial_training_resumes(
    footage, face_model, tmp_path
):
    from kornia.filters import gaussian_blur2d

    from renderer.adversarial import PatchCritic, critic_loss, generator_loss

    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    critic = PatchCritic(base=8)
    opt = torch.optim.Adam(critic.parameters(), lr=2e-3, betas=(0.5, 0.999))
    mask = torch.ones(4, 1, 32, 32)
    for _ in range(150):  # real: textured; rendered: the same, blurred
        real = (0.5 + 0.2 * torch.randn(4, 3, 32, 32, generator=g)).clamp(0, 1)
        fake = gaussian_blur2d(real, (7, 7), (2.0, 2.0))
        opt.zero_grad()
        critic_loss(critic, real, fake, mask).backward()
        opt.step()
    assert critic(real).mean() > critic(fake).mean() + 0.5
    assert generator_loss(critic, fake, mask) > generator_loss(critic, real, mask)
    assert generator_loss(critic, fake, torch.zeros_like(mask)) == 0  # off the face: no say
    # renderer training with the term resumes exactly (the critic is checkpointed, never saved with it)
    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    cfg = RendererTrainConfig(
        steps=4, checkpoint_every=2, lr_final=1.0, adversarial_weight=0.1, adversarial_start=0
    )
    train_renderer(cache, cfg, tmp_path / "a", progress=False, preset=TINY)
    train_renderer(cache, replace(cfg, steps=2), tmp_path / "b", progress=False, preset=TINY)
    train_renderer(cache, cfg, tmp_path / "b", progress=False, preset=TINY)
    a, b = load_renderer(tmp_path / "a")[0], load_renderer(tmp_path / "b")[0]
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        torch.testing.assert_close(va, vb, msg=k)
    assert not any("critic" in k for k in a.state_dict())


def test_load_renderer_rejects_other_files(tmp_path):
    from nvp.errors import FormatError

    (tmp_path / "renderer.json").write_text('{"format": "other"}')
    with pytest.raises(FormatError, match="expected nvp.renderer"):
        load_renderer(tmp_path)


def test_renderer_files_keep_the_region_they_were_trained_with(tmp_path):
    import json

    from renderer.networks import make_renderer, save_renderer

    save_renderer(make_renderer(TINY), tmp_path, TINY, {})
    net, preset, _ = load_renderer(tmp_path)
    assert preset.region_grow == TINY.region_grow == 0.015 and net.region_input
    # version 3 and 4 files: no region input to the compositing network; version 3 files (before the
    # preset recorded it) were trained with a 6 % region
    save_renderer(make_renderer(TINY, region_input=False), tmp_path, TINY, {})
    m = json.loads((tmp_path / "renderer.json").read_text())
    (tmp_path / "renderer.json").write_text(json.dumps({**m, "version": 4}))
    net, preset, _ = load_renderer(tmp_path)
    assert preset.region_grow == 0.015 and not net.region_input
    del m["preset"]["region_grow"]
    (tmp_path / "renderer.json").write_text(json.dumps({**m, "version": 3}))
    assert load_renderer(tmp_path)[1].region_grow == 0.06


def test_learning_rate_falls_from_lr_to_its_final_fraction():
    from renderer.train import learning_rate

    cfg = RendererTrainConfig(lr=1e-3, lr_final=0.05)
    lrs = [learning_rate(cfg, p) for p in np.linspace(-0.5, 1.5, 41)]
    assert lrs[0] == pytest.approx(1e-3) and lrs[10] == pytest.approx(1e-3)  # progress 0 (and before)
    assert lrs[30] == pytest.approx(5e-5) and lrs[-1] == pytest.approx(5e-5)  # progress 1 (and after)
    assert learning_rate(cfg, 0.5) == pytest.approx(0.5 * (1e-3 + 5e-5))
    assert all(a >= b for a, b in zip(lrs[:-1], lrs[1:], strict=True)) and type(lrs[0]) is float


def test_a_plateau_is_the_best_of_the_last_window_barely_below_the_best_before_it():
    from renderer.plateau import held_out_blocks, plateaued

    falling = [(s, 1.0 - 0.02 * s / 250) for s in range(250, 3001, 250)]  # 2 % every 250 steps
    assert not plateaued(falling, 1000, 0.01)
    assert plateaued(falling, 1000, 0.1)  # 8 % in the last 1000 steps is under a 10 % bar
    flat = [(s, 0.5 + 0.01 * (-1) ** (s // 250)) for s in range(250, 2001, 250)]  # noise around a level
    assert plateaued(flat, 1000, 0.01)
    assert not plateaued(flat[:4], 1000, 0.01)  # nothing older than the window yet
    assert not plateaued([], 1000, 0.01)
    # four stretches of 41 frames spread over a minute of footage, the measured frames at their middles, at
    # least 18 frames (0.7 s) from any frame trained on; one row in eight at most (fewer stretches, or none)
    measured, left_out = held_out_blocks(np.arange(1500), 16)
    trained = np.setdiff1d(np.arange(1500), left_out)
    assert len(measured) == 16 and len(left_out) == 4 * 41 and np.isin(measured, left_out).all()
    assert np.abs(measured[:, None] - trained[None]).min() >= 18
    assert np.diff(measured[::4]).min() > 300  # spread over the footage, not one stretch
    measured, left_out = held_out_blocks(np.arange(0, 3000, 2), 16)  # every other frame cached
    assert len(measured) == 16 and len(left_out) == 4 * 21
    measured, left_out = held_out_blocks(np.arange(700), 16)
    assert len(measured) == 16 and len(left_out) == 2 * 41
    assert all(len(a) == 0 for a in held_out_blocks(np.arange(200), 16))


def test_a_plateau_schedule_holds_its_rate_then_falls_to_its_floor_in_its_steps_or_time():
    from renderer.plateau import PlateauSchedule
    from renderer.train import learning_rate

    cfg = RendererTrainConfig(lr=1.0, lr_final=0.05)
    s = PlateauSchedule(decay_fraction=0.25)

    def rate(step, elapsed, budget):
        return learning_rate(cfg, s.progress(step, elapsed, budget))

    assert rate(5000, 1e6, None) == 1.0 and s.end(8000) == 8000
    assert not s.must_decay(6399, 0.0, 8000, None) and s.must_decay(6400, 0.0, 8000, None)
    assert s.must_decay(10, 720.0, 8000, 900.0)  # 80 % of a 15-minute budget
    s.start_decay(2000, 300.0, "plateau", steps_left=6000)
    assert (s.decay_from, s.decay_steps, s.end(8000)) == (2000, 500, 2500)
    rates = [rate(k, 300.0, 900.0) for k in range(2000, 2501, 50)]
    assert rates[0] == 1.0 and rates[5] == pytest.approx(0.525) and rates[-1] == pytest.approx(0.05)
    assert all(a > b for a, b in zip(rates[:-1], rates[1:], strict=True))
    assert rate(2100, 900.0, 900.0) == pytest.approx(0.05)  # the time budget ends the decay first
    s.start_decay(7000, 0.0, "limit", steps_left=1000)
    assert s.decay_steps == 1000  # the run's own limit is nearer than a quarter of 7000
    assert PlateauSchedule.from_state(s.state()) == s


def test_a_training_that_stops_on_a_plateau_decays_ends_and_resumes_exactly(
    footage, face_model, tmp_path, monkeypatch
):
    import renderer.train

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    # a bar of 100 %: the first judgement with a window behind it is a plateau (step 12), and a quarter of
    # 12 steps of decay follow
    cfg = RendererTrainConfig(
        steps=40,
        checkpoint_every=4,
        preview_every=10**6,
        stop_on_plateau=True,
        plateau_window=8,
        plateau_gain=1.0,
        plateau_reach=0,  # one frame of the ten is held out
    )
    full = train_renderer(cache, cfg, tmp_path / "a", progress=False, preset=TINY)
    assert full["steps"] == 15 and full["decay"] == {"from": 12, "steps": 3, "why": "plateau"}
    assert [r.get("held_out") is not None for r in full["log"]] == [True, True, True, False]
    # interrupted inside the decay (after the checkpoint at step 12), resumed: the same weights
    real_preview = renderer.train._preview

    def interrupt(path, *args):
        raise KeyboardInterrupt

    monkeypatch.setattr(renderer.train, "_preview", interrupt)
    with pytest.raises(KeyboardInterrupt):
        train_renderer(cache, replace(cfg, preview_every=14), tmp_path / "b", progress=False, preset=TINY)
    monkeypatch.setattr(renderer.train, "_preview", real_preview)
    resumed = train_renderer(cache, cfg, tmp_path / "b", progress=False, preset=TINY)
    assert resumed["steps"] == 15 and resumed["decay"] == full["decay"]
    a, _, _ = load_renderer(tmp_path / "a")
    b, _, _ = load_renderer(tmp_path / "b")
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        torch.testing.assert_close(va, vb, msg=k)
    # a loss that never levels off: the decay starts where the steps would otherwise run out (80 % of 20)
    never = replace(cfg, steps=20, plateau_gain=-1.0)
    info = train_renderer(cache, never, tmp_path / "c", progress=False, preset=TINY)
    assert info["steps"] == 20 and info["decay"] == {"from": 16, "steps": 4, "why": "limit"}
    with pytest.raises(ValueError, match="several videos"):
        train_renderer([cache, cache], cfg, tmp_path / "d", progress=False, preset=TINY)


def test_a_diverged_training_goes_back_to_its_last_healthy_state_with_half_the_rate(
    footage, face_model, tmp_path, monkeypatch, caplog
):
    import renderer.train
    from nvp.errors import NvpError

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    real_loss, calls = renderer.train.renderer_loss, [0]

    def loss_leaving_its_range(*args, spoilt=range(120, 150)):
        """The loss 20× its value for the calls in ``spoilt``, as a training thrown off by a batch."""
        calls[0] += 1
        return real_loss(*args) * (20 if calls[0] - 1 in spoilt else 1)

    monkeypatch.setattr(renderer.train, "renderer_loss", loss_leaving_its_range)
    cfg = RendererTrainConfig(steps=200, checkpoint_every=50, preview_every=10**6, lr_final=1.0)
    info = train_renderer(cache, cfg, tmp_path / "a", progress=False, preset=TINY)
    # steps 101-150 diverged; the state at step 50 is the last one a healthy block followed
    (event,) = info["diverged"]
    assert event["step"] == 150 and event["back_to"] == 50 and event["loss"] > 3 * event["best"]
    assert info["steps"] == 200 and calls[0] == 300  # 150 steps, then 150 again from step 50
    assert "diverged at step 150" in caplog.text and "going back to step 50" in caplog.text
    assert [r["step"] for r in info["log"]] == [50, 100, 150, 200]  # the diverged block's row is gone
    assert info["log"][-1]["loss"] < 1.5 * info["log"][1]["loss"]
    assert all(torch.isfinite(v).all() for v in load_renderer(tmp_path / "a")[0].state_dict().values())
    # the rate after the rollback is half the configured one: it stays halved when the run resumes
    ckpt = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    assert ckpt["guard"]["rollbacks"] == [event]
    assert ckpt["opt"]["param_groups"][0]["lr"] == pytest.approx(cfg.lr / 2)

    # a training that keeps diverging stops with one error after its rollbacks
    calls[0] = 0
    monkeypatch.setattr(
        renderer.train, "renderer_loss", lambda *a: loss_leaving_its_range(*a, spoilt=range(60, 10**6))
    )
    with pytest.raises(NvpError, match="diverged at step 50 .* after going back 2 times"):
        train_renderer(cache, replace(cfg, max_rollbacks=2), tmp_path / "b", progress=False, preset=TINY)


def test_high_frequency_loss_sees_lost_detail_only_inside_the_mask():
    from kornia.filters import gaussian_blur2d

    from renderer.train import high_frequency_l1, high_pass, renderer_loss

    g = torch.Generator().manual_seed(0)
    smooth = gaussian_blur2d(torch.rand(2, 3, 32, 32, generator=g), (9, 9), (3.0, 3.0))
    detailed = smooth + 0.1 * torch.randn(2, 3, 32, 32, generator=g)
    assert high_pass(torch.full((1, 3, 8, 8), 0.7)).abs().max() < 1e-6  # flat: no detail
    mask = torch.zeros(2, 1, 32, 32)
    mask[..., 8:24, 8:24] = 1
    assert high_frequency_l1(detailed, detailed, mask) == 0
    lost = high_frequency_l1(smooth, detailed, mask)
    assert lost > 10 * high_frequency_l1(smooth + 0.01, smooth, mask)  # an offset is no lost detail
    outside = detailed.clone()
    outside[..., :4, :] = smooth[..., :4, :]  # detail lost only outside the (blurred) mask's reach
    assert high_frequency_l1(outside, detailed, mask) == 0
    base = RendererTrainConfig()
    args = (smooth, smooth, detailed, mask)
    with_detail = renderer_loss(*args, replace(base, detail_weight=2.0))
    assert with_detail == pytest.approx(float(renderer_loss(*args, base) + 2.0 * lost), rel=1e-5)


def test_mix_regions_widens_a_fraction_of_the_crops_to_a_union():
    from renderer.train import mix_regions

    n, s = 6, 16
    rows = np.zeros((n, s, s), bool)
    for i in range(n):
        rows[i, 4 : 8 + i, 4:12] = True  # the "chin" of frame i reaches row 7 + i
    cache = SimpleNamespace(region=rows, frames=np.arange(n))
    region = torch.from_numpy(rows[:1].repeat(8, 0))[:, None].float()
    rng = np.random.default_rng(0)
    assert torch.equal(mix_regions(region, cache, rng, 0.0), region)
    mixed = mix_regions(region, cache, rng, 1.0)
    assert (mixed >= region).all() and not torch.equal(mixed, region)
    for m in mixed[:, 0].numpy().astype(bool):  # each crop is its own region ∪ one frame's region
        assert any((m == (rows[0] | r)).all() for r in rows)


def test_vgg_perceptual_term_from_a_user_weights_file(footage, face_model, tmp_path):
    from nvp.errors import FormatError
    from renderer.perceptual import VGGPerceptual

    torch.manual_seed(0)
    # a state dict in torchvision's layout
    layers, c = [], 3
    for v in [64, 64, "M", 128, 128, "M", 256, 256, 256]:
        layers += (
            [torch.nn.MaxPool2d(2)] if v == "M" else [torch.nn.Conv2d(c, v, 3, padding=1), torch.nn.ReLU()]
        )
        c = v if v != "M" else c
    weights = tmp_path / "vgg16.pth"
    torch.save({f"features.{k}": t for k, t in torch.nn.Sequential(*layers).state_dict().items()}, weights)
    vgg = VGGPerceptual(weights)
    a = torch.rand(1, 3, 32, 32)
    assert vgg(a, a) == 0 and vgg(a, torch.rand(1, 3, 32, 32)) > 0
    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(4), progress=False)
    info = train_renderer(
        cache,
        RendererTrainConfig(steps=1, vgg_weights=str(weights)),
        tmp_path / "r",
        progress=False,
        preset=TINY,
    )
    assert info["steps"] == 1
    (tmp_path / "bad.pth").write_bytes(b"nope")
    with pytest.raises(FormatError, match="VGG-16 weights"):
        VGGPerceptual(tmp_path / "bad.pth")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_training_and_rendering_on_cuda(footage, face_model, tmp_path):
    from renderer.render import FrameRenderer

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(4), progress=False)
    train_renderer(cache, RendererTrainConfig(steps=2), tmp_path, device="cuda", progress=False, preset=TINY)
    v = seq.camera_vertices(face_model, np.array([0]))[0]
    with FrameRenderer(tmp_path, face_model, seq, device="cuda") as fr:
        assert fr.render(np.zeros((SIZE, SIZE, 3), np.uint8), 0, v).shape == (SIZE, SIZE, 3)
    from renderer.register import registration_offsets

    assert registration_offsets(tmp_path, path, seq, [0, 1], device="cuda", progress=False).shape == (2, 2)


@pytest.mark.parametrize("r", [1, 4, 12])
def test_separable_morphology_equals_square_pooling(r):
    import torch.nn.functional as F

    from renderer.masks import box_blur, dilate, erode

    x = (torch.rand(2, 1, 40, 56) > 0.9).float() * torch.rand(2, 1, 40, 56)
    k = 2 * r + 1
    assert torch.equal(dilate(x, r), F.max_pool2d(x, k, stride=1, padding=r))
    assert torch.equal(erode(x, r), -F.max_pool2d(-x, k, stride=1, padding=r))
    square = F.avg_pool2d(x, k, stride=1, padding=r, count_include_pad=False)
    assert torch.allclose(box_blur(x, r), square, atol=1e-6)


@pytest.mark.parametrize(("size", "sigma"), [(3, 0.5), (7, 1.0), (5, 1.3)])
def test_the_gaussian_blur_is_kornias(size, sigma):
    from kornia.filters import gaussian_blur2d

    from renderer.masks import gaussian_blur

    x = torch.rand(2, 3, 37, 52)
    expected = gaussian_blur2d(x, (size, size), (sigma, sigma), "replicate")
    torch.testing.assert_close(gaussian_blur(x, size, sigma), expected, rtol=0, atol=1e-6)


def test_the_renderer_learns_loss_falls_and_a_held_out_frame_improves(footage, face_model, tmp_path):
    from renderer.networks import make_renderer, save_renderer
    from renderer.render import FrameRenderer

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    save_renderer(make_renderer(TINY), tmp_path / "untrained", TINY, {})
    cfg = RendererTrainConfig(steps=120, lr=3e-3, checkpoint_every=40, preview_every=10**6)
    info = train_renderer(cache, cfg, tmp_path / "trained", progress=False, preset=TINY)
    assert info["log"][-1]["loss"] < 0.7 * info["log"][0]["loss"]
    real = list(iter_frames(path))[11]  # never trained on

    def error(renderer_dir):
        with FrameRenderer(renderer_dir, face_model, seq, detail=False) as fr:
            out = fr.render(real, 11, fr.tracked(11))
        return np.abs(out.astype(float) - real).mean()

    assert error(tmp_path / "trained") < 0.7 * error(tmp_path / "untrained")


def test_registration_measures_a_known_error_of_the_tracking(face_model, tmp_path):
    """Registration (renderer.register) finds where a trained renderer sees the face: tracking moved right
    and up off the footage is measured back left and down, by what it was moved. The face has a pattern
    (stripes across the texture) as a real face has eyes, brows and nostrils: a smooth gradient says
    little about a shift along it."""
    from renderer.register import registered, registration_offsets

    seq = synthetic_tracked(face_model, frames=12, size=SIZE, focal=200.0)
    path = tmp_path / "face.mp4"
    waves = lambda uv: 0.5 + 0.4 * torch.sin(uv * 6 * np.pi)  # noqa: E731
    face_video(path, seq, face_model, lambda uv: torch.cat([uv[..., :1], waves(uv)], -1))
    preset = Preset("reg", crop=64, base=8, dilated=False, texture_size=64, steps=2, batch=2)
    cache = build_cache(path, seq, face_model, preset, np.arange(12), progress=False)
    cfg = RendererTrainConfig(steps=150, lr=3e-3, checkpoint_every=10**6, preview_every=10**6)
    train_renderer(cache, cfg, tmp_path / "r", progress=False, preset=preset)
    frames = np.arange(12)
    exact = registration_offsets(tmp_path / "r", path, seq, frames, progress=False)
    shift = np.array([0.4, -0.3])  # frame pixels, below the longest offset taken (MAX_SHIFT)
    moved = registered(seq, face_model, np.tile(shift, (12, 1)))
    back = registration_offsets(tmp_path / "r", path, moved, frames, progress=False)
    # measured (AMD EPYC): (-0.45 ± 0.01, 0.39 ± 0.01) over training seeds 0-3 (a 48² crop: -0.50 ... -0.53
    # in x, 0.23 ... 0.30 in y; DIS flow over so few pixels is biased either way)
    change = np.median(back - exact, 0)
    np.testing.assert_allclose(change, -shift, atol=0.15)


def test_a_timed_renderer_training_shows_seconds_and_time_left(
    footage, face_model, tmp_path, capsys, monkeypatch
):
    import renderer.train

    # the training's clock: every reading 0.5 s after the last (one before the first step, one after each),
    # so how many steps a time allows does not depend on how busy the machine is
    ticks = iter(np.arange(10_000) * 0.5)
    monkeypatch.setattr(renderer.train, "time", SimpleNamespace(perf_counter=lambda: float(next(ticks))))
    tiny = Preset("tiny", crop=32, base=4, dilated=False, texture_size=32, steps=3, batch=1)
    path, seq = footage
    cache = build_cache(path, seq, face_model, tiny, np.arange(4), progress=False)
    # a time alone: as many steps as it allows (2 s of 0.5 s steps), not the preset's 3
    info = train_renderer(cache, RendererTrainConfig(budget_s=2.0), tmp_path / "r", preset=tiny)
    assert info["train_seconds"] == 2.0 and info["steps"] == 4
    err = capsys.readouterr().err
    assert "/2 s" in err and "left" in err
    # steps and a time: the steps end first (4 steps, 2 s), and the bar counted down to their end, not to
    # the time's 600 s
    cfg = RendererTrainConfig(steps=4, budget_s=600.0)
    info = train_renderer(cache, cfg, tmp_path / "r2", preset=tiny)
    assert info["steps"] == 4 and info["train_seconds"] == 2.0
    totals = [int(t) for t in re.findall(r"/(\d+) s", capsys.readouterr().err)]
    assert totals[0] == 600 and totals[-1] == 2, totals


@pytest.mark.parametrize("shape", [(1, 1, 48, 48), (2, 1, 13, 20)])
@pytest.mark.parametrize("r", [1, 3, 6])
def test_mask_morphology_equals_pooling(shape, r):
    """Dilation by doubling and the box blur by cumulative sums give what pooling gives, much faster."""
    import torch.nn.functional as F

    from renderer.masks import box_blur, dilate, erode

    m = torch.rand(*shape, generator=torch.Generator().manual_seed(r))
    pooled = F.max_pool2d(F.max_pool2d(m, (2 * r + 1, 1), 1, (r, 0)), (1, 2 * r + 1), 1, (0, r))
    assert torch.equal(dilate(m, r), pooled)
    assert torch.equal(
        erode(m, r), -F.max_pool2d(F.max_pool2d(-m, (2 * r + 1, 1), 1, (r, 0)), (1, 2 * r + 1), 1, (0, r))
    )
    mean = F.avg_pool2d(m, (2 * r + 1, 1), 1, (r, 0), count_include_pad=False)
    mean = F.avg_pool2d(mean, (1, 2 * r + 1), 1, (0, r), count_include_pad=False)
    torch.testing.assert_close(box_blur(m, r), mean, atol=1e-5, rtol=0)
    assert dilate(m, 0) is m and box_blur(m, 0) is m
    wide = dilate(m[..., :3, :3], 5)  # a window wider than the image: the image's maximum everywhere
    assert torch.equal(wide, m[..., :3, :3].amax((-2, -1), keepdim=True).expand_as(wide))


def test_pretraining_on_many_videos_resumes_exactly_and_saves_their_mean_texture(
    footage, face_model, tmp_path
):
    from nvp.errors import FormatError

    path, seq = footage
    caches = [build_cache(path, seq, face_model, TINY, np.arange(a, a + 5), progress=False) for a in (0, 5)]
    cfg = RendererTrainConfig(steps=4, checkpoint_every=2, preview_every=10**6, lr_final=1.0, init=None)
    train_renderer(caches, cfg, tmp_path / "a", progress=False, preset=TINY, names=["x", "y"])
    train_renderer(caches, replace(cfg, steps=2), tmp_path / "b", progress=False, preset=TINY)
    train_renderer(caches, cfg, tmp_path / "b", progress=False, preset=TINY)
    a, _, m = load_renderer(tmp_path / "a")
    b, _, _ = load_renderer(tmp_path / "b")
    for (k, va), vb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        torch.testing.assert_close(va, vb, msg=k)
    state = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)
    own = [state["textures"][f"{i}.texture"] for i in range(2)]
    assert not torch.allclose(own[0], own[1])  # each video learns its own texture, the networks are shared
    torch.testing.assert_close(a.texture.texture.detach(), (own[0] + own[1]) / 2)
    assert m["videos"] == ["x", "y"] and m["init"] == "scratch" and m["train_frames"] == 10
    with pytest.raises(FormatError, match="cannot be resumed"):  # another set of videos
        train_renderer([*caches, caches[0]], cfg, tmp_path / "a", progress=False, preset=TINY)


def test_a_training_starts_from_a_renderer_of_the_same_structure_only(tmp_path):
    from nvp.errors import FormatError
    from renderer.networks import make_renderer, save_renderer
    from renderer.train import initial_weights

    start = make_renderer(TINY)
    with torch.no_grad():
        for p in start.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    save_renderer(start, tmp_path / "g", TINY, {}, half=True)
    net = make_renderer(TINY)
    assert initial_weights(net, TINY, str(tmp_path / "g")) == str(tmp_path / "g")
    for (k, got), want in zip(net.state_dict().items(), start.state_dict().values(), strict=True):
        torch.testing.assert_close(got, want, atol=2e-3, rtol=2e-3, msg=k)  # stored as float16
    assert initial_weights(make_renderer(TINY), TINY, None) == "scratch"
    assert initial_weights(make_renderer(TINY), TINY, "generic") == "scratch"  # none ships for 'tiny'
    wide = replace(TINY, base=8)
    with pytest.raises(FormatError, match="another structure"):
        initial_weights(make_renderer(wide), wide, str(tmp_path / "g"))


def test_a_person_trained_from_a_pretrained_start_learns_faster(footage, face_model, tmp_path):
    from renderer.render import FrameRenderer

    path, seq = footage
    caches = [build_cache(path, seq, face_model, TINY, np.arange(a, a + 5), progress=False) for a in (0, 5)]
    pre = RendererTrainConfig(steps=150, lr=3e-3, init=None, checkpoint_every=10**6, preview_every=10**6)
    train_renderer(caches, pre, tmp_path / "generic", progress=False, preset=TINY)
    person = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    real = list(iter_frames(path))[11]  # never trained on

    def error(init) -> float:
        out = tmp_path / str(init is None)
        cfg = RendererTrainConfig(steps=10, lr=3e-3, init=init, checkpoint_every=10**6, preview_every=10**6)
        train_renderer(person, cfg, out, progress=False, preset=TINY)
        with FrameRenderer(out, face_model, seq, detail=False) as fr:
            img = fr.render(real, 11, fr.tracked(11))
        return float(np.abs(img.astype(float) - real).mean())

    assert error(str(tmp_path / "generic")) < 0.8 * error(None)


def test_the_network_window_holds_the_painted_part_and_its_context():
    from renderer.render import network_window

    paint = torch.zeros(1, 1, 192, 192)
    assert network_window(paint, 48) == (slice(0, 192), slice(0, 192))  # nothing painted: the whole crop
    paint[..., 100:170, 60:130] = 1
    rows, cols = network_window(paint, 20)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (80, 192, 32, 160)
    for s in (rows, cols):  # the strided U-Nets need sides divisible by 16
        assert s.start % 16 == 0 and (s.stop - s.start) % 16 == 0


def test_two_processes_under_torchrun_follow_the_one_process_pretraining(
    footage, face_model, tmp_path, torchrun
):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    path, seq = footage
    for a in (0, 5):
        cache = build_cache(path, seq, face_model, TINY, np.arange(a, a + 5), progress=False)
        cache.save(tmp_path / "caches" / f"c{a}")
    script = Path(__file__).parent / "ddp_pretrain_toy.py"
    caches = tmp_path / "caches"
    cmd = [sys.executable, script, caches, tmp_path / "one"]
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    assert proc.returncode == 0, f"one: {proc.stderr[-2000:]}"
    torchrun(script, caches, tmp_path / "two")
    runs = ("one", "two")
    manifests = {k: json.loads((tmp_path / k / "renderer.json").read_text()) for k in runs}
    assert manifests["one"]["processes"] == 1 and manifests["two"]["processes"] == 2
    logs = {k: m["log"] for k, m in manifests.items()}
    assert [r["step"] for r in logs["one"]] == [r["step"] for r in logs["two"]] == [2, 4, 6]
    # the same batches, each process half of each, gradients averaged: the same run up to float rounding
    np.testing.assert_allclose([r["loss"] for r in logs["two"]], [r["loss"] for r in logs["one"]], rtol=1e-4)
    one, _, _ = load_renderer(tmp_path / "one")
    two, _, _ = load_renderer(tmp_path / "two")
    for (k, a), b in zip(one.state_dict().items(), two.state_dict().values(), strict=True):
        torch.testing.assert_close(b, a, atol=1e-5, rtol=1e-4, msg=k)


def test_the_shipped_generic_renderer_fits_the_cpu_preset_and_is_small():
    import json

    from renderer.networks import generic_renderer_dir
    from renderer.preset import get_preset

    folder = generic_renderer_dir(get_preset("cpu"))
    assert folder is not None
    manifest = json.loads((folder / "renderer.json").read_text())
    assert len(manifest["videos"]) >= 20
    assert "dfrf__cnn2_25fps.mp4" not in manifest["videos"]  # docs/training.md's curves are measured on it
    assert (folder / "renderer.npz").stat().st_size < 6 * 2**20
    net, _, _ = load_renderer(folder)
    assert all(torch.isfinite(p).all() for p in net.parameters())


def test_bfloat16_rendering_stays_within_a_few_levels_of_float32(footage, face_model, tmp_path, monkeypatch):
    from renderer.networks import fast_bf16
    from renderer.render import FrameRenderer

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    cfg = RendererTrainConfig(steps=20, lr=3e-3, init=None, checkpoint_every=10**6, preview_every=10**6)
    train_renderer(cache, cfg, tmp_path / "r", progress=False, preset=TINY)
    real = list(iter_frames(path))[11]
    images = []
    for bf16 in (False, True):
        with FrameRenderer(tmp_path / "r", face_model, seq, bf16=bf16) as fr:
            images.append(fr.render(real, 11, fr.tracked(11)).astype(float))
    assert np.abs(images[0] - real).max() > 0  # something was painted
    # typically at most 1 level anywhere (mean 0.009); a network trained while the machine was busy (other
    # thread counts, other rounding) once gave 5 at one pixel: a few levels at the odd pixel, none on average
    d = np.abs(images[0] - images[1])
    assert d.max() <= 8 and np.percentile(d, 99) <= 2 and d.mean() <= 0.1
    monkeypatch.setenv("NVP_PRECISION", "fp32")
    assert not fast_bf16("cpu")
    monkeypatch.delenv("NVP_PRECISION")
    assert not fast_bf16("cuda")


def test_frames_rendered_in_parallel_equal_one_at_a_time_in_order(footage, face_model, tmp_path):
    from nvp.geometry import posed
    from renderer.loop import MOUTH_LAG, render_frames
    from renderer.mouths import EntryChooser, build_mouth_bank
    from renderer.render import FrameRenderer

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    cfg = RendererTrainConfig(steps=10, lr=3e-3, init=None, checkpoint_every=10**6, preview_every=10**6)
    train_renderer(cache, cfg, tmp_path / "r", progress=False, preset=TINY)
    build_mouth_bank(path, seq, face_model, frames=np.array([2, 6, 9])).save(tmp_path / "r" / "mouths")
    frames = list(iter_frames(path))
    order = [3, 11, 0, 7, 7, 5, 10, 1, 2]

    def opened(j: int, k: int, tracked: np.ndarray) -> np.ndarray:  # a different mouth per output frame
        expression = seq.expression[k].copy()
        expression[:3] += 2.0 * np.sin(j + 1)
        return posed(face_model.vertices(seq.identity, expression), seq.rotation[k], seq.translation[k])

    variants = {"re": None, "dub": opened}
    with FrameRenderer(tmp_path / "r", face_model, seq) as fr:
        one = list(render_frames(fr, (frames[k] for k in order), order, variants, False, workers=1))
        two = list(render_frames(fr, (frames[k] for k in order), order, variants, False, workers=3))
        # the dub's open mouths got the bank entries a stream chooser fixes MOUTH_LAG frames later
        faces = [
            fr.prepare(frames[k], k, opened(j, k, fr.tracked(k)), fr.tracked(k)) for j, k in enumerate(order)
        ]
        chooser = EntryChooser(MOUTH_LAG)
        entries = [e for face in faces for e in chooser.push(fr.entry_costs(face))] + chooser.flush()
        for face, entry, (_, made) in zip(faces, entries, one, strict=True):
            np.testing.assert_array_equal(fr.composite(face, entry), made["dub"])
        assert any(fr._interior_window(face.geo) is not None for face in faces)  # some mouths were open

        def broken(j: int, k: int, tracked: np.ndarray) -> np.ndarray:
            if j == 4:
                raise RuntimeError("frame 4 is broken")
            return tracked

        with pytest.raises(RuntimeError, match="frame 4"):
            for _ in render_frames(fr, (frames[k] for k in order), order, {"x": broken}, False, workers=2):
                pass
        # the renderer still works after the failed loop (its twins were closed, not it)
        assert fr.render(frames[0], 0, fr.tracked(0)).shape == frames[0].shape
    assert len(one) == len(two) == len(order)
    for k, (f1, m1), (f2, m2) in zip(order, one, two, strict=True):
        np.testing.assert_array_equal(f1, frames[k])
        np.testing.assert_array_equal(f2, frames[k])
        for name in variants:
            np.testing.assert_array_equal(m1[name], m2[name])
    assert np.abs(one[0][1]["dub"].astype(int) - one[0][1]["re"]).max() > 0  # the dub moved the mouth


def test_an_open_rendered_mouth_shows_the_person_s_own_interior_from_the_bank(footage, face_model, tmp_path):
    from nvp.geometry import posed
    from renderer.gl import GLRasterizer
    from renderer.interior import INTERIOR_TOLERANCE
    from renderer.masks import dilate
    from renderer.mouths import build_mouth_bank
    from renderer.render import FrameRenderer

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(10), progress=False)
    cfg = RendererTrainConfig(steps=10, lr=3e-3, init=None, checkpoint_every=10**6, preview_every=10**6)
    train_renderer(cache, cfg, tmp_path / "r", progress=False, preset=TINY)
    k = face_model.exp_basis.shape[0]
    wide = 4.0 * np.eye(k, dtype=np.float32)[np.argmax(face_model.inner_lip_gap(seq.identity, np.eye(k)))]
    opened = posed(face_model.vertices(seq.identity, wide[None])[0], seq.rotation[5], seq.translation[5])
    bank = build_mouth_bank(path, seq, face_model, frames=np.array([2, 6]))
    assert bank.patches.shape == (2, 64, 64, 3) and bank.pixels.shape == (2, face_model.num_vertices, 2)
    # the light of every 5th frame and of the entries' (the colour of the skin around the lips)
    np.testing.assert_array_equal(bank.light_frames, np.union1d(np.flatnonzero(seq.valid)[::5], [2, 6]))
    assert bank.light_colours.shape == (len(bank.light_frames), 3) and bank.light_colours.min() > 0
    lips = face_model.vertex_regions["lips"]  # the lips lie inside their patch, 1.6 mouth widths across
    assert 0.15 * 64 < bank.pixels[:, lips, 0].min() and bank.pixels[:, lips, 0].max() < 0.85 * 64
    footage_mouths = bank.patches.copy()
    bank.patches[:] = (0, 255, 0)  # a green mouth interior, to see where it lands
    bank.save(tmp_path / "r" / "mouths")
    frame = list(iter_frames(path))[5]
    with (
        FrameRenderer(tmp_path / "r", face_model, seq, interiors=False) as a,
        FrameRenderer(tmp_path / "r", face_model, seq) as b,
    ):
        assert a.mouths is None and len(b.mouths) == 2
        tracked = a.tracked(5)
        plain = a.render(frame, 5, opened, tracked).astype(int)
        teeth = b.render(frame, 5, opened, tracked, mouth=1).astype(int)
        np.testing.assert_array_equal(b.render(frame, 5, tracked), a.render(frame, 5, tracked))  # closed
        # a bank frame shot in other light (here: its channels scaled) pastes about the same interior: each
        # channel is scaled so that the entry's lips take the rendered lips' colour, but for a tolerance
        pasted = []
        for tint in ((1.0, 1.0, 1.0), (0.8, 0.5, 1.6)):
            b.mouths.patches = np.clip(footage_mouths * np.array(tint) * 0.6, 0, 255).astype(np.uint8)
            b._patches = torch.from_numpy(b.mouths.patches).permute(0, 3, 1, 2)
            pasted.append(b.render(frame, 5, opened, tracked, mouth=1).astype(int))
    with GLRasterizer(SIZE, SIZE) as gl:
        r = gl.rasterize(opened, face_model.triangles, face_model.uvs, seq.focal, seq.center)
    inner = torch.isin(
        r.triangle_id, torch.from_numpy(np.flatnonzero(face_model.triangle_regions["mouth_interior"]))
    )
    assert inner.sum() >= 4  # the wide-open mouth shows its interior
    near = dilate(inner.float()[None, None], 4)[0, 0].numpy() > 0  # a crop pixel is ~2 frame pixels
    changed = np.abs(teeth - plain).sum(-1) > 0
    # there and only there (the edge of a crop pixel's mask, and a little inside it: INTERIOR_EDGE_LEVEL)
    assert changed[inner.numpy()].mean() > 0.8 and not changed[~near].any()
    green = teeth[inner.numpy()].mean(0)  # green, its level that of the rendered lips' green
    assert green[1] > 100 and green[0] < 60 and green[2] < 60
    # the tint (0.5 on green, 1.6 on blue) is taken back to within the tolerance of each paste (both may
    # differ from the rendered lips by up to it)
    ratio = pasted[1][inner.numpy()].mean(0) / pasted[0][inner.numpy()].mean(0)
    assert np.all(np.abs(np.log(ratio)) <= 2 * np.log(1 + INTERIOR_TOLERANCE) + 0.02), ratio


def _opened_mouth_with_bank(footage, face_model, tmp_path, colours, same_shapes: bool = False) -> np.ndarray:
    """An untrained 64² renderer in ``tmp_path`` with a two-entry mouth bank (footage frames 2 and 6, their
    interiors painted ``colours``; ``same_shapes``: entry 1 takes entry 0's inner-lip shape, so only their
    interiors differ), and frame 5's geometry with the mouth wide open ``(V, 3)``."""
    from nvp.geometry import posed
    from renderer.mouths import build_mouth_bank
    from renderer.networks import make_renderer, save_renderer

    path, seq = footage
    preset = replace(TINY, crop=64, source_input=False)
    save_renderer(make_renderer(preset), tmp_path, preset, {})
    k = face_model.exp_basis.shape[0]
    wide = 4.0 * np.eye(k, dtype=np.float32)[np.argmax(face_model.inner_lip_gap(seq.identity, np.eye(k)))]
    bank = build_mouth_bank(path, seq, face_model, frames=np.array([2, 6]))
    if same_shapes:
        bank.shapes[1], bank.pixels[1] = bank.shapes[0], bank.pixels[0]
    bank.patches[0], bank.patches[1] = colours
    bank.save(tmp_path / "mouths")
    return posed(face_model.vertices(seq.identity, wide[None])[0], seq.rotation[5], seq.translation[5])


def test_the_bank_entry_whose_interior_looks_like_the_networks_own_is_chosen(
    footage, face_model, tmp_path, monkeypatch
):
    """Two bank entries of the same inner-lip shape and light: the one whose interior agrees with the
    networks' soft interior (here: all grey) wins, and only the nearest ``CANDIDATES`` are compared."""
    import renderer.interior as render_module
    from renderer.render import FrameRenderer

    path, seq = footage
    grey = np.array([120, 100, 90], np.uint8)
    opened = _opened_mouth_with_bank(footage, face_model, tmp_path, ((0, 255, 0), grey), same_shapes=True)

    class Flat:  # networks that paint everything grey
        source_input = False

        def __call__(self, uv, mask, *rest):
            return None, torch.from_numpy(grey / 255).float().view(1, 3, 1, 1).expand(1, 3, *mask.shape[-2:])

    frame = list(iter_frames(path))[5]
    with FrameRenderer(tmp_path, face_model, seq) as fr:
        fr.net = Flat()
        face = fr.prepare(frame, 5, opened, fr.tracked(5))
        window = fr._interior_window(face.geo)
        assert window is not None and (face.geo.mouth > 0.5).sum() >= 2  # the interior shows
        apart = fr._disagreement(face, window, np.array([0, 1]))
        assert apart[1] < 1 and apart[0] > 50  # levels of 255
        costs = fr.entry_costs(face)
        assert np.argmin(costs) == 1 and np.isfinite(costs).all()
        np.testing.assert_array_equal(fr.composite(face), fr.composite(face, 1))  # what is pasted
        assert np.abs(fr.composite(face, 0).astype(int) - fr.composite(face, 1)).max() > 50
        monkeypatch.setattr(render_module, "CANDIDATES", 1)
        costs = fr.entry_costs(face)  # equal shapes: the first is the nearest, the other is not compared
        assert np.isfinite(costs[0]) and np.isinf(costs[1])


def test_a_render_of_the_footage_own_geometry_keeps_its_fine_detail(footage, face_model, tmp_path):
    """Where the surface did not move, the painted lower face (and the band around the mesh) gets the
    footage's own detail back, also the detail a blurry network loses at the crop's own resolution."""
    import cv2

    from renderer.networks import make_renderer, save_renderer
    from renderer.render import FrameRenderer

    path, seq = footage
    plain = replace(TINY, source_input=False)
    save_renderer(make_renderer(plain), tmp_path, plain, {})
    rng = np.random.default_rng(0)
    real = np.clip(list(iter_frames(path))[3] + rng.normal(0, 25, (SIZE, SIZE, 3)), 0, 255).astype(np.uint8)

    def fine(img: np.ndarray) -> np.ndarray:
        g = img.astype(np.float32)
        return g - cv2.GaussianBlur(g, (5, 5), 0)

    errors = {}
    for detail in (False, True):
        with FrameRenderer(tmp_path, face_model, seq, detail=detail, interiors=False) as fr:
            out, weight = fr.render(real, 3, fr.tracked(3), with_weight=True)
        painted = weight > 0.9
        assert painted.sum() > 50
        errors[detail] = np.abs(fine(out) - fine(real))[painted].mean()
    assert errors[True] < 0.25 * errors[False]  # 0.18 measured; 0.30 without the band and the background


def test_a_detail_source_from_another_frame_keeps_the_footage_own_pixels_off_the_mesh(
    footage, face_model, tmp_path
):
    """The band around the mesh that the networks paint keeps the painted frame's own pixels, whatever
    frame the surface's detail comes from: a re-creation from another frame's detail shows there what a
    dub shows (the footage), while the surface takes the source's (here a flat one: none)."""
    import cv2

    from nvp.geometry import pinhole
    from renderer.networks import make_renderer, save_renderer
    from renderer.render import FrameRenderer

    path, seq = footage
    plain = replace(TINY, source_input=False)
    save_renderer(make_renderer(plain), tmp_path, plain, {})
    rng = np.random.default_rng(0)
    real = np.clip(list(iter_frames(path))[3] + rng.normal(0, 25, (SIZE, SIZE, 3)), 0, 255).astype(np.uint8)
    with FrameRenderer(tmp_path, face_model, seq, detail=True, interiors=False) as fr:
        tracked = fr.tracked(3)
        out, weight = fr.render(
            real, 3, tracked, source=(np.full_like(real, 128), 3, tracked), with_weight=True
        )

    def fine(img: np.ndarray) -> np.ndarray:
        g = img.astype(np.float32)
        return g - cv2.GaussianBlur(g, (5, 5), 0)

    hull = np.zeros((SIZE, SIZE), np.uint8)
    points = pinhole(tracked, seq.focal, seq.center)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.round(points).astype(np.int32)), 1)
    kernel = np.ones((5, 5), np.uint8)
    off = (weight > 0.9) & (cv2.dilate(hull, kernel) == 0)
    on = (weight > 0.9) & (cv2.erode(hull, kernel) > 0)
    assert off.sum() > 20 and on.sum() > 50
    error = np.abs(fine(out) - fine(real))
    # 0.02 measured; 0.29 when the band took the networks' render (the footage's detail only where paint < 1)
    assert error[off].mean() < 0.1 * error[on].mean()


def test_colour_match_finds_a_fade_and_leaves_the_networks_softness_alone():
    """A footage frame fading to white is an affine change of the face's colours, found over the face the
    frame keeps even with a hand in front of part of it; a render a little softer than the footage (gain
    1.05) or a level off is left as it is; too few pixels give no change."""
    from renderer.crop import colour_match

    rng = np.random.default_rng(0)
    render = torch.from_numpy(rng.uniform(0.2, 0.8, (3, 40, 40))).float()
    where = torch.zeros(40, 40, dtype=torch.bool)
    where[:30] = True
    faded = 0.4 * render + 0.6
    faded[:, :5] = 0.1  # a dark hand over a sixth of the measured pixels
    gain, offset = colour_match(render, faded, where)
    assert torch.allclose(gain, torch.full((3, 1, 1), 0.4), atol=0.02)
    assert torch.allclose(offset, torch.full((3, 1, 1), 0.6), atol=0.02)
    softer = render.mean() + 1.05 * (render - render.mean()) + 2 / 255
    gain, offset = colour_match(render, softer, where)
    assert torch.equal(gain, torch.ones(3, 1, 1)) and torch.equal(offset, torch.zeros(3, 1, 1))
    few = torch.zeros_like(where)
    few[0, :10] = True
    gain, offset = colour_match(render, faded, few)
    assert torch.equal(gain, torch.ones(3, 1, 1)) and torch.equal(offset, torch.zeros(3, 1, 1))


class _UVFace(torch.nn.Module):
    """Stands in for trained networks on the synthetic footage: paints the mesh in the footage's own
    UV colours (so it renders a frame's face as the footage showed it before any fade)."""

    source_input = False

    def forward(self, uv, mask, mouth, background, region, source=None):
        face = torch.cat([uv, 1 - uv[..., :1]], -1).permute(0, 3, 1, 2) * mask
        return face, face + (1 - mask) * background


def test_the_painted_face_follows_a_footage_frame_fading_to_white(footage, face_model, tmp_path, monkeypatch):
    """Networks that learned the face in the footage's light paint it so into a frame that fades to
    white; the painted lower face takes the faded frame's light from the face around it, and a frame in
    the learned light is painted as without the match."""
    import renderer.render
    from renderer.networks import make_renderer, save_renderer
    from renderer.render import FrameRenderer

    path, seq = footage
    plain = replace(TINY, source_input=False)
    save_renderer(make_renderer(plain), tmp_path, plain, {})
    real = list(iter_frames(path))[3]
    faded = np.round(0.35 * real + 0.65 * 255).astype(np.uint8)

    def rendered(match: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not match:
            unchanged = (torch.ones(3, 1, 1), torch.zeros(3, 1, 1))
            monkeypatch.setattr(renderer.render, "colour_match", lambda *a, **k: unchanged)
        with FrameRenderer(tmp_path, face_model, seq, detail=False, interiors=False) as fr:
            fr.net = _UVFace()
            out, weight = fr.render(real, 3, fr.tracked(3), with_weight=True)
            return out.astype(int), fr.render(faded, 3, fr.tracked(3)).astype(int), weight

    (real_on, faded_on, weight), (real_off, faded_off, _) = rendered(True), rendered(False)
    painted = (weight > 0.9) & (np.abs(real.astype(int) - 90).sum(-1) > 30)  # the face, not the backdrop
    assert painted.sum() > 20
    assert np.abs(real_on - real_off)[painted].mean() < 0.5  # the learned light: as without the match
    err_on, err_off = (np.abs(x - faded)[painted].mean() for x in (faded_on, faded_off))
    assert err_on < 0.35 * err_off


def test_the_bank_s_teeth_follow_a_footage_frame_fading_to_white(footage, face_model, tmp_path):
    """A bank entry's interior pasted into a frame that fades to white takes the frame's light like the
    painted face around it (its colours still follow the lips as the networks learned them)."""
    from renderer.render import FrameRenderer

    path, seq = footage
    opened = _opened_mouth_with_bank(footage, face_model, tmp_path, ((0, 160, 0), (120, 100, 90)))
    real = list(iter_frames(path))[5]
    faded = np.round(0.35 * real + 0.65 * 255).astype(np.uint8)
    with FrameRenderer(tmp_path, face_model, seq) as fr:
        fr.net = _UVFace()
        shown = {}
        for name, frame in (("real", real), ("faded", faded)):
            face = fr.prepare(frame, 5, opened, fr.tracked(5))
            shown[name] = [fr.composite(face, e).astype(int) for e in (0, 1)]
    interior = np.abs(shown["real"][0] - shown["real"][1]).max(-1) > 40  # where the entries show
    assert interior.sum() >= 2
    # in the faded frame the grey entry is as much lighter as the frame is (0.65 of the way to white)
    lifted = shown["faded"][1][interior].mean() - shown["real"][1][interior].mean()
    assert lifted > 0.4 * (255 - shown["real"][1][interior].mean())


def test_training_checkpoints_by_time_as_well_as_steps(footage, face_model, tmp_path, monkeypatch):
    import renderer.train

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(6), progress=False)
    cfg = RendererTrainConfig(steps=6, checkpoint_every=250, checkpoint_seconds=0.0, lr_final=1.0)
    real, calls = renderer.train.renderer_loss, []

    def killed_in_step_4(*a, **k):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(renderer.train, "renderer_loss", killed_in_step_4)
    with pytest.raises(KeyboardInterrupt):
        train_renderer(cache, cfg, tmp_path / "r", progress=False, preset=TINY)
    state = torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=True)
    assert state["step"] == 3  # far from step 250: saved by time
    monkeypatch.undo()
    assert train_renderer(cache, cfg, tmp_path / "r", progress=False, preset=TINY)["steps"] == 6


@pytest.mark.parametrize("damage", ["truncate", "empty", "junk"])
def test_a_resumed_training_says_so_and_a_damaged_checkpoint_is_one_clear_error(
    footage, face_model, tmp_path, caplog, damage
):
    import logging

    from nvp.errors import FormatError

    path, seq = footage
    cache = build_cache(path, seq, face_model, TINY, np.arange(6), progress=False)
    cfg = RendererTrainConfig(steps=2, checkpoint_every=1, lr_final=1.0)
    train_renderer(cache, cfg, tmp_path / "r", progress=False, preset=TINY)
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # visible without -v
        train_renderer(cache, replace(cfg, steps=3), tmp_path / "r", progress=False, preset=TINY)
    resumed = [r.getMessage() for r in caplog.records if "resuming" in r.getMessage()]
    assert len(resumed) == 1 and "at step 2" in resumed[0] and "checkpoint.pt" in resumed[0], resumed
    ckpt = tmp_path / "r" / "checkpoint.pt"
    data = ckpt.read_bytes()
    damaged = {
        "truncate": data[: len(data) // 2],
        "empty": b"",
        "junk": bytes(range(256)) * (len(data) // 256),
    }
    ckpt.write_bytes(damaged[damage])
    with pytest.raises(FormatError, match="damaged and cannot be read") as e:
        train_renderer(cache, replace(cfg, steps=4), tmp_path / "r", progress=False, preset=TINY)
    assert str(ckpt) in str(e.value) and "delete it to start training again" in str(e.value)
