"""Fast rasterizer: OpenGL 3.3 through moderngl on a headless EGL context (Mesa llvmpipe on CPU).

This module is the only place that knows OpenGL's image orientation. **The single flip**: OpenGL's
window coordinates put row 0 at the *bottom* of the framebuffer, and ``glReadPixels`` returns rows
bottom-to-top, while every array in nvp has row 0 at the *top* of the image. Instead of rendering
right-side-up and reversing the rows after readback, the vertex shader negates clip-space y
(``gl_Position.y = -clip.y``). Image row ``r`` then lands in framebuffer row ``r`` (window y in
``[r, r+1)``, sampled at ``r + 0.5`` exactly like the reference rasterizer), and the readback arrays are
already in image order, with no copy. The negation mirrors the screen-space winding, which is harmless
because backface culling is off and nothing uses ``gl_FrontFacing``.

Framebuffer layout: four float32 colour attachments, each read back straight into the contiguous tensor
of its ``RasterOutput`` field, and moderngl's depth renderbuffer; colours cleared to 0, depth to far.

- attachment 0, RGBA32F: ``(b0, b1, b2, 1)``, read back as RGB -> ``barycentric``.
- attachment 1, RG32F: ``(u, v)`` -> ``uv``.
- attachment 2, R32F: camera z (``w_clip``, interpolated) -> ``depth``.
- attachment 3, R32F: ``gl_PrimitiveID + 1`` (exact as a float32 up to 2^24) -> ``triangle_id`` after
  subtracting 1, so the cleared background decodes to ``-1``.

The mesh is drawn non-indexed (three vertices per triangle) so each corner can carry its own barycentric
unit vector; perspective-correct interpolation of those vectors gives perspective-correct barycentrics.
Only the clip-coordinate buffer is written per call; barycentric and UV buffers are rebuilt only when the
triangles or the UVs change.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from renderer.raster import (
    RasterOutput,
    as_numpy,
    check_mesh,
    check_output,
    depth_range,
    empty_output,
    to_clip,
)

log = logging.getLogger(__name__)

_VERTEX_SHADER = """
#version 330
in vec4 in_clip;
in vec3 in_bary;
in vec2 in_uv;
out vec3 v_bary;
out vec2 v_uv;
out float v_depth;
void main() {
    v_bary = in_bary;
    v_uv = in_uv;
    v_depth = in_clip.w;  // w_clip is the camera z
    // The single OpenGL flip (see the module docstring): image row 0 -> framebuffer row 0.
    gl_Position = vec4(in_clip.x, -in_clip.y, in_clip.z, in_clip.w);
}
"""

_FRAGMENT_SHADER = """
#version 330
in vec3 v_bary;
in vec2 v_uv;
in float v_depth;
layout(location = 0) out vec4 out_bary;
layout(location = 1) out vec2 out_uv;
layout(location = 2) out float out_depth;
layout(location = 3) out float out_id;
void main() {
    out_bary = vec4(v_bary, 1.0);
    out_uv = v_uv;
    out_depth = v_depth;
    out_id = float(gl_PrimitiveID + 1);  // exact in float32 up to 2^24
}
"""


#: float32 components of the colour attachments: barycentrics (RGBA, read back as RGB), uv, depth, id + 1.
_ATTACHMENT_COMPONENTS = (4, 2, 1, 1)


def create_egl_context():
    """A standalone OpenGL >= 3.3 context on EGL (headless). Raises ``RuntimeError`` if none is available."""
    import moderngl

    try:
        return moderngl.create_standalone_context(backend="egl", require=330)
    except Exception as e:  # moderngl/glcontext raise plain Exceptions with the EGL error text
        raise RuntimeError(f"cannot create a headless EGL OpenGL 3.3 context: {e}") from e


class GLRasterizer:
    """Rasterize triangle meshes into ``RasterOutput`` with OpenGL (moderngl, headless EGL).

    Owns its OpenGL context, framebuffer and vertex buffers; use it as a context manager (or call
    :meth:`release`). Not thread-safe; one instance per thread.

    Args:
        width, height: output image size in pixels.
        near, far: clipping planes in the units of the vertices; None (default) chooses them per call from
            the vertex depths (see :func:`renderer.raster.depth_range`). Triangles are clipped by OpenGL at
            these planes.

    Example::

        with GLRasterizer(512, 512) as rast:
            frags = rast.rasterize(vertices_cam, model.triangles, model.uvs, seq.focal, seq.center)
    """

    def __init__(self, width: int, height: int, near: float | None = None, far: float | None = None) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"width and height must be positive, got {width}x{height}")
        self.width = int(width)
        self.height = int(height)
        self.near = near
        self.far = far
        self._ctx = create_egl_context()
        self._mesh_key: tuple[np.ndarray, np.ndarray] | None = None
        self._vao = None
        self._buffers: list = []
        self._id_staging = np.zeros((self.height, self.width), dtype=np.float32)
        with self._ctx:
            import moderngl

            ctx = self._ctx
            self._program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
            size = (self.width, self.height)
            self._fbo = ctx.framebuffer(
                color_attachments=[
                    ctx.renderbuffer(size, components=c, dtype="f4") for c in _ATTACHMENT_COMPONENTS
                ],
                depth_attachment=ctx.depth_renderbuffer(size),
            )
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
            ctx.depth_func = "<"
            log.debug("GLRasterizer %dx%d on %s", self.width, self.height, ctx.info.get("GL_RENDERER"))

    # ------------------------------------------------------------------ lifetime
    def __enter__(self) -> GLRasterizer:
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def release(self) -> None:
        """Free the OpenGL context and everything in it (idempotent)."""
        if self._ctx is not None:
            self._ctx.release()
            self._ctx = None
            self._vao = None
            self._buffers = []

    @property
    def renderer_name(self) -> str:
        """The OpenGL renderer string (e.g. ``llvmpipe (LLVM 15.0.6, 256 bits)``)."""
        self._check_alive()
        with self._ctx:
            return str(self._ctx.info.get("GL_RENDERER"))

    def _check_alive(self) -> None:
        if self._ctx is None:
            raise RuntimeError("GLRasterizer was released; create a new one")

    # ------------------------------------------------------------------ drawing
    def _prepare_mesh(self, triangles: np.ndarray, uvs: np.ndarray) -> None:
        """(Re)build the static per-corner buffers when the topology or the UVs change."""
        key = self._mesh_key
        if key is not None and np.array_equal(key[0], triangles) and np.array_equal(key[1], uvs):
            return
        ctx = self._ctx
        for b in self._buffers:
            b.release()
        if self._vao is not None:
            self._vao.release()
        n = triangles.shape[0] * 3
        bary = np.tile(np.eye(3, dtype=np.float32), (triangles.shape[0], 1))
        corner_uv = np.ascontiguousarray(uvs[triangles.reshape(-1)], dtype=np.float32)
        clip_buf = ctx.buffer(reserve=n * 16, dynamic=True)
        bary_buf = ctx.buffer(bary.tobytes())
        uv_buf = ctx.buffer(corner_uv.tobytes())
        self._vao = ctx.vertex_array(
            self._program,
            [(clip_buf, "4f", "in_clip"), (bary_buf, "3f", "in_bary"), (uv_buf, "2f", "in_uv")],
        )
        self._buffers = [clip_buf, bary_buf, uv_buf]
        self._mesh_key = (triangles.copy(), uvs.copy())

    def rasterize(
        self,
        vertices_cam: np.ndarray | torch.Tensor,
        triangles: np.ndarray | torch.Tensor,
        uvs: np.ndarray | torch.Tensor,
        focal: float,
        center: np.ndarray | torch.Tensor,
        out: RasterOutput | None = None,
    ) -> RasterOutput:
        """Rasterize one mesh seen by an OpenCV pinhole camera.

        Args:
            vertices_cam: ``(V, 3)`` vertices in the camera frame (x right, y down, z forward), any units.
            triangles: ``(F, 3)`` vertex indices (any winding; no culling).
            uvs: ``(V, 2)`` per-vertex texture coordinates.
            focal: focal length in pixels.
            center: ``(2,)`` principal point in pixels.
            out: optional ``RasterOutput`` of this size (e.g. the previous call's result, see
                :func:`renderer.raster.empty_output`) that is overwritten in place and returned. Saves
                allocating (and page-faulting) ~37 bytes per pixel on every call, which is a large part of
                the cost at 512² on this CPU backend. Default: new tensors.

        Returns:
            ``RasterOutput`` of size ``(height, width)``, row 0 = top of the image (``out`` if given).
        """
        self._check_alive()
        verts = as_numpy(vertices_cam, np.float64)
        tris = as_numpy(triangles, np.int64)
        uv = as_numpy(uvs, np.float32)
        c = as_numpy(center, np.float64).reshape(-1)
        check_mesh(verts, tris, uv, c)
        near, far = depth_range(verts[:, 2], self.near, self.far)
        clip = to_clip(verts, float(focal), c, self.width, self.height, near, far)
        if out is None:
            out = empty_output(self.height, self.width)
        else:
            check_output(out, self.height, self.width)
        # Each target is read straight into its final contiguous tensor (no slicing copies afterwards);
        # the float id goes through a staging buffer that lives as long as the rasterizer.
        with self._ctx:
            self._fbo.use()
            self._fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            if tris.shape[0]:
                self._prepare_mesh(tris, uv)
                self._buffers[0].write(np.ascontiguousarray(clip[tris.reshape(-1)]).tobytes())
                self._vao.render(vertices=tris.shape[0] * 3)
            targets = (out.barycentric.numpy(), out.uv.numpy(), out.depth.numpy(), self._id_staging)
            for i, target in enumerate(targets):
                comps = 1 if target.ndim == 2 else target.shape[2]
                self._fbo.read_into(target, components=comps, attachment=i, dtype="f4")
        out.triangle_id.copy_(torch.from_numpy(self._id_staging)).sub_(1)
        torch.ge(out.triangle_id, 0, out=out.mask)
        return out
