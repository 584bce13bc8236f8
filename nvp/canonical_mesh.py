"""Reader for mediapipe's canonical face mesh (``geometry_pipeline_metadata_landmarks.binarypb``).

The file is a protobuf ``GeometryPipelineMetadata``: field 1 ``canonical_mesh`` (a ``Mesh3d`` with
packed float ``vertex_buffer`` = x, y, z, u, v per vertex and packed uint32 ``index_buffer`` of triangles)
and repeated field 2 ``procrustes_landmark_basis`` (landmark id, weight). Only the protobuf wire format is
needed to read it, so it is decoded here without the protobuf package.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from nvp.errors import FormatError


@dataclass(frozen=True)
class CanonicalMesh:
    """mediapipe's canonical face mesh.

    Attributes:
        vertices: ``(468, 3)`` float32, centimetres, mediapipe model axes (x right, y up, z towards viewer).
        uvs: ``(468, 2)`` float32 texture coordinates in [0, 1], v = 0 at the top of the texture.
        triangles: ``(898, 3)`` int64 vertex indices.
        procrustes_weights: ``(468,)`` float32 weights mediapipe uses to align landmarks to the mesh
            (zero for vertices it ignores).
    """

    vertices: np.ndarray
    uvs: np.ndarray
    triangles: np.ndarray
    procrustes_weights: np.ndarray


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(buf):
            raise FormatError("truncated protobuf varint")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7


def _fields(buf: bytes) -> list[tuple[int, int, bytes | int]]:
    """Split a protobuf message into (field number, wire type, payload) triples."""
    out, pos = [], 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
        elif wire == 1:
            value, pos = buf[pos : pos + 8], pos + 8
        elif wire == 2:
            n, pos = _varint(buf, pos)
            value, pos = buf[pos : pos + n], pos + n
        elif wire == 5:
            value, pos = buf[pos : pos + 4], pos + 4
        else:
            raise FormatError(f"unsupported protobuf wire type {wire}")
        out.append((field, wire, value))
    return out


def _packed_varints(buf: bytes) -> list[int]:
    vals, pos = [], 0
    while pos < len(buf):
        v, pos = _varint(buf, pos)
        vals.append(v)
    return vals


def parse_geometry_metadata(data: bytes) -> CanonicalMesh:
    """Decode the canonical mesh from the bytes of ``geometry_pipeline_metadata_landmarks.binarypb``."""
    vertex_buffer: list[float] = []
    index_buffer: list[int] = []
    weights = {}
    for field, wire, value in _fields(data):
        if field == 1 and wire == 2:
            for f, w, v in _fields(value):
                if f == 3 and w == 2:
                    vertex_buffer.extend(struct.unpack(f"<{len(v) // 4}f", v))
                elif f == 3 and w == 5:
                    vertex_buffer.append(struct.unpack("<f", v)[0])
                elif f == 4 and w == 2:
                    index_buffer.extend(_packed_varints(v))
                elif f == 4 and w == 0:
                    index_buffer.append(v)
        elif field == 2 and wire == 2:
            lid, weight = 0, 0.0
            for f, w, v in _fields(value):
                if f == 1 and w == 0:
                    lid = v
                elif f == 2 and w == 5:
                    weight = struct.unpack("<f", v)[0]
            weights[lid] = weight
    if len(vertex_buffer) % 5 or len(index_buffer) % 3 or not vertex_buffer:
        raise FormatError(
            f"canonical mesh malformed: {len(vertex_buffer)} vertex floats, {len(index_buffer)} indices"
        )
    vb = np.asarray(vertex_buffer, dtype=np.float32).reshape(-1, 5)
    tris = np.asarray(index_buffer, dtype=np.int64).reshape(-1, 3)
    w = np.zeros(len(vb), dtype=np.float32)
    for lid, weight in weights.items():
        if lid < len(w):
            w[lid] = weight
    return CanonicalMesh(
        vertices=vb[:, :3].copy(), uvs=vb[:, 3:].copy(), triangles=tris, procrustes_weights=w
    )
