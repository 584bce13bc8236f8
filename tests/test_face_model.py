"""The shipped face model, its topology, regions and file format."""

from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest

from nvp.canonical_mesh import parse_geometry_metadata
from nvp.errors import FormatError
from nvp.face_model import FaceModel
from nvp.topology import boundary_loops


def test_shapes_and_sizes(face_model):
    m = face_model
    assert m.template.shape == (468, 3)
    assert m.num_exp >= 32 and m.exp_basis.shape == (m.num_exp, 468, 3)
    assert m.id_basis.shape == (m.num_id, 468, 3)
    assert m.triangles.shape == (898, 3)
    assert (0 <= m.uvs).all() and (m.uvs <= 1).all()
    assert len(m.sha256) == 64


def test_face_is_in_opencv_object_axes(face_model):
    m = face_model
    # chin (152) below forehead (10): y down; nose tip (1) nearer the camera than the ear-side contour
    assert m.template[152, 1] > m.template[10, 1]
    assert m.template[1, 2] < m.template[234, 2]
    # subject's right eye corner (33) is on the image left (x < 0)
    assert m.template[33, 0] < 0 < m.template[263, 0]
    assert 11 < m.face_width() < 18  # centimetres


def test_mouth_and_eyes_are_closed_by_triangles(face_model):
    loops = boundary_loops(face_model.triangles)
    assert len(loops) == 1  # only the face outline: mouth and eyes are covered
    inner = set(face_model.landmark_groups["lips_inner"].tolist())
    mouth = face_model.triangles[face_model.triangle_regions["mouth_interior"]]
    assert len(mouth) >= 10 and all(set(t) <= inner for t in mouth.tolist())
    assert face_model.triangle_regions["eye_interior"].sum() >= 10


def test_regions_are_where_they_belong(face_model):
    m = face_model
    r = m.vertex_regions
    for name in ("lips", "mouth", "jaw", "eyes", "upper_face"):
        assert r[name].any(), name
    assert (r["lips"] <= r["mouth"]).all()
    assert not (r["lips"] & r["upper_face"]).any()
    y = m.template[:, 1]
    assert y[r["jaw"]].mean() > y[r["lips"]].mean() > y[r["eyes"]].mean()
    assert r["lips"][13] and r["lips"][14]


def test_expression_basis_moves_the_mouth_more_than_the_forehead(face_model):
    m = face_model
    disp = np.linalg.norm(m.exp_basis, axis=-1)  # (K, V)
    lips, upper = m.vertex_regions["lips"], m.vertex_regions["upper_face"] & ~m.vertex_regions["eyes"]
    assert disp[:4, lips].mean() > 2 * disp[:4, upper].mean()


def test_vertices_are_linear(face_model):
    m = face_model
    a = np.zeros(m.num_id, np.float32)
    d = np.zeros((2, m.num_exp), np.float32)
    d[1, 0] = 1
    v = m.vertices(a, d)
    np.testing.assert_allclose(v[0], m.template, atol=1e-6)
    np.testing.assert_allclose(v[1] - v[0], m.exp_basis[0], atol=1e-5)


def test_save_load_round_trip_and_hash_check(face_model, tmp_path):
    js = face_model.save(tmp_path / "fm")
    loaded = FaceModel.load(js)
    np.testing.assert_array_equal(loaded.exp_basis, face_model.exp_basis)
    assert set(loaded.vertex_regions) == set(face_model.vertex_regions)
    npz = tmp_path / "fm.npz"
    data = bytearray(npz.read_bytes())
    data[-10] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="sha256"):
        FaceModel.load(js)


def test_load_rejects_other_versions(face_model, tmp_path):
    js = face_model.save(tmp_path / "fm")
    m = json.loads(js.read_text())
    m["version"] = 99
    js.write_text(json.dumps(m))
    with pytest.raises(FormatError, match="version"):
        FaceModel.load(js)
    with pytest.raises(FormatError):
        FaceModel.load(tmp_path / "missing.json")


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _field(num: int, payload: bytes) -> bytes:
    return _varint(num << 3 | 2) + _varint(len(payload)) + payload


def test_parse_geometry_metadata_from_bytes_made_here():
    verts = [0.0, 1.0, 2.0, 0.25, 0.5, 3.0, 4.0, 5.0, 0.75, 1.0, 6.0, 7.0, 8.0, 0.0, 0.0]
    mesh = _field(3, struct.pack("<15f", *verts)) + _field(4, b"".join(_varint(i) for i in (0, 1, 2)))
    ref = _varint(1 << 3 | 0) + _varint(2) + _varint(2 << 3 | 5) + struct.pack("<f", 0.5)
    data = _field(1, mesh) + _field(2, ref)
    m = parse_geometry_metadata(data)
    np.testing.assert_allclose(m.vertices[1], [3, 4, 5])
    np.testing.assert_allclose(m.uvs[0], [0.25, 0.5])
    assert m.triangles.tolist() == [[0, 1, 2]]
    np.testing.assert_allclose(m.procrustes_weights, [0, 0, 0.5])


def test_parse_rejects_garbage():
    with pytest.raises(FormatError):
        parse_geometry_metadata(_field(1, _field(3, struct.pack("<4f", 1, 2, 3, 4))))


def test_shipped_task_file_is_the_expected_one():
    from tracking.landmarks import read_task_member, task_file, verify_task_file

    verify_task_file(task_file())
    mesh = parse_geometry_metadata(read_task_member("geometry_pipeline_metadata_landmarks.binarypb"))
    assert mesh.vertices.shape == (468, 3) and mesh.triangles.shape == (898, 3)


def test_copy_of_assets_loads_elsewhere(face_model, tmp_path):
    from nvp.face_model import ASSETS, DEFAULT_NAME

    for ext in (".json", ".npz"):
        shutil.copy(ASSETS / f"{DEFAULT_NAME}{ext}", tmp_path / f"x{ext}")
    (tmp_path / "x.json").write_text(
        (tmp_path / "x.json").read_text().replace(f'"{DEFAULT_NAME}.npz"', '"x.npz"')
    )
    assert FaceModel.load(tmp_path / "x.json").sha256 == face_model.sha256
