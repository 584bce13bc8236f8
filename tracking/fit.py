"""Fitting the face model to 2D landmarks: pure functions on tensors (batched Gauss-Newton).

Unknowns: one identity ``a (K_id)`` and focal length per video; per frame a rotation ``R_t``, translation
``t_t`` (cm) and expression ``d_t (K_exp)``. Energy (a MAP estimate with landmark noise ``sigma`` ×
interocular distance and standard-normal coefficient priors)::

    sum_t sum_i w_i |proj(R_t S_i(a, d_t) + t_t) - l_ti|^2 / s^2  +  mu_exp |d_t|^2  +  mu_id |a|^2
      + sum_t |Lambda^(1/2) (x_{t+1} (-) x_t)|^2            (temporal term, x = (rotation, t, d))

Rotations are updated on the left, ``R <- exp([dw]x) R``; the temporal rotation difference is
``log(R_{t+1} R_t^T)``. The temporal term couples neighbouring frames into a block-tridiagonal system that
is solved exactly (block Thomas algorithm), so smoothing acts only where the landmarks leave the
coefficients uncertain: a fast, clearly visible mouth opening is followed without lag, while noise in
poorly constrained directions is suppressed. Frames without data (no face, poor fit) are bridged by the
same system.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from nvp.geometry import project, skew


@dataclass(frozen=True)
class TrackingConfig:
    """Tracker fitting settings (all dimensionless unless stated)."""

    sigma: float = 0.01
    """Landmark noise as a fraction of the interocular distance (scales the data term)."""
    lip_weight: float = 2.0
    """Weight of lip landmarks relative to the others."""
    mu_exp: float = 1.0
    """Weight of the standard-normal prior on expression coefficients."""
    mu_id: float = 1.0
    """Weight of the standard-normal prior on identity coefficients (once per video)."""
    focal_candidates: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0)
    """Focal lengths tried, as multiples of max(width, height); the one with the lowest energy wins."""
    smooth_rot: float = 2.0e5
    """Temporal weight on frame-to-frame rotation change (per rad^2)."""
    smooth_trans: float = 200.0
    """Temporal weight on frame-to-frame translation change (per cm^2)."""
    smooth_exp: float = 20.0
    """Temporal weight on frame-to-frame expression change (per unit coefficient^2)."""
    iterations: int = 4
    """Per-frame Gauss-Newton iterations before the temporally coupled ones."""
    coupled_iterations: int = 2
    """Gauss-Newton iterations with the temporal term (whole sequence)."""
    keyframes: int = 40
    """Frames used to estimate identity and focal length."""
    identity_rounds: int = 2
    """Alternations between per-frame fits and identity/focal updates on the keyframes."""
    lip_flow: float = 0.8
    """How much of each frame's outer lip landmarks is predicted from its neighbours' moved by the optical
    flow between the frames rather than taken from its own detection (:func:`tracking.lipflow.fuse`; 0: the
    detections alone). Chosen on dfrf__cnn2 / edtalk__pose_source2 (held-out frames re-created by renderers
    trained on the plain tracking, mouth box, pooled PSNR; flow over the whole frame, all lip landmarks):
    0.6 / 0.8 / 0.9 gave +0.18 / +0.29 / +0.29 and +0.21 / +0.37 / +0.41 dB; the detections smoothed in time
    instead (Gaussian σ 1 / 2 frames) −0.18 / −0.46 dB on edtalk. As built (outer contour,
    :func:`tracking.lipflow.lip_landmarks`; ``scripts/eval/lower_face_limits.py``): dfrf__cnn2 29.04 → 29.18,
    edtalk 28.91 → 29.16, wav2lipgfpgan kim 28.76 → 29.09; the test people minimates 27.56 → 27.67, multivsr
    22.68 → 22.77, voxceleb2_id00100 29.27 → 29.37 dB."""
    max_error: float = 0.06
    """A frame whose RMS reprojection error exceeds this fraction of the interocular distance is invalid."""
    chunk: int = 256
    """Frames per batch in the per-frame solver (bounds memory)."""


@dataclass
class FrameParams:
    """Per-frame unknowns: rotation ``(T,3,3)``, translation ``(T,3)`` cm, expression ``(T,K_exp)``."""

    rotation: torch.Tensor
    translation: torch.Tensor
    expression: torch.Tensor

    def take(self, idx) -> FrameParams:
        return FrameParams(self.rotation[idx], self.translation[idx], self.expression[idx])

    def put(self, idx, other: FrameParams) -> None:
        self.rotation[idx] = other.rotation
        self.translation[idx] = other.translation
        self.expression[idx] = other.expression


@dataclass(frozen=True)
class ModelTensors:
    """Face model restricted to the fitted landmarks: shape ``(N,3)``, bases ``(K,N,3)``."""

    identity_shape: torch.Tensor
    exp_basis: torch.Tensor
    template: torch.Tensor
    id_basis: torch.Tensor

    def shape(self, expression: torch.Tensor) -> torch.Tensor:
        """Object-space landmark positions ``(T,N,3)`` for expressions ``(T,K_exp)``."""
        return self.identity_shape + torch.einsum("tk,knc->tnc", expression, self.exp_basis)

    def with_identity(self, identity: torch.Tensor) -> ModelTensors:
        shape = self.template + torch.einsum("k,knc->nc", identity, self.id_basis)
        return ModelTensors(shape, self.exp_basis, self.template, self.id_basis)


def init_pose(
    points3d: np.ndarray, template: np.ndarray, focal: float, center: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Initial rotations ``(T,3,3)`` and translations ``(T,3)`` from detector 3D landmarks.

    A similarity transform maps the template (cm) onto the landmarks (x, y, z in pixels); its scale gives
    the depth ``focal / scale`` and its translation the position of the object origin in the image.
    """
    from nvp.geometry import similarity_procrustes

    s, r, t = similarity_procrustes(template[None].astype(np.float64), points3d.astype(np.float64))
    depth = focal / s
    trans = np.stack([(t[:, 0] - center[0]) * depth / focal, (t[:, 1] - center[1]) * depth / focal, depth], 1)
    return r.astype(np.float32), trans.astype(np.float32)


def residuals(
    model: ModelTensors, p: FrameParams, focal: torch.Tensor, center: torch.Tensor, obs: torch.Tensor
) -> torch.Tensor:
    """Reprojection residuals ``(T,N,2)`` in pixels."""
    cam = torch.einsum("tij,tnj->tni", p.rotation, model.shape(p.expression)) + p.translation[:, None]
    return project(cam, focal, center) - obs


def frame_system(
    model: ModelTensors,
    p: FrameParams,
    focal: torch.Tensor,
    center: torch.Tensor,
    obs: torch.Tensor,
    weight: torch.Tensor,
    scale: float,
    mu_exp: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gauss-Newton normal equations of each frame's data + prior terms.

    Args:
        obs: ``(T,N,2)`` landmarks in pixels. weight: ``(T,N)`` per-landmark weights (0 = ignore).
        scale: pixels per unit residual (sigma × interocular distance).

    Returns:
        ``H (T,P,P)``, ``g (T,P)``, ``cost (T,)`` with ``P = 6 + K_exp`` ordered (rotation, translation,
        expression); the Gauss-Newton step solves ``H dx = -g``.
    """
    shape = model.shape(p.expression)
    rs = torch.einsum("tij,tnj->tni", p.rotation, shape)
    cam = rs + p.translation[:, None]
    x, y, z = cam.unbind(-1)
    z = z.clamp_min(1e-3)
    uv = torch.stack([x / z, y / z], -1) * focal + center
    sw = weight.sqrt()[..., None] / scale
    r = (uv - obs) * sw  # (T,N,2)
    fz = focal / z
    zero = torch.zeros_like(z)
    dproj = (
        torch.stack([torch.stack([fz, zero, -fz * x / z], -1), torch.stack([zero, fz, -fz * y / z], -1)], -2)
        * sw[..., None]
    )  # (T,N,2,3)
    t_, n_ = r.shape[:2]
    jrot = dproj @ -skew(rs)  # (T,N,2,3)
    jexp = torch.einsum("tnac,knc->tnak", dproj @ p.rotation[:, None], model.exp_basis)  # (T,N,2,K)
    jac = torch.cat([jrot, dproj, jexp], -1).reshape(t_, n_ * 2, -1)  # (T,2N,P)
    rr = r.reshape(t_, -1)
    h = jac.transpose(1, 2) @ jac
    g = (jac.transpose(1, 2) @ rr[..., None])[..., 0]
    k = p.expression.shape[1]
    h[:, 6:, 6:] += mu_exp * torch.eye(k, dtype=h.dtype)
    g[:, 6:] += mu_exp * p.expression
    cost = (rr**2).sum(-1) + mu_exp * (p.expression**2).sum(-1)
    return h, g, cost


def apply_step(p: FrameParams, step: torch.Tensor) -> FrameParams:
    """New parameters after a step ``(T,P)`` (left-multiplied rotation update)."""
    rot = axis_angle_to_rotation_matrix(step[:, :3]) @ p.rotation
    return FrameParams(rot, p.translation + step[:, 3:6], p.expression + step[:, 6:])


def solve_frames(
    model: ModelTensors,
    p: FrameParams,
    focal: torch.Tensor,
    center: torch.Tensor,
    obs: torch.Tensor,
    weight: torch.Tensor,
    scale: float,
    cfg: TrackingConfig,
    iterations: int,
) -> FrameParams:
    """Independent Levenberg-Marquardt fits of every frame (batched, chunked); returns new parameters."""
    out = FrameParams(p.rotation.clone(), p.translation.clone(), p.expression.clone())
    for s in range(0, p.rotation.shape[0], cfg.chunk):
        idx = slice(s, s + cfg.chunk)
        cur = out.take(idx)
        o, w = obs[idx], weight[idx]
        damping = torch.full((cur.rotation.shape[0],), 1e-3, dtype=obs.dtype)
        for _ in range(iterations):
            h, g, cost = frame_system(model, cur, focal, center, o, w, scale, cfg.mu_exp)
            diag = torch.diagonal(h, dim1=1, dim2=2)
            a = h + torch.diag_embed(damping[:, None] * diag + 1e-6)
            step = -torch.linalg.solve(a.double(), g.double()[..., None])[..., 0].to(obs.dtype)
            cand = apply_step(cur, step)
            r = residuals(model, cand, focal, center, o) * (w.sqrt()[..., None] / scale)
            new_cost = (r**2).sum((1, 2)) + cfg.mu_exp * (cand.expression**2).sum(-1)
            better = new_cost <= cost
            cur = FrameParams(
                torch.where(better[:, None, None], cand.rotation, cur.rotation),
                torch.where(better[:, None], cand.translation, cur.translation),
                torch.where(better[:, None], cand.expression, cur.expression),
            )
            damping = torch.where(better, damping * 0.3, damping * 10).clamp(1e-7, 1e4)
        out.put(idx, cur)
    return out


def temporal_differences(p: FrameParams) -> torch.Tensor:
    """``(T-1, P)`` differences ``x_{t+1} (-) x_t``: rotation as ``log(R_{t+1} R_t^T)``."""
    rel = p.rotation[1:] @ p.rotation[:-1].transpose(1, 2)
    return torch.cat(
        [
            rotation_matrix_to_axis_angle(rel),
            p.translation[1:] - p.translation[:-1],
            p.expression[1:] - p.expression[:-1],
        ],
        1,
    )


def solve_block_tridiagonal(diag: np.ndarray, off: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``A_t x_t + B x_{t-1} + B x_{t+1} = rhs_t`` (block Thomas algorithm).

    Args:
        diag: ``(T,P,P)`` diagonal blocks ``A_t``. off: ``(P,)`` the diagonal of the symmetric off-diagonal
            block ``B`` (the same for every pair of neighbours). rhs: ``(T,P)``.

    Returns:
        ``(T,P)`` solution.
    """
    t_ = diag.shape[0]
    c = np.zeros_like(diag)
    d = np.zeros_like(rhs)
    m = diag[0]
    c[0] = np.linalg.solve(m, np.diag(off))
    d[0] = np.linalg.solve(m, rhs[0])
    for t in range(1, t_):
        m = diag[t] - off[:, None] * c[t - 1]
        c[t] = np.linalg.solve(m, np.diag(off))
        d[t] = np.linalg.solve(m, rhs[t] - off * d[t - 1])
    x = np.zeros_like(rhs)
    x[-1] = d[-1]
    for t in range(t_ - 2, -1, -1):
        x[t] = d[t] - c[t] @ x[t + 1]
    return x


def solve_sequence(
    model: ModelTensors,
    p: FrameParams,
    focal: torch.Tensor,
    center: torch.Tensor,
    obs: torch.Tensor,
    weight: torch.Tensor,
    scale: float,
    cfg: TrackingConfig,
    active: torch.Tensor,
) -> FrameParams:
    """One Gauss-Newton step of the whole sequence with the temporal term.

    Frames where ``active`` is False contribute no data (and no prior): their values follow from their
    neighbours, which bridges gaps smoothly.
    """
    t_, k = p.expression.shape
    h = torch.zeros(t_, 6 + k, 6 + k, dtype=torch.float64)
    g = torch.zeros(t_, 6 + k, dtype=torch.float64)
    for s in range(0, t_, cfg.chunk):
        idx = slice(s, s + cfg.chunk)
        hh, gg, _ = frame_system(model, p.take(idx), focal, center, obs[idx], weight[idx], scale, cfg.mu_exp)
        h[idx], g[idx] = hh.double(), gg.double()
    h[~active] = 0.0
    g[~active] = 0.0
    lam = torch.tensor(
        [cfg.smooth_rot] * 3 + [cfg.smooth_trans] * 3 + [cfg.smooth_exp] * k, dtype=torch.float64
    )
    if t_ > 1:
        diff = temporal_differences(p).double() * lam  # Lambda * d_t
        g[1:] += diff
        g[:-1] -= diff
        count = torch.full((t_,), 2.0, dtype=torch.float64)
        count[0] = count[-1] = 1.0
    else:
        count = torch.zeros(1, dtype=torch.float64)
    h.diagonal(dim1=1, dim2=2).add_(count[:, None] * lam + 1e-9)  # in place: bounded memory on long videos
    step = solve_block_tridiagonal(h.numpy(), -lam.numpy(), -g.numpy())
    return apply_step(p, torch.from_numpy(step).to(obs.dtype))


def fit_identity(
    model: ModelTensors,
    p: FrameParams,
    identity: torch.Tensor,
    focal: torch.Tensor,
    center: torch.Tensor,
    obs: torch.Tensor,
    weight: torch.Tensor,
    scale: float,
    cfg: TrackingConfig,
) -> torch.Tensor:
    """Identity coefficients minimising the keyframes' energy with their pose and expression fixed.

    The landmarks are linear in the identity up to the perspective division, so one damped Gauss-Newton
    step from the current value is a near-exact solve.
    """
    shape = model.shape(p.expression)
    cam = torch.einsum("tij,tnj->tni", p.rotation, shape) + p.translation[:, None]
    x, y, z = cam.unbind(-1)
    z = z.clamp_min(1e-3)
    uv = torch.stack([x / z, y / z], -1) * focal + center
    sw = weight.sqrt()[..., None] / scale
    r = ((uv - obs) * sw).reshape(-1)
    fz = focal / z
    zero = torch.zeros_like(z)
    dproj = (
        torch.stack([torch.stack([fz, zero, -fz * x / z], -1), torch.stack([zero, fz, -fz * y / z], -1)], -2)
        * sw[..., None]
    )
    jac = (dproj @ torch.einsum("tij,knj->tnik", p.rotation, model.id_basis)).reshape(r.shape[0], -1).double()
    h = jac.T @ jac
    g = jac.T @ r.double() + cfg.mu_id * identity.double()
    h += torch.diag(cfg.mu_id + 1e-3 * torch.diagonal(h))
    return identity - torch.linalg.solve(h, g).to(obs.dtype)


def energy(
    model: ModelTensors,
    p: FrameParams,
    identity: torch.Tensor,
    focal: torch.Tensor,
    center: torch.Tensor,
    obs: torch.Tensor,
    weight: torch.Tensor,
    scale: float,
    cfg: TrackingConfig,
) -> float:
    """Total data + prior energy of a set of frames (no temporal term)."""
    r = residuals(model, p, focal, center, obs) * (weight.sqrt()[..., None] / scale)
    return float((r**2).sum() + cfg.mu_exp * (p.expression**2).sum() + cfg.mu_id * (identity**2).sum())
