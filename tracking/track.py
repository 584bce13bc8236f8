"""Tracking orchestration: detections → fitted ``TrackedSequence``."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from nvp.errors import NoFaceError
from nvp.face_model import FaceModel, default_face_model
from nvp.gaze import SPREAD_KEY, eye_spread, iris_circles
from nvp.geometry import pinhole, posed
from nvp.metrics import interocular_distance
from nvp.tracked import TrackedSequence
from tracking.detect import Detections, detect_video
from tracking.fit import (
    FrameParams,
    ModelTensors,
    TrackingConfig,
    energy,
    fit_identity,
    init_pose,
    solve_frames,
    solve_sequence,
)
from tracking.lipflow import fuse, lip_landmarks

log = logging.getLogger(__name__)


def landmark_weights(model: FaceModel, lip_weight: float) -> np.ndarray:
    """``(L,)`` per-landmark weights: lips count ``lip_weight`` times, the rest once."""
    w = np.ones(len(model.landmark_vertices), np.float32)
    w[model.vertex_regions["lips"][model.landmark_vertices]] = lip_weight
    return w


def _nearest_fill(values: np.ndarray, have: np.ndarray) -> np.ndarray:
    """Copy each missing frame's value from the nearest frame that has one (initialisation only)."""
    idx = np.flatnonzero(have)
    pos = np.searchsorted(idx, np.arange(len(have))).clip(0, len(idx) - 1)
    prev = idx[(pos - 1).clip(0)]
    nxt = idx[pos]
    t = np.arange(len(have))
    take = np.where(np.abs(t - prev) < np.abs(nxt - t), prev, nxt)
    return values[take]


def fit_detections(
    det: Detections, model: FaceModel | None = None, cfg: TrackingConfig | None = None
) -> TrackedSequence:
    """Fit the face model to a video's detections (see ``tracking.fit`` for the energy)."""
    model = model or default_face_model()
    cfg = cfg or TrackingConfig()
    t0 = time.perf_counter()
    torch.manual_seed(0)
    found = det.found.copy()
    if not found.any():
        raise NoFaceError("no face was detected in any frame")
    lmv = model.landmark_vertices
    g = model.landmark_groups
    pts = det.points[:, : len(lmv)]
    if det.lip_flow is not None and cfg.lip_flow > 0:  # the lips steadied by the image's motion
        pts = pts.copy()
        lips = det.lip_points
        pts[:, lips, :2] = fuse(det.points[:, lips, :2], det.lip_flow[:, 0], det.lip_flow[:, 1], cfg.lip_flow)
    iod = interocular_distance(pts[found, :, :2], g["left_eye"], g["right_eye"])
    iod_px = float(np.median(iod))
    scale = cfg.sigma * iod_px
    obs_np = np.nan_to_num(pts[..., :2]).astype(np.float32)
    w_np = np.where(found[:, None], landmark_weights(model, cfg.lip_weight)[None], 0.0).astype(np.float32)
    obs, weight = torch.from_numpy(obs_np), torch.from_numpy(w_np)
    center_np = np.array([det.width / 2.0, det.height / 2.0], np.float32)
    center = torch.from_numpy(center_np)
    base = ModelTensors(
        identity_shape=torch.from_numpy(model.template[lmv]),
        exp_basis=torch.from_numpy(model.exp_basis[:, lmv]),
        template=torch.from_numpy(model.template[lmv]),
        id_basis=torch.from_numpy(model.id_basis[:, lmv]),
    )

    def initial(frames: np.ndarray, mt: ModelTensors, focal: torch.Tensor) -> FrameParams:
        r, t = init_pose(pts[frames], mt.identity_shape.numpy(), float(focal), center_np)
        return FrameParams(torch.from_numpy(r), torch.from_numpy(t), torch.zeros(len(frames), model.num_exp))

    # identity and focal length on keyframes: the landmarks barely constrain perspective, so each focal
    # length candidate gets its own identity fit and the lowest total energy (with priors) decides
    found_idx = np.flatnonzero(found)
    keys = found_idx[
        np.linspace(0, len(found_idx) - 1, min(cfg.keyframes, len(found_idx))).round().astype(int)
    ]
    keys = np.unique(keys)
    best = None
    for mult in cfg.focal_candidates:
        focal = torch.tensor(mult * max(det.width, det.height), dtype=torch.float32)
        ident = torch.zeros(model.num_id, dtype=torch.float32)
        mt = base.with_identity(ident)
        kp = initial(keys, mt, focal)
        for _ in range(cfg.identity_rounds):
            kp = solve_frames(mt, kp, focal, center, obs[keys], weight[keys], scale, cfg, cfg.iterations)
            ident = fit_identity(base, kp, ident, focal, center, obs[keys], weight[keys], scale, cfg)
            mt = base.with_identity(ident)
        kp = solve_frames(mt, kp, focal, center, obs[keys], weight[keys], scale, cfg, cfg.iterations)
        e = energy(mt, kp, ident, focal, center, obs[keys], weight[keys], scale, cfg)
        log.debug("focal %.0f px: energy %.1f", float(focal), e)
        if best is None or e < best[0]:
            best = (e, focal, ident, mt)
    _, focal, identity, mt = best
    t_id = time.perf_counter()

    # every frame independently, then the temporally coupled refinement
    fp = initial(found_idx, mt, focal)
    fp = solve_frames(mt, fp, focal, center, obs[found_idx], weight[found_idx], scale, cfg, cfg.iterations)
    rot = _nearest_fill(_scatter(fp.rotation.numpy(), found_idx, len(found)), found)
    trans = _nearest_fill(_scatter(fp.translation.numpy(), found_idx, len(found)), found)
    expr = _nearest_fill(_scatter(fp.expression.numpy(), found_idx, len(found)), found)
    p = FrameParams(torch.from_numpy(rot), torch.from_numpy(trans), torch.from_numpy(expr))
    err = _rms_error(model, identity.numpy(), p, float(focal), center_np, pts[..., :2])
    valid = found & (err <= cfg.max_error * iod_px)
    active = torch.from_numpy(valid)
    weight = weight * active[:, None]
    for _ in range(cfg.coupled_iterations):
        p = solve_sequence(mt, p, focal, center, obs, weight, scale, cfg, active)
    err = _rms_error(model, identity.numpy(), p, float(focal), center_np, pts[..., :2])
    elapsed = time.perf_counter() - t0
    log.info(
        "fit %d frames (%d valid) in %.1f s (identity %.1f s); focal %.0f px; median error %.2f px",
        len(found),
        valid.sum(),
        elapsed,
        t_id - t0,
        float(focal),
        np.nanmedian(err),
    )
    seq = TrackedSequence(
        fps=det.fps,
        width=det.width,
        height=det.height,
        focal=float(focal),
        center=center_np,
        identity=identity.numpy().astype(np.float32),
        rotation=p.rotation.numpy().astype(np.float32),
        translation=p.translation.numpy().astype(np.float32),
        expression=p.expression.numpy().astype(np.float32),
        landmarks=np.where(found[:, None, None], pts[..., :2], np.nan).astype(np.float32),
        valid=valid,
        fit_error=err.astype(np.float32),
        face_model_sha256=model.sha256,
        info={"fit_config": asdict(cfg), "interocular_px": iod_px, "fit_seconds": round(elapsed, 2)},
        iris=iris_circles(np.where(found[:, None, None], det.points, np.nan)),
    )
    # where this person's eyeballs sit sideways: the two eyes look the same way (nvp.gaze.eye_spread)
    return dataclasses.replace(seq, info={**seq.info, SPREAD_KEY: eye_spread(model, seq)})


def _scatter(values: np.ndarray, idx: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n, *values.shape[1:]), values.dtype)
    out[idx] = values
    return out


def _rms_error(
    model: FaceModel, identity: np.ndarray, p: FrameParams, focal: float, center: np.ndarray, obs: np.ndarray
) -> np.ndarray:
    """``(T,)`` RMS pixel distance between projected landmark vertices and detections (NaN if missing)."""
    verts = model.vertices(identity, p.expression.numpy())[:, model.landmark_vertices]
    uv = pinhole(posed(verts, p.rotation.numpy(), p.translation.numpy()), focal, center)
    return np.sqrt(((uv - obs) ** 2).sum(-1).mean(-1))


def track_video(
    path: str | Path,
    *,
    cfg: TrackingConfig | None = None,
    model: FaceModel | None = None,
    progress: bool = True,
    max_frames: int | None = None,
    saves: Path | None = None,
) -> tuple[TrackedSequence, Detections]:
    """Detect and fit a whole video. Returns the tracked sequence and the raw detections.

    ``saves``: a folder where the detection saves its progress as it goes and finds an interrupted run's
    (:func:`tracking.detect.detect_video`; :func:`saved_frames` says how far it got)."""
    t0 = time.perf_counter()
    model = model or default_face_model()
    det = detect_video(path, progress=progress, max_frames=max_frames, lips=lip_landmarks(model), saves=saves)
    t_det = time.perf_counter() - t0
    seq = fit_detections(det, model, cfg)
    total = time.perf_counter() - t0
    info = dict(seq.info, source=str(path), detect_seconds=round(t_det, 2), total_seconds=round(total, 2))
    return dataclasses.replace(seq, info=info), det


def saved_frames(path: str | Path, saves: Path, model: FaceModel | None = None) -> tuple[int, int]:
    """How far an interrupted :func:`track_video` of ``path`` with ``saves`` got: the frames whose landmarks
    are saved (for this video, these settings and this nvp) and the video's frames."""
    from nvp.media import probe_video
    from tracking.detect import detections_key, saved_segments

    n = probe_video(path).num_frames
    if not Path(saves).is_dir():
        return 0, n
    lips = lip_landmarks(model or default_face_model())
    done = saved_segments(Path(saves), detections_key(path, 1, None, lips), n)
    return sum(len(d["found"]) for d in done), n
