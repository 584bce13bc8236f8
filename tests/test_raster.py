"""Rasterizers: the OpenGL backend against the pure-torch reference, orientation, depth, mouth coverage."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderer.raster import RasterOutput, depth_range, empty_output, to_clip
from renderer.raster_ref import TorchRasterizer, rasterize_reference

# ---------------------------------------------------------------------------------------------- fixtures

_GL_CACHE: dict = {}


@pytest.fixture(scope="module")
def gl_rasterizer():
    """Factory ``(width, height) -> GLRasterizer`` sharing one instance per size; skips without EGL."""
    from renderer.gl import GLRasterizer

    def make(width: int, height: int):
        key = (width, height)
        if key not in _GL_CACHE:
            try:
                _GL_CACHE[key] = GLRasterizer(width, height)
            except RuntimeError as e:
                pytest.skip(f"no headless OpenGL (EGL) context on this machine: {e}")
        return _GL_CACHE[key]

    yield make
    for r in _GL_CACHE.values():
        r.release()
    _GL_CACHE.clear()


@pytest.fixture(params=["gl", "ref"])
def backend(request, gl_rasterizer):
    """Factory ``(width, height) -> rasterizer`` for each backend."""
    if request.param == "gl":
        return gl_rasterizer
    return TorchRasterizer


def rotation(yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """Object-to-camera rotation (OpenCV camera): yaw about y, pitch about x, roll about z."""
    y, p, r = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return rz @ rx @ ry


def mouth_open_expression(model, amount: float = 3.0) -> np.ndarray:
    """Expression coefficients setting the component that most opens the inner lips (13–14) to ``amount``."""
    base = model.vertices(np.zeros(model.num_id))
    gaps = [
        np.linalg.norm((base[13] + amount * b[13]) - (base[14] + amount * b[14])) for b in model.exp_basis
    ]
    exp = np.zeros(model.num_exp)
    exp[int(np.argmax(gaps))] = amount
    return exp


SIZE = 160
FOCAL = 400.0
CENTER = np.array([81.0, 78.5])

POSES = {
    # name: (rotation kwargs, translation, mouth open, focal)
    "frontal": ({}, (0.0, 0.0, 50.0), False, FOCAL),
    "head_turn": ({"yaw_deg": 40.0, "pitch_deg": -10.0, "roll_deg": 8.0}, (1.0, -0.5, 48.0), False, FOCAL),
    "open_mouth": ({"yaw_deg": -15.0, "pitch_deg": 12.0}, (0.0, 1.0, 52.0), True, FOCAL),
    # tracker-like telephoto camera (focal 16 x image size, face ~5 m away): nearly orthographic
    "telephoto": ({"yaw_deg": 20.0}, (0.5, 0.0, 400.0), True, FOCAL * 8.0),
}


def posed(model, name: str) -> tuple[np.ndarray, float]:
    rot_kw, trans, open_mouth, focal = POSES[name]
    exp = mouth_open_expression(model) if open_mouth else np.zeros(model.num_exp)
    verts = model.vertices(np.zeros(model.num_id), exp)
    return verts @ rotation(**rot_kw).T + np.asarray(trans), focal


@pytest.fixture(scope="module")
def reference_outputs(face_model):
    """Reference rasterization of every pose (computed once; it is slow)."""
    out = {}
    for name in POSES:
        verts, focal = posed(face_model, name)
        out[name] = rasterize_reference(
            verts, face_model.triangles, face_model.uvs, focal, CENTER, SIZE, SIZE
        )
    return out


def point_in_polygon(px: np.ndarray, py: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule: which points ``(px, py)`` lie inside the closed polygon ``(N, 2)``."""
    inside = np.zeros(px.shape, dtype=bool)
    n = len(poly)
    for i in range(n):
        (x0, y0), (x1, y1) = poly[i], poly[(i + 1) % n]
        crosses = (y0 > py) != (y1 > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = x0 + (py - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (px < x_at)
    return inside


def one_triangle(corners_cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    verts = np.asarray(corners_cam, dtype=np.float64)
    tris = np.array([[0, 1, 2]])
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=np.float32)
    return verts, tris, uvs


# --------------------------------------------------------------------------------------------- to_clip


def test_to_clip_maps_pixels_to_gl_ndc():
    width, height, focal, center, near, far = 200, 100, 150.0, np.array([97.0, 52.0]), 2.0, 80.0
    pts = np.array([[0.0, 0.0, 10.0], [3.0, -2.0, 20.0], [-1.0, 4.0, near], [2.0, 1.0, far]])
    clip = to_clip(pts, focal, center, width, height, near, far)
    assert clip.shape == (4, 4) and clip.dtype == np.float32
    ndc = clip[:, :3] / clip[:, 3:]
    u, v = (focal * pts[:, :2] / pts[:, 2:] + center).T
    np.testing.assert_allclose(ndc[:, 0], 2 * u / width - 1, atol=1e-5)
    np.testing.assert_allclose(ndc[:, 1], 1 - 2 * v / height, atol=1e-5)  # GL: y up, +1 = top row
    np.testing.assert_allclose(clip[:, 3], pts[:, 2])
    np.testing.assert_allclose(ndc[2:, 2], [-1.0, 1.0], atol=1e-5)
    # the principal point is the image centre when center = size / 2
    mid = to_clip(np.array([[0.0, 0.0, 5.0]]), focal, [100.0, 50.0], width, height, near, far)
    np.testing.assert_allclose(mid[0, :2] / mid[0, 3], [0.0, 0.0], atol=1e-6)


def test_to_clip_and_depth_range_reject_bad_input():
    with pytest.raises(ValueError, match="near"):
        to_clip(np.zeros((1, 3)), 1.0, [0, 0], 4, 4, 5.0, 1.0)
    with pytest.raises(ValueError, match=r"\(V,3\)"):
        to_clip(np.zeros((3, 2)), 1.0, [0, 0], 4, 4, 1.0, 2.0)
    assert depth_range(np.array([10.0, 20.0]), None, None) == (5.0, 40.0)
    assert depth_range(np.array([10.0, 20.0]), 1.0, None) == (1.0, 40.0)


# ------------------------------------------------------------------------------------ per-backend checks


def test_output_types_and_background_padding(backend, face_model):
    verts, focal = posed(face_model, "frontal")
    out = backend(SIZE, SIZE).rasterize(verts, face_model.triangles, face_model.uvs, focal, CENTER)
    assert isinstance(out, RasterOutput)
    assert out.triangle_id.shape == (SIZE, SIZE) and out.triangle_id.dtype == torch.int64
    assert out.barycentric.shape == (SIZE, SIZE, 3) and out.barycentric.dtype == torch.float32
    assert out.uv.shape == (SIZE, SIZE, 2) and out.uv.dtype == torch.float32
    assert out.depth.shape == (SIZE, SIZE) and out.depth.dtype == torch.float32
    assert out.mask.shape == (SIZE, SIZE) and out.mask.dtype == torch.bool
    assert torch.equal(out.mask, out.triangle_id >= 0)
    bg = ~out.mask
    assert bg.any() and out.mask.any()
    assert (out.triangle_id[bg] == -1).all()
    assert (out.barycentric[bg] == 0).all() and (out.uv[bg] == 0).all() and (out.depth[bg] == 0).all()
    fg = out.mask
    assert out.triangle_id.max() < len(face_model.triangles)
    torch.testing.assert_close(out.barycentric[fg].sum(-1), torch.ones(int(fg.sum())), atol=1e-4, rtol=0)
    assert out.barycentric[fg].min() > -1e-3
    assert ((out.uv[fg] >= -1e-4) & (out.uv[fg] <= 1 + 1e-4)).all()


def test_orientation_top_left_triangle(backend):
    """A triangle up and left of the optical axis (x < 0, y < 0 in OpenCV) lands in the top-left corner."""
    size, focal, center = 64, 64.0, np.array([32.0, 32.0])
    verts, tris, uvs = one_triangle([[-4.3, -4.4, 10.0], [-1.7, -4.1, 10.0], [-4.2, -1.6, 10.0]])
    out = backend(size, size).rasterize(verts, tris, uvs, focal, center)
    rows, cols = np.nonzero(out.mask.numpy())
    assert len(rows) > 50
    # pixel bounds of the projected corners: columns 4.5 .. 21.1, rows 3.8 .. 21.8
    assert rows.min() >= 3 and rows.max() <= 22 and cols.min() >= 4 and cols.max() <= 21
    # the right angle is at the top-left: the first covered row is wide, the last one narrow
    top, bottom = out.mask[rows.min() + 1].sum(), out.mask[rows.max() - 1].sum()
    assert top > 3 * bottom


def test_positive_x_and_y_map_right_and_down(backend):
    size, focal, center = 64, 64.0, np.array([30.0, 34.0])
    # small triangle around camera point (x=+2, y=0, z=10) -> column ~ 42.8 > cx, row ~ cy
    verts, tris, uvs = one_triangle([[1.6, -0.4, 10.0], [2.4, -0.4, 10.0], [2.0, 0.45, 10.0]])
    rast = backend(size, size)
    out = rast.rasterize(verts, tris, uvs, focal, center)
    rows, cols = np.nonzero(out.mask.numpy())
    assert len(cols) > 0 and cols.min() > center[0] and abs(rows.mean() + 0.5 - center[1]) < 2
    # the same triangle moved to y = +2 appears below the principal point
    down = verts[:, [1, 0, 2]]  # swap x and y
    out = rast.rasterize(down, tris, uvs, focal, center)
    rows, cols = np.nonzero(out.mask.numpy())
    assert len(rows) > 0 and rows.min() > center[1] and abs(cols.mean() + 0.5 - center[0]) < 2


def test_depth_and_barycentrics_are_perspective_correct(backend):
    """A strongly tilted triangle: depth is the camera z of the ray/plane hit, barycentrics reproject."""
    size, focal, center = 96, 80.0, np.array([47.5, 49.0])
    verts, tris, uvs = one_triangle([[-6.0, -5.0, 8.0], [7.0, -4.0, 30.0], [-2.0, 6.0, 14.0]])
    out = backend(size, size).rasterize(verts, tris, uvs, focal, center)
    fg = out.mask.numpy()
    assert fg.sum() > 500
    rows, cols = np.nonzero(fg)
    # analytic depth: plane n.X = d, ray X = z * ((c + .5 - cx) / f, (r + .5 - cy) / f, 1)
    normal = np.cross(verts[1] - verts[0], verts[2] - verts[0])
    offset = normal @ verts[0]
    rays = np.stack(
        [(cols + 0.5 - center[0]) / focal, (rows + 0.5 - center[1]) / focal, np.ones(len(rows))], 1
    )
    z_true = offset / (rays @ normal)
    np.testing.assert_allclose(out.depth.numpy()[fg], z_true, rtol=2e-4)
    # the barycentric combination of the corners is the 3D point seen through the pixel centre
    pts = out.barycentric.numpy()[fg].astype(np.float64) @ verts
    np.testing.assert_allclose(pts[:, 2], z_true, rtol=2e-4)
    proj = focal * pts[:, :2] / pts[:, 2:] + center
    np.testing.assert_allclose(proj, np.stack([cols + 0.5, rows + 0.5], 1), atol=2e-2)
    # and the UVs are the same combination of the corner UVs
    np.testing.assert_allclose(out.uv.numpy()[fg], out.barycentric.numpy()[fg] @ uvs, atol=1e-5)


def test_no_backface_culling_and_nearest_surface_wins(backend):
    size, focal, center = 48, 48.0, np.array([24.0, 24.0])
    far_tri = [[-3.0, -3.0, 12.0], [3.0, -3.0, 12.0], [0.0, 3.0, 12.0]]
    near_tri = [[-2.0, -2.0, 10.0], [0.0, 2.0, 10.0], [2.0, -2.0, 10.0]]  # opposite winding
    verts = np.array(far_tri + near_tri)
    uvs = np.zeros((6, 2), dtype=np.float32)
    rast = backend(size, size)
    for order in ([[0, 1, 2], [3, 4, 5]], [[3, 4, 5], [0, 1, 2]]):
        tris = np.array(order)
        near_id = order.index([3, 4, 5])
        out = rast.rasterize(verts, tris, uvs, focal, center)
        ids = out.triangle_id.numpy()
        assert (ids == near_id).sum() > 50 and (ids == 1 - near_id).sum() > 50
        np.testing.assert_allclose(out.depth.numpy()[ids == near_id], 10.0, rtol=1e-5)
        # the centre of the image sees the near triangle whichever is drawn first
        assert ids[size // 2, size // 2] == near_id


def test_mouth_interior_covered_when_open(backend, face_model):
    verts, focal = posed(face_model, "open_mouth")
    rast = backend(SIZE, SIZE)
    out = rast.rasterize(verts, face_model.triangles, face_model.uvs, focal, CENTER)
    inner = face_model.landmark_vertices[face_model.landmark_groups["lips_inner"]]
    poly = focal * verts[inner, :2] / verts[inner, 2:] + CENTER
    rr, cc = np.mgrid[0:SIZE, 0:SIZE]
    in_mouth = point_in_polygon(cc + 0.5, rr + 0.5, poly)
    assert in_mouth.sum() > 40, "the mouth should be visibly open"
    assert out.mask.numpy()[in_mouth].all(), "background pixels inside the open mouth"
    interior = np.nonzero(face_model.triangle_regions["mouth_interior"])[0]
    seen = np.isin(out.triangle_id.numpy()[in_mouth], interior)
    assert seen.mean() > 0.8
    # the check has teeth: without the closing triangles the open mouth shows background
    keep = ~face_model.triangle_regions["mouth_interior"]
    holey = rast.rasterize(verts, face_model.triangles[keep], face_model.uvs, focal, CENTER)
    assert (~holey.mask.numpy()[in_mouth]).mean() > 0.5


def test_out_argument_fills_in_place(backend, face_model):
    rast = backend(SIZE, SIZE)
    a_verts, focal = posed(face_model, "frontal")
    b_verts, _ = posed(face_model, "open_mouth")
    expected = rast.rasterize(b_verts, face_model.triangles, face_model.uvs, focal, CENTER)
    out = rast.rasterize(a_verts, face_model.triangles, face_model.uvs, focal, CENTER)
    ptrs = [t.data_ptr() for t in (out.triangle_id, out.barycentric, out.uv, out.depth, out.mask)]
    again = rast.rasterize(b_verts, face_model.triangles, face_model.uvs, focal, CENTER, out=out)
    assert again is out
    assert ptrs == [t.data_ptr() for t in (out.triangle_id, out.barycentric, out.uv, out.depth, out.mask)]
    for name in ("triangle_id", "barycentric", "uv", "depth", "mask"):
        assert torch.equal(getattr(out, name), getattr(expected, name)), name
    filled = rast.rasterize(
        b_verts, face_model.triangles, face_model.uvs, focal, CENTER, out=empty_output(SIZE, SIZE)
    )
    assert torch.equal(filled.triangle_id, expected.triangle_id)
    with pytest.raises(ValueError, match="out.triangle_id"):
        rast.rasterize(
            b_verts, face_model.triangles, face_model.uvs, focal, CENTER, out=empty_output(8, SIZE)
        )


def test_rejects_bad_shapes(backend):
    rast = backend(8, 8)
    verts, tris, uvs = one_triangle([[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]])
    with pytest.raises(ValueError, match="uvs"):
        rast.rasterize(verts, tris, uvs[:2], 8.0, [4.0, 4.0])
    with pytest.raises(ValueError, match="triangles"):
        rast.rasterize(verts, tris + 1, uvs, 8.0, [4.0, 4.0])
    with pytest.raises(ValueError, match="vertices_cam"):
        rast.rasterize(verts[:, :2], tris, uvs, 8.0, [4.0, 4.0])


# --------------------------------------------------------------------------------- GL against reference


@pytest.mark.parametrize("pose", list(POSES))
def test_gl_matches_reference_on_posed_face(pose, face_model, gl_rasterizer, reference_outputs):
    verts, focal = posed(face_model, pose)
    gl = gl_rasterizer(SIZE, SIZE).rasterize(
        torch.from_numpy(verts).float(), torch.from_numpy(face_model.triangles), face_model.uvs, focal, CENTER
    )
    ref = reference_outputs[pose]
    union = (gl.mask | ref.mask).numpy()
    same = (gl.triangle_id == ref.triangle_id).numpy()
    assert union.sum() > 3000
    assert same.mean() >= 0.99
    assert same[union].mean() >= 0.99, f"triangle ids agree on only {same[union].mean():.4f} of the face"
    both = torch.from_numpy(same) & gl.mask
    torch.testing.assert_close(gl.barycentric[both], ref.barycentric[both], atol=2e-3, rtol=0)
    torch.testing.assert_close(gl.uv[both], ref.uv[both], atol=2e-4, rtol=0)
    torch.testing.assert_close(gl.depth[both], ref.depth[both], atol=0, rtol=1e-4)


def test_gl_reuses_buffers_without_aliasing_outputs(face_model, gl_rasterizer):
    rast = gl_rasterizer(SIZE, SIZE)
    a_verts, focal = posed(face_model, "frontal")
    b_verts, _ = posed(face_model, "head_turn")
    a = rast.rasterize(a_verts, face_model.triangles, face_model.uvs, focal, CENTER)
    a_ids = a.triangle_id.clone()
    b = rast.rasterize(b_verts, face_model.triangles, face_model.uvs, focal, CENTER)
    assert torch.equal(a.triangle_id, a_ids), "a later call overwrote an earlier output"
    assert not torch.equal(a.triangle_id, b.triangle_id)
    # new UVs (same topology) take effect
    flipped = face_model.uvs[:, ::-1].copy()
    c = rast.rasterize(a_verts, face_model.triangles, flipped, focal, CENTER)
    assert torch.equal(c.triangle_id, a.triangle_id)
    torch.testing.assert_close(c.uv[c.mask], a.uv[a.mask].flip(-1), atol=1e-6, rtol=0)
    # an empty mesh gives an all-background image
    empty = rast.rasterize(a_verts, np.zeros((0, 3), dtype=np.int64), face_model.uvs, focal, CENTER)
    assert not empty.mask.any() and (empty.triangle_id == -1).all()


def test_gl_release_is_final():
    from renderer.gl import GLRasterizer

    try:
        rast = GLRasterizer(8, 8)
    except RuntimeError as e:
        pytest.skip(f"no headless OpenGL (EGL) context on this machine: {e}")
    with rast:
        assert rast.renderer_name
    rast.release()  # idempotent
    verts, tris, uvs = one_triangle([[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]])
    with pytest.raises(RuntimeError, match="released"):
        rast.rasterize(verts, tris, uvs, 8.0, [4.0, 4.0])
