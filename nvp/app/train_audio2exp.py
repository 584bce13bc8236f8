"""Training and evaluation of the generic Audio2ExpressionNet with per-video person maps.

Training (Thies et al. 2020, Sec. 3.1): every training video gets its own person map ``(K_exp × A)`` (plus
a bias), trained jointly with the generic network; the loss is in vertex space (mouth 10×) with the
temporal term (λ = 20); Adam, lr 1e-4. Each batch item is three consecutive frames of one video, each
filtered over its 8 surrounding per-frame predictions.

Evaluation protocol for a person the network has never seen: solve the person map in closed form on the
first part of their video, predict the rest from audio alone, compare with tracking.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from nvp.artifact import atomic_path
from nvp.audio2exp import (
    Audio2ExpConfig,
    Audio2ExpressionNet,
    VertexMetric,
    audio_expressions,
    save_net,
    solve_person_map,
)
from nvp.errors import NvpError
from nvp.face_model import FaceModel
from nvp.geometry import posed
from nvp.metrics import closed_level, closure_f1, interocular_distance
from nvp.person import VideoSample, rest_expression

log = logging.getLogger(__name__)
FORMAT_VERSION = 1


@dataclass(frozen=True)
class Audio2ExpTrainConfig:
    """Corpus training settings."""

    kind: str = "phonemes"
    """Speech features: 'phonemes' (hama posteriors) or 'mel'."""
    steps: int = 4000
    """Optimisation steps."""
    batch: int = 64
    """Items per step (each item: three consecutive frames of one video)."""
    lr: float = 1e-4
    """Adam learning rate (the paper's value)."""
    map_lr: float = 1e-3
    """Adam learning rate of the per-video person maps."""
    weight_decay: float = 1e-4
    """Adam weight decay on the generic network."""
    feature_noise: float = 0.3
    """Gaussian noise added to the input features during training, in units of each channel's std."""
    mouth_weight: float = 10.0
    """Weight of mouth-region vertices in the vertex-space loss."""
    temporal_weight: float = 20.0
    """λ of the temporal (forward/backward/central difference) term."""
    ridge: float = 10.0
    """Ridge regularisation of closed-form person maps."""
    train_fraction: float = 0.8
    """Part of each validation video used to solve its person map; the rest is predicted."""
    val_every: int = 250
    """Steps between validations (and checkpoints)."""
    seed: int = 0
    """Random seed (weights, batches)."""
    augments: tuple[str, ...] = ()
    """Copies of the training videos' audio (:mod:`nvp.augment` names, ``VideoSample.augmented``, made by the
    corpus loader); each batch item reads the clean or one of the copies' feature windows with equal
    probability, so each copy's speech is mapped to the same mouth."""
    closure_weight: float = 1.0
    """Weight of the closure head's loss (binary cross-entropy: is the tracked inner-lip gap at or below
    the video's closed level, ``nvp.metrics.closed_level``); 0 trains no closure head."""
    net: Audio2ExpConfig = field(default_factory=lambda: Audio2ExpConfig(dropout=0.3))
    """Network sizes."""


def _filter_indices(t: np.ndarray, num_frames: int, f: int) -> np.ndarray:
    """Per-frame window indices ``(B, 2 + F)`` needed to filter frames t-1, t, t+1 (edge-clamped)."""
    offs = np.arange(-1 - f // 2, 1 + f - f // 2)
    return np.clip(t[:, None] + offs[None], 0, num_frames - 1)


def _predict_triplets(
    net: Audio2ExpressionNet, windows: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Audio-expressions ``(B, 3, A)`` of frames t-1, t, t+1 from their windows ``(B, 2 + F, W, D)``, and
    the closure logits ``(B, 3)`` of those frames (None without the closure head)."""
    b, n = windows.shape[:2]
    f = net.cfg.filter_window
    raw, closure = net.frame_outputs(windows.flatten(0, 1))
    raw = raw.view(b, n, -1)
    outs = [net.filter(raw[:, k : k + f])[0] for k in range(3)]
    if closure is not None:
        centre = f // 2  # window index of frame t-1 (see _filter_indices)
        closure = closure.view(b, n)[:, centre : centre + 3]
    return torch.stack(outs, 1), closure


def evaluate_person(
    sample: VideoSample,
    model: FaceModel,
    audio_exp: np.ndarray | None,
    train_fraction: float = 0.8,
    ridge: float = 10.0,
    voice: np.ndarray | None = None,
) -> dict[str, float]:
    """Person-specific evaluation on the held-out tail of one video.

    The person map is solved on the first ``train_fraction`` of the frames; the tail is predicted. With
    ``audio_exp=None`` the prediction is the person's mean expression (baseline). With ``voice`` ``(T,)``
    (see :func:`nvp.vad.voice_activity`) unvoiced frames blend towards the person's rest
    expression, as ``nvp.person.predict_expressions`` does.

    Returns mouth landmark error (projected lip vertices of predicted vs tracked mesh under the tracked
    pose, / interocular distance), lip vertex error (mm, object space), the correlation of predicted and
    tracked mouth opening (inner-lip gap; 0 for a constant prediction) and lip-closure precision/recall/F1
    (closed: inner-lip gap below the person's closed level, ``min + 0.15 (p95 - min)`` of the tracked gap
    on the training part).
    """
    seq = sample.tracked
    t_split = int(round(seq.num_frames * train_fraction))
    tr = np.flatnonzero(seq.valid[:t_split])
    te = t_split + np.flatnonzero(seq.valid[t_split:])
    if len(tr) < MIN_TRAIN_FRAMES or len(te) < MIN_TEST_FRAMES:
        raise ValueError(f"{sample.name}: too few valid frames to evaluate ({len(tr)} train, {len(te)} test)")
    gap_true_all = model.inner_lip_gap(seq.identity, seq.expression)
    if audio_exp is None:
        pred = np.broadcast_to(seq.expression[tr].mean(0), (len(te), model.num_exp))
    else:
        pmap = solve_person_map(audio_exp[tr], seq.expression[tr], ridge)
        pred = pmap.apply(audio_exp[te])
        if voice is not None:
            rest = rest_expression(seq.expression[tr], gap_true_all[tr])
            pred = rest + voice[te, None] * (pred - rest)
    lips = np.flatnonzero(model.vertex_regions["lips"])
    v_pred = model.vertices(seq.identity, pred)
    v_true = model.vertices(seq.identity, seq.expression[te])
    lip_mm = 10 * np.linalg.norm(v_pred[:, lips] - v_true[:, lips], axis=-1).mean()

    def px(v):
        return seq.pixels(posed(v, seq.rotation[te], seq.translation[te]))

    g = model.landmark_groups
    iod = interocular_distance(seq.landmarks[te], g["left_eye"], g["right_eye"])
    iod = np.where(np.isfinite(iod), iod, np.nanmedian(iod))
    mouth = (np.linalg.norm(px(v_pred[:, lips]) - px(v_true[:, lips]), axis=-1).mean(-1) / iod).mean()
    lo, hi = gap_true_all[tr].min(), np.percentile(gap_true_all[tr], 95)
    thr = lo + 0.15 * (hi - lo)
    gap_pred = model.inner_lip_gap(seq.identity, pred)
    gap_true = gap_true_all[te]
    out = {"mouth_error_iod": float(mouth), "lip_vertex_error_mm": float(lip_mm)}
    varies = audio_exp is not None and gap_pred.std() > 1e-6 and gap_true.std() > 1e-6
    out["opening_corr"] = float(np.corrcoef(gap_pred, gap_true)[0, 1]) if varies else 0.0
    out.update(closure_f1(gap_pred, gap_true, thr))
    out["test_frames"] = int(len(te))
    return out


def closed_frames(sample: VideoSample, model: FaceModel) -> np.ndarray:
    """``(T,)`` float32 closure labels of a training video: 1 where the tracked inner-lip gap is at or
    below the video's closed level (:func:`nvp.metrics.closed_level` of its valid frames)."""
    gap = model.inner_lip_gap(sample.tracked.identity, sample.expression)
    return (gap <= closed_level(gap[sample.valid])).astype(np.float32)


def _closure_pos_weight(closed: list[torch.Tensor], weight: float) -> torch.Tensor | None:
    """BCE weight of closed frames: open / closed frame count over the corpus (both classes count
    equally), None when no closure head is trained."""
    if weight <= 0:
        return None
    shut = float(sum(c.sum() for c in closed))
    total = float(sum(len(c) for c in closed))
    return torch.tensor((total - shut) / max(shut, 1.0))


def _summary(rows: list[dict[str, float]]) -> dict[str, float]:
    keys = ("mouth_error_iod", "lip_vertex_error_mm", "closure_f1", "opening_corr")
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}


MIN_TRAIN_FRAMES, MIN_TEST_FRAMES = 10, 5
"""Valid frames a validation video needs in its person-map part and in its held-out tail."""


def usable_sets(
    train_set: list[VideoSample], val_set: list[VideoSample], train_fraction: float
) -> tuple[list[VideoSample], list[VideoSample]]:
    """The training videos and the validation videos long enough for :func:`evaluate_person` (the others
    are dropped with a warning), checked before any training; :class:`NvpError` when either set is empty."""
    ok = []
    for s in val_set:
        t_split = int(round(s.tracked.num_frames * train_fraction))
        n_train, n_test = int(s.valid[:t_split].sum()), int(s.valid[t_split:].sum())
        if n_train < MIN_TRAIN_FRAMES or n_test < MIN_TEST_FRAMES:
            log.warning(
                "validation video %s is too short (%d + %d valid frames; needs %d + %d): left out",
                s.name,
                n_train,
                n_test,
                MIN_TRAIN_FRAMES,
                MIN_TEST_FRAMES,
            )
        else:
            ok.append(s)
    if not train_set:
        raise NvpError("no training video could be used (all were skipped or chosen for validation)")
    if not ok:
        raise NvpError(
            "no validation video could be used (all were skipped or too short); name others with --val"
        )
    return train_set, ok


class _Trainable(torch.nn.Module):
    """The generic network and the training videos' person maps, as one module (for
    DistributedDataParallel): feature windows of frame triplets and video ids in, expressions and closure
    logits out."""

    def __init__(self, net: Audio2ExpressionNet, maps: torch.Tensor, bias: torch.Tensor) -> None:
        super().__init__()
        self.net = net
        self.maps, self.bias = torch.nn.Parameter(maps), torch.nn.Parameter(bias)

    def forward(self, windows: torch.Tensor, vids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        ae, closure_logits = _predict_triplets(self.net, windows)  # (B, 3, A), (B, 3)
        pred = torch.einsum("bka,bta->btk", self.maps[vids], ae) + self.bias[vids][:, None]
        return pred, closure_logits


def train(
    train_set: list[VideoSample],
    val_set: list[VideoSample],
    model: FaceModel,
    cfg: Audio2ExpTrainConfig,
    out_dir: Path,
    progress: bool = True,
    provenance: dict | None = None,
) -> dict:
    """Train the generic network and the training videos' person maps; resumable from ``out_dir``.

    Writes ``checkpoint.pt`` every ``val_every`` steps (network, maps, optimiser, step, RNG state) and
    ``best.{npz,json}`` whenever the mean validation mouth error improves; its manifest holds the config,
    the step, the validation metrics and ``provenance`` (e.g. which videos). Returns the training log.

    Under ``torchrun`` (:mod:`nvp.app.distributed`) every process takes its share of each batch and
    DistributedDataParallel averages the gradients; the main process validates and writes the files.
    """
    from nvp.app.distributed import process_group

    group = process_group()
    train_set, val_set = usable_sets(train_set, val_set, cfg.train_fraction)
    share = group.share(cfg.batch)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    net_cfg = replace(
        cfg.net, feature_dim=int(train_set[0].windows.shape[2]), closure_head=cfg.closure_weight > 0
    )
    net = Audio2ExpressionNet(net_cfg)
    # frame-centre feature rows of every training video (each window's middle row covers the audio once)
    centre = net_cfg.window // 2
    net.per_frame.set_input_stats(torch.from_numpy(np.concatenate([s.windows[:, centre] for s in train_set])))
    k, a = model.num_exp, net_cfg.audio_exp_dim
    maps = torch.zeros(len(train_set), k, a)
    torch.nn.init.normal_(maps, std=0.1)
    bias = torch.from_numpy(np.stack([s.expression[s.valid].mean(0) for s in train_set]))
    trainable = _Trainable(net, maps, bias)
    maps, bias = trainable.maps, trainable.bias
    opt = torch.optim.Adam(
        [
            {"params": net.parameters(), "lr": cfg.lr, "weight_decay": cfg.weight_decay},
            {"params": [maps, bias], "lr": cfg.map_lr},
        ]
    )
    metric = VertexMetric(model.exp_basis, model.vertex_regions["mouth"], cfg.mouth_weight)
    windows = [[torch.from_numpy(w) for w in (s.windows, *s.augmented)] for s in train_set]
    targets = [torch.from_numpy(s.expression) for s in train_set]
    closed = [torch.from_numpy(closed_frames(s, model)) for s in train_set]
    pos_weight = _closure_pos_weight(closed, cfg.closure_weight)
    # items: (video, t) with frames t-1, t, t+1 valid
    items = []
    for v, s in enumerate(train_set):
        ok = s.valid.copy()
        ok3 = np.zeros_like(ok)
        ok3[1:-1] = ok[:-2] & ok[1:-1] & ok[2:]
        items += [(v, t) for t in np.flatnonzero(ok3)]
    items = np.asarray(items)
    log_rows: list[dict] = []
    step, best = 0, float("inf")
    ckpt = out_dir / "checkpoint.pt"
    if ckpt.exists():
        from nvp.artifact import load_checkpoint
        from nvp.errors import FormatError

        state = load_checkpoint(ckpt)
        try:
            net.load_state_dict(state["net"])
            with torch.no_grad():
                maps.copy_(state["maps"])
                bias.copy_(state["bias"])
            opt.load_state_dict(state["opt"])
            if "torch_rng" in state:  # dropout draws from torch's global generator
                torch.set_rng_state(state["torch_rng"])
            step, best = int(state["step"]), float(state["best"])
        except (RuntimeError, KeyError, ValueError, TypeError, AttributeError) as e:
            raise FormatError(
                f"{ckpt} was written by another nvp version, network or set of videos and cannot be "
                "resumed; delete it to train from scratch"
            ) from e
        log_rows = json.loads((out_dir / "log.json").read_text()) if (out_dir / "log.json").exists() else []
        if group.main:
            log.warning("resuming audio2exp training from %s at step %d of %d", ckpt, step, cfg.steps)
    forward = trainable
    if group.world > 1:
        from torch.nn.parallel import DistributedDataParallel

        forward = DistributedDataParallel(trainable)  # starts every process from the main one's weights
    f = net_cfg.filter_window
    bar = tqdm(total=cfg.steps, initial=step, desc="train audio2exp", disable=not (progress and group.main))
    t0 = time.perf_counter()
    running = []
    while step < cfg.steps:
        net.train()
        # batches depend only on (seed, step), so a resumed run continues exactly like an uninterrupted one
        rng = np.random.default_rng([cfg.seed, step])
        pick = items[rng.integers(0, len(items), cfg.batch)][share]  # the batch is drawn alike everywhere
        variant = rng.integers(0, 1 << 30, cfg.batch)[share]
        wins, tgts, vids, shut = [], [], [], []
        for (v, t), k in zip(pick, variant, strict=True):
            source = windows[v][k % len(windows[v])]  # clean or one of the copies
            idx = _filter_indices(np.array([t]), len(source), f)[0]
            wins.append(source[idx])
            tgts.append(targets[v][t - 1 : t + 2])
            shut.append(closed[v][t - 1 : t + 2])
            vids.append(v)
        wins = torch.stack(wins)
        if cfg.feature_noise > 0:
            noise_rng = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
            noise = torch.randn((cfg.batch, *wins.shape[1:]), generator=noise_rng)[share]
            wins = wins + cfg.feature_noise * net.per_frame.input_std * noise
        pred, closure_logits = forward(wins, torch.as_tensor(vids))
        # the vertex loss is an RMS over the whole batch: made from sums over all processes, and scaled by
        # their number because DistributedDataParallel averages the processes' gradients
        sums = group.total(metric.loss_sums(pred, torch.stack(tgts)))
        vertex_loss = metric.loss_from_sums(sums, cfg.temporal_weight)
        closure_loss = torch.zeros(())
        if closure_logits is not None:  # a mean over the items: DistributedDataParallel's average is right
            closure_loss = torch.nn.functional.binary_cross_entropy_with_logits(
                closure_logits, torch.stack(shut), pos_weight=pos_weight
            )
        loss = group.world * vertex_loss + cfg.closure_weight * closure_loss
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        running.append(vertex_loss.item() + cfg.closure_weight * group.mean(closure_loss.item()))
        bar.update(1)
        if (step % cfg.val_every == 0 or step == cfg.steps) and not group.main:
            running = []
            group.barrier()  # the main process validates and saves
            continue
        if step % cfg.val_every == 0 or step == cfg.steps:
            rows = [
                evaluate_person(s, model, audio_expressions(net, s.windows), cfg.train_fraction, cfg.ridge)
                for s in val_set
            ]
            summary = _summary(rows)
            entry = {
                "step": step,
                "train_loss": float(np.mean(running)),
                **summary,
                "seconds": round(time.perf_counter() - t0, 1),
            }
            running = []
            log_rows.append(entry)
            bar.set_postfix(loss=f"{entry['train_loss']:.4f}", val_mouth=f"{summary['mouth_error_iod']:.4f}")
            if summary["mouth_error_iod"] < best:
                best = summary["mouth_error_iod"]
                save_net(
                    net,
                    out_dir / "best",
                    {
                        "feature_kind": cfg.kind,
                        "step": step,
                        "validation": summary,
                        "validation_per_video": {s.name: r for s, r in zip(val_set, rows, strict=True)},
                        "train_config": {k: v for k, v in asdict(cfg).items() if k != "net"},
                        **(provenance or {}),
                    },
                )
            with atomic_path(ckpt) as tmp:  # flushed and renamed: a kill keeps the last whole checkpoint
                torch.save(
                    {
                        "net": net.state_dict(),
                        "maps": maps.detach(),
                        "bias": bias.detach(),
                        "opt": opt.state_dict(),
                        "step": step,
                        "best": best,
                        "torch_rng": torch.get_rng_state(),
                    },
                    tmp,
                )
            (out_dir / "log.json").write_text(json.dumps(log_rows, indent=2) + "\n")
            group.barrier()
    bar.close()
    return {"log": log_rows, "best_mouth_error_iod": best}


def train_on_corpus(
    corpus: Path,
    output: Path,
    cfg: Audio2ExpTrainConfig,
    val: list[str] | None = None,
    exclude: list[str] | None = None,
    cache: Path | None = None,
    progress: bool = True,
) -> dict | None:
    """``nvp train-audio2exp``: train on the videos of the folder ``corpus`` (``val``: validation file names,
    default 5 spread over the list; ``exclude``: left out) into ``output``; tracking and features are
    cached in ``cache`` (default ``output/cache``), the copies of ``cfg.augments`` too. Under
    torchrun every process calls it and the main process tracks the corpus into the cache first. Returns
    :func:`train`'s result in the main process, None in the others."""
    from nvp.app.corpus import corpus_split
    from nvp.app.distributed import process_group
    from nvp.face_model import default_face_model

    group = process_group()  # one process, or one of torchrun's
    cache = Path(cache) if cache else Path(output) / "cache"
    if not group.main:
        group.barrier()  # the main process tracks the corpus into the cache first
    train_set, val_set, split = corpus_split(
        Path(corpus), val, exclude, cache, cfg.kind, progress and group.main, cfg.augments
    )
    if group.main:
        group.barrier()
    frames = {"train_frames": int(sum(s.valid.sum() for s in train_set))}
    result = train(
        train_set,
        val_set,
        default_face_model(),
        cfg,
        Path(output),
        progress=progress,
        provenance={"split": split, **frames, "corpus": str(corpus), "processes": group.world},
    )
    return result if group.main else None
