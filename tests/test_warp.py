"""Tests for renderer.warp: the surface correspondence that moves the footage's detail."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderer.raster_ref import rasterize_reference
from renderer.warp import sample_pixels, source_positions, stillness, surface_points, transfer_band


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


def test_stillness_is_one_where_nothing_moved_and_falls_linearly_to_zero():
    src = np.zeros((4, 3))
    tgt = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.1, 0], [0.5, 0, 0]])
    np.testing.assert_allclose(stillness(tgt, src, 0.1), [1.0, 0.5, 0.0, 0.0], atol=1e-6)


def _stripes(size: int = 48, shift: int = 0) -> torch.Tensor:
    """(3, size, size): a smooth ramp plus one-pixel stripes (fine detail)."""
    x = torch.arange(size, dtype=torch.float32)
    fine = ((x + shift) % 2) * 0.2
    img = x[None, :] / size * 0.5 + fine[None, :] + torch.zeros(size, 1)
    return img.expand(3, size, size).clone()


def test_transfer_band_takes_fine_detail_from_the_trusted_source_and_keeps_the_render_elsewhere():
    from kornia.filters import gaussian_blur2d

    real = _stripes()
    soft = gaussian_blur2d(real[None], (9, 9), (2.0, 2.0), border_type="replicate")  # a network's render
    source = real + 0.3  # the same detail under another exposure: only its fine band may be used
    weight = torch.zeros(48, 48)
    weight[:, :24] = 1
    out = transfer_band(soft, source, weight, sigma=2.0)[0]
    inner = (slice(4, 44), slice(2, 16))
    # deep inside the trusted part: the real fine stripes are back, the source's brightness is not
    assert float((out - real)[(0, *inner)].abs().mean()) < 0.25 * float(
        (soft[0] - real)[(0, *inner)].abs().mean()
    )
    assert float((out - soft[0])[(0, *inner)].mean().abs()) < 0.02
    # untrusted part (beyond the fade): exactly the render
    torch.testing.assert_close(out[:, :, 30:], soft[0, :, :, 30:])
    # no weight at all: the render unchanged
    torch.testing.assert_close(transfer_band(soft, source, torch.zeros(48, 48), 2.0), soft)


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
