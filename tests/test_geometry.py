"""Pure geometry functions."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from nvp.geometry import project, similarity_procrustes, skew


def test_procrustes_recovers_a_known_similarity_batched():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    rots = Rotation.random(4, random_state=1).as_matrix()
    scales = np.array([0.5, 1.0, 2.0, 3.0])
    trans = rng.normal(size=(4, 3))
    dst = scales[:, None, None] * np.einsum("bij,nj->bni", rots, src) + trans[:, None]
    s, r, t = similarity_procrustes(np.broadcast_to(src, (4, 50, 3)), dst)
    np.testing.assert_allclose(s, scales, rtol=1e-9)
    np.testing.assert_allclose(r, rots, atol=1e-9)
    np.testing.assert_allclose(t, trans, atol=1e-9)


def test_procrustes_weights_ignore_outliers():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    dst = src.copy()
    dst[0] += 100.0
    w = np.ones(20)
    w[0] = 0
    s, r, t = similarity_procrustes(src, dst, w)
    np.testing.assert_allclose(r, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(s, 1.0, atol=1e-9)


def test_project_follows_opencv_convention():
    pts = torch.tensor([[0.0, 0.0, 10.0], [1.0, 2.0, 10.0]])
    uv = project(pts, torch.tensor(100.0), torch.tensor([64.0, 48.0]))
    torch.testing.assert_close(uv, torch.tensor([[64.0, 48.0], [74.0, 68.0]]))  # x right, y down


def test_skew_is_the_cross_product():
    a, b = torch.randn(5, 3), torch.randn(5, 3)
    torch.testing.assert_close((skew(a) @ b[..., None])[..., 0], torch.linalg.cross(a, b))


def test_unposed_undoes_the_pose():
    from nvp.geometry import posed, unposed

    rng = np.random.default_rng(2)
    x = rng.normal(size=(5, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r, t = q * np.sign(np.linalg.det(q)), np.array([1.0, 2.0, 50.0])  # a proper rotation
    np.testing.assert_allclose(unposed(posed(x, r, t), r, t), x, atol=1e-9)
