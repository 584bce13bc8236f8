"""Tests for renderer.warp: the surface correspondence that moves the footage's detail."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderer.raster_ref import rasterize_reference
from renderer.warp import (
    mesh_edges,
    moved_detail,
    rigidity,
    sample_pixels,
    smooth,
    source_positions,
    surface_points,
)


def test_surface_points_interpolate_vertex_values():
    tri = torch.tensor([[0, 1, 2]])
    values = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 20.0]])
    tid = torch.tensor([[0, -1]])
    bary = torch.tensor([[[0.5, 0.25, 0.25], [1.0, 0.0, 0.0]]])
    out = surface_points(tid, bary, tri, values)
    np.testing.assert_allclose(out[0, 0], [2.5, 5.0])
    np.testing.assert_allclose(out[0, 1], [0.0, 0.0])  # background


def test_sample_pixels_reads_pixel_centres_and_interpolates():
    img = torch.arange(12.0).reshape(1, 3, 4)  # value = 4 * row + col
    pos = torch.tensor([[0.5, 0.5], [3.5, 2.5], [1.0, 0.5], [2.5, 1.0]])  # (x, y)
    np.testing.assert_allclose(sample_pixels(img, pos)[0], [0.0, 11.0, 0.5, 4.0], atol=1e-5)


def test_sample_pixels_bicubic_keeps_fine_detail_that_bilinear_averages_away():
    x = torch.arange(32, dtype=torch.float32)
    img = (((x[None, :] + x[:, None]) % 2) * 2 - 1)[None].repeat(1, 1, 1)  # finest checkerboard
    img = img * torch.cos(x / 32)[None, None, :]  # not exactly at Nyquist
    ys, xs = torch.meshgrid(x + 0.8, x + 0.8, indexing="ij")  # a 0.3-pixel shift
    pos = torch.stack([xs, ys], -1)
    inner = (slice(None), slice(4, -4), slice(4, -4))
    energy = {m: float(sample_pixels(img, pos, m)[inner].pow(2).mean()) for m in ("bilinear", "bicubic")}
    assert energy["bicubic"] > 1.3 * energy["bilinear"]


def test_rigidity_is_one_for_rigid_motion_and_falls_where_the_surface_stretched():
    v, tri = quad()
    edges = mesh_edges(tri)
    assert sorted(map(tuple, edges.tolist())) == [(0, 1), (0, 2), (0, 3), (1, 2), (2, 3)]
    angle = 0.3
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    moved = v @ rot.T + np.array([5.0, -2.0, 1.0])  # carried without stretching
    np.testing.assert_allclose(rigidity(moved, v, edges, 0.1), 1.0, atol=1e-6)
    stretched = v.copy()
    stretched[2, 0] += 0.1  # edge (2, 3) stretches by 5 %, the diagonal (0, 2) by 2.5 %, (1, 2) by 0.1 %
    r = rigidity(stretched, v, edges, 0.1)
    diagonal = (np.hypot(2.1, 2.0) - np.hypot(2.0, 2.0)) / np.hypot(2.0, 2.0)
    expected = [1 - diagonal / 0.1, 1 - (np.hypot(0.1, 2.0) - 2) / 2 / 0.1, 0.5, 0.5]
    np.testing.assert_allclose(r, expected, atol=1e-5)
    np.testing.assert_allclose(rigidity(stretched, v, edges, 0.02)[[2, 3]], 0.0)


def _stripes(size: int = 48, shift: int = 0) -> torch.Tensor:
    """(3, size, size): a smooth ramp plus one-pixel stripes (fine detail)."""
    x = torch.arange(size, dtype=torch.float32)
    fine = ((x + shift) % 2) * 0.2
    img = x[None, :] / size * 0.5 + fine[None, :] + torch.zeros(size, 1)
    return img.expand(3, size, size).clone()


def test_moved_detail_puts_the_source_band_in_place_of_the_render_band():
    from kornia.filters import gaussian_blur2d

    real = _stripes()[None]
    soft = gaussian_blur2d(real, (9, 9), (2.0, 2.0), border_type="replicate")  # a network's render
    source = real + 0.3  # the same detail under another exposure: only its fine band may be used
    src_low, crop_res = smooth(source, 2.0), gaussian_blur2d(source, (5, 5), (1.0, 1.0), "replicate")
    render_band = soft - smooth(soft, 2.0)
    ones, zeros = torch.ones(1, 1, 48, 48), torch.zeros(1, 1, 48, 48)

    def out(fine, band):
        return soft + moved_detail(source, crop_res, src_low, render_band, fine, band)

    inner = (0, 0, slice(4, 44), slice(4, 44))
    # trusted band: the real fine stripes are back, the source's brightness is not
    err, soft_err = (out(ones, ones) - real)[inner].abs().mean(), (soft - real)[inner].abs().mean()
    assert float(err) < 0.25 * float(soft_err)
    assert float((out(ones, ones) - soft)[inner].mean().abs()) < 0.02
    # only the finest detail: the render plus what the source's crop-resolution copy lacks
    torch.testing.assert_close(out(ones, zeros), soft + source - crop_res)
    # only the band: the render's band replaced by the source's band above crop resolution
    torch.testing.assert_close(out(zeros, ones), soft - render_band + crop_res - src_low)
    # no weight at all: the render unchanged
    torch.testing.assert_close(out(zeros, zeros), soft)


def test_paste_with_the_frame_as_its_own_source_gives_the_frame_back():
    """Same geometry, detail from the frame itself, every weight 1: a soft render pasted with the moved
    detail is the footage again (the band is taken at full resolution, not blurred by the crop)."""
    from kornia.filters import gaussian_blur2d

    from renderer.crop import MovedDetail, cut, paste_region

    g = torch.Generator().manual_seed(0)
    frame = gaussian_blur2d(torch.rand(1, 3, 120, 120, generator=g), (5, 5), (0.7, 0.7))[0] * 255
    box, size = np.array([60.0, 60.0, 96.0]), 48  # 2 frame pixels per crop pixel
    crop = cut(frame[None], torch.from_numpy(box[None]).float(), size)[0]
    soft = gaussian_blur2d(crop[None], (9, 9), (2.0, 2.0), "replicate")[0]
    centres = (torch.arange(size, dtype=torch.float32) + 0.5) * (box[2] / size) + float(box[0] - box[2] / 2)
    positions = torch.stack(torch.meshgrid(centres, centres, indexing="xy"), -1)
    ones = torch.ones(size, size)
    moved = MovedDetail(frame, crop, box, positions, ones, ones, soft - smooth(soft[None], 2.0)[0], 2.0)
    plain, _, _ = paste_region(frame, soft, box, torch.ones(1, 1, size, size))
    pasted, _, (rows, cols) = paste_region(
        frame, soft, box, torch.ones(1, 1, size, size), moved=moved, paint=torch.ones(1, 1, size, size)
    )
    inner = (slice(None), slice(16, -16), slice(16, -16))
    real = frame[:, rows, cols][inner]
    assert float((pasted[inner] - real).abs().mean()) < 0.1 * float((plain[inner] - real).abs().mean())


def test_paste_reads_the_source_only_at_valid_surface_positions():
    """Beside the edge of what the source shows (a silhouette, the mouth interior) a frame pixel lies
    between crop pixels with and without a surface position: it reads the source where the surface's own
    positions point, not halfway to the meaningless position of a pixel off it (that drew a dotted line
    along a dub's jaw)."""
    from renderer.crop import MovedDetail, paste_region

    box, size = np.array([60.0, 60.0, 96.0]), 48
    g = torch.Generator().manual_seed(1)
    frame = torch.rand(3, 120, 120, generator=g) * 255  # noise wherever the source is not flat
    frame[:, :, 12:60] = 100.0  # the left half of the box, where the valid positions point
    centres = (torch.arange(size, dtype=torch.float32) + 0.5) * (box[2] / size) + float(box[0] - box[2] / 2)
    positions = torch.stack(torch.meshgrid(centres, centres, indexing="xy"), -1)
    valid = torch.zeros(size, size)
    valid[:, :23] = 1.0
    positions[valid == 0] = 100.0  # off the surface the position means nothing (here: in the noise)
    flat = torch.full((3, size, size), 100.0)
    moved = MovedDetail(frame, flat, box, positions, valid, valid, torch.zeros(3, size, size), 2.0)
    ones = torch.ones(1, 1, size, size)
    pasted, _, (rows, cols) = paste_region(
        torch.full_like(frame, 100.0), flat, box, ones, moved=moved, paint=ones
    )
    # every pixel that got any detail shows the flat source (the box's own edge pixels aside: the crop's
    # bilinear samples there reach outside it)
    assert float((pasted[:, 2:-2, 2:-2] - 100.0).abs().max()) < 1.0


def quad(z: float = 10.0, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-1, -1, z], [1, -1, z], [1, 1, z], [-1, 1, z]], np.float64)
    v[:, 0] += shift
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_same_geometry_maps_every_pixel_to_itself():
    size, focal, center = 32, 100.0, np.array([16.0, 16.0])
    v, tri = quad()
    r = rasterize_reference(v, tri, np.zeros((4, 2)), focal, center, size, size)
    pix = torch.from_numpy(focal * v[:, :2] / v[:, 2:] + center).float()
    pos, valid = source_positions(
        r.triangle_id,
        r.barycentric,
        torch.from_numpy(tri),
        pix,
        torch.from_numpy(v[:, 2]).float(),
        r.depth,
        (1.0, np.zeros(2)),
        torch.ones(2, dtype=torch.bool),
    )
    ys, xs = np.nonzero(r.mask.numpy())
    np.testing.assert_allclose(pos[ys, xs, 0], xs + 0.5, atol=1e-3)
    np.testing.assert_allclose(pos[ys, xs, 1], ys + 0.5, atol=1e-3)
    assert valid[r.mask].min() == 1 and valid[~r.mask].max() == 0


def test_moved_geometry_points_at_the_old_place_and_hidden_or_excluded_points_are_invalid():
    size, focal, center = 32, 100.0, np.array([16.0, 16.0])
    old, tri = quad()
    new, _ = quad(shift=0.2)  # the surface moved 2 px to the right
    r = rasterize_reference(new, tri, np.zeros((4, 2)), focal, center, size, size)
    src = rasterize_reference(old, tri, np.zeros((4, 2)), focal, center, size, size)
    pix = torch.from_numpy(focal * old[:, :2] / old[:, 2:] + center).float()
    args = (r.triangle_id, r.barycentric, torch.from_numpy(tri), pix, torch.from_numpy(old[:, 2]).float())
    pos, valid = source_positions(*args, src.depth, (1.0, np.zeros(2)), torch.ones(2, dtype=torch.bool))
    y, x = 16, 20
    assert pos[y, x, 0].item() == pytest.approx(x + 0.5 - 2.0, abs=1e-3) and valid[y, x] == 1
    # a nearer surface in the source hides the point
    hidden = torch.where(src.depth > 0, src.depth - 1.0, src.depth)
    _, valid2 = source_positions(*args, hidden, (1.0, np.zeros(2)), torch.ones(2, dtype=torch.bool))
    assert valid2.max() == 0
    # triangles that may not be moved (the mouth interior) are never valid
    _, valid3 = source_positions(*args, src.depth, (1.0, np.zeros(2)), torch.tensor([True, False]))
    assert valid3[r.triangle_id == 1].max() == 0 and valid3[r.triangle_id == 0].min() == 1


def test_the_source_moved_onto_a_window_is_the_whole_crops_there_and_invalid_elsewhere():
    from types import SimpleNamespace

    from renderer.inputs import moved_source

    size, focal, center = 32, 100.0, np.array([16.0, 16.0])
    old, tri = quad()
    new, _ = quad(shift=0.2)
    r = rasterize_reference(new, tri, np.zeros((4, 2)), focal, center, size, size)
    src = rasterize_reference(old, tri, np.zeros((4, 2)), focal, center, size, size)
    geo = SimpleNamespace(triangle_id=r.triangle_id, barycentric=r.barycentric)
    crop = torch.rand(3, size, size, generator=torch.Generator().manual_seed(0))
    box = np.array([16.0, 16.0, 32.0])  # the crop is the frame: crop pixel = frame pixel
    args = (
        geo,
        crop,
        box,
        old,
        src.depth,
        (focal, center),
        torch.from_numpy(tri),
        torch.ones(2, dtype=torch.bool),
    )
    whole, pos, valid = moved_source(*args)
    rows, cols = slice(8, 24), slice(16, 32)
    part, pos_w, valid_w = moved_source(*args, window=(rows, cols))
    assert valid[rows, cols].sum() > 50  # the window shows moved pixels
    assert torch.equal(part[:, rows, cols], whole[:, rows, cols]) and torch.equal(
        pos_w[rows, cols], pos[rows, cols]
    )
    assert torch.equal(valid_w, part[3])
    outside = torch.ones(size, size, dtype=torch.bool)
    outside[rows, cols] = False
    assert part[:, outside].abs().max() == 0 and pos_w[outside].abs().max() == 0


def test_renderer_with_source_input_keeps_moved_pixels_where_it_trusts_them():
    from renderer.networks import NeuralRenderer, UNetConfig

    torch.manual_seed(0)
    net = NeuralRenderer(UNetConfig(base=4, depth=2), texture_size=16, source_input=True)
    with torch.no_grad():
        net.interior.out.bias[3] = 50.0  # weight of the moved pixels -> 1
    s = 32
    uv = torch.rand(1, s, s, 2)
    mask = torch.ones(1, 1, s, s)
    moved = torch.rand(1, 3, s, s)
    valid = torch.zeros(1, 1, s, s)
    valid[..., : s // 2] = 1  # left half has moved pixels
    source = torch.cat([moved * valid, valid], 1)
    blank, none = torch.zeros(1, 3, s, s), torch.zeros_like(mask)
    interior, _ = net(uv, mask, none, blank, none, source)
    torch.testing.assert_close(interior[..., : s // 2], moved[..., : s // 2])
    assert (interior[..., s // 2 :] - moved[..., s // 2 :]).abs().mean() > 0.1  # painted where invalid
    with pytest.raises(ValueError, match="moved source"):
        net(uv, mask, torch.zeros_like(mask), torch.zeros(1, 3, s, s), torch.zeros_like(mask))
