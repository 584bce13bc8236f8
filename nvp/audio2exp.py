"""Audio2ExpressionNet (Neural Voice Puppetry, Sec. 3.1) and the person-specific expression maps.

Shapes: ``B`` batch, ``W`` feature frames per video frame (16), ``D`` feature dimension, ``F`` per-frame
predictions seen by the temporal filter (8), ``A`` audio-expression dimension (32), ``K_exp`` expression
coefficients of the face model.

* ``PerFrameNet``: ``(B, W, D) → (B, A)``: four temporal convolutions (kernel 3, stride 2, over the W
  feature frames, D as channels), then fully connected 64→128→64→A; leaky ReLU 0.02; tanh output.
* ``ExpressionFilter``: ``(B, F, A) → (B, A)``: five 1-D convolutions over the F predictions reduce the A
  channels to one, a fully connected layer turns the F values into softmax weights, and the output is
  the weighted sum of the F predictions (an expression-aware, learned temporal filter).
* Person map: ``K_exp × A`` matrix taking the audio-expression to the person's expression coefficients.
  For a new person it is solved in closed form (``solve_person_map``).

The loss lives in vertex space (``VertexMetric``): RMS vertex distance with the mouth weighted 10×, plus a
temporal term on forward, backward and central differences (λ = 20).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from nvp.artifact import load_artifact, save_artifact
from nvp.errors import FormatError

FORMAT_VERSION = 1
ASSETS = Path(__file__).parent / "assets"


@dataclass(frozen=True)
class Audio2ExpConfig:
    """Network sizes; saved with every trained model."""

    feature_dim: int = 191
    """D: feature channels per feature frame (191 for phonemes, 80 for mel)."""
    window: int = 16
    """W: feature frames per video frame (must be 16: four stride-2 convolutions reduce it to 1)."""
    audio_exp_dim: int = 32
    """A: dimension of the audio-expression space shared by all people."""
    filter_window: int = 8
    """F: per-frame predictions combined by the expression-aware temporal filter."""
    conv_channels: tuple[int, ...] = (32, 32, 64, 64)
    """Output channels of the four temporal convolutions."""
    negative_slope: float = 0.02
    """Leaky ReLU slope."""
    dropout: float = 0.0
    """Dropout on the fully connected layers during training (small corpora overfit)."""
    closure_head: bool = False
    """Also predict, per frame, the logit that the lips are closed (a linear layer on the per-frame net's
    last hidden features). A regression to expressions averages a closed and an open mouth into a
    half-open one where the audio is ambiguous; the head says how likely a closure is, so the person
    layer can close the mouth fully (:mod:`nvp.person`)."""


class PerFrameNet(nn.Module):
    """Per-frame audio → audio-expression network: ``(B, W, D) → (B, A)``."""

    def __init__(self, cfg: Audio2ExpConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = cfg.feature_dim
        for out in cfg.conv_channels:
            layers += [nn.Conv1d(c, out, 3, stride=2, padding=1), nn.LeakyReLU(cfg.negative_slope)]
            c = out
        self.conv = nn.Sequential(*layers)
        # per-channel input standardisation, set from the training corpus (see ``set_input_stats``)
        self.register_buffer("input_mean", torch.zeros(cfg.feature_dim))
        self.register_buffer("input_std", torch.ones(cfg.feature_dim))
        steps = cfg.window
        for _ in cfg.conv_channels:
            steps = (steps + 1) // 2
        self.fc = nn.Sequential(
            nn.Flatten(),
            nn.Linear(c * steps, 128),
            nn.LeakyReLU(cfg.negative_slope),
            nn.Dropout(cfg.dropout),
            nn.Linear(128, 64),
            nn.LeakyReLU(cfg.negative_slope),
            nn.Dropout(cfg.dropout),
            nn.Linear(64, cfg.audio_exp_dim),
            nn.Tanh(),
        )

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        return self.fc[-2:](self.hidden(windows))

    def hidden(self, windows: torch.Tensor) -> torch.Tensor:
        """``(B, 64)`` features of the last hidden layer (before the audio-expression output layer)."""
        if windows.ndim != 3:
            raise ValueError(f"expected feature windows (B, W, D), got {tuple(windows.shape)}")
        x = (windows - self.input_mean) / self.input_std
        return self.fc[:-2](self.conv(x.transpose(1, 2)))

    def set_input_stats(self, features: torch.Tensor) -> None:
        """Standardise inputs with the per-channel mean and std of ``features`` ``(..., D)``."""
        flat = features.reshape(-1, features.shape[-1]).double()
        self.input_mean.copy_(flat.mean(0))
        self.input_std.copy_(flat.std(0).clamp_min(1e-3))


class ExpressionFilter(nn.Module):
    """Expression-aware temporal filter: ``(B, F, A) → (B, A)`` plus the weights ``(B, F)``."""

    def __init__(self, cfg: Audio2ExpConfig) -> None:
        super().__init__()
        chans = [cfg.audio_exp_dim, 16, 8, 4, 2, 1]
        layers: list[nn.Module] = []
        for a, b in zip(chans[:-1], chans[1:], strict=True):
            layers += [nn.Conv1d(a, b, 3, padding=1), nn.LeakyReLU(cfg.negative_slope)]
        self.conv = nn.Sequential(*layers[:-1])  # no activation before the fully connected layer
        self.fc = nn.Linear(cfg.filter_window, cfg.filter_window)

    def forward(self, preds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits = self.fc(self.conv(preds.transpose(1, 2))[:, 0])
        weights = torch.softmax(logits, -1)
        return torch.einsum("bf,bfa->ba", weights, preds), weights


class Audio2ExpressionNet(nn.Module):
    """Generic audio → audio-expression network (per-frame net + expression-aware filter)."""

    def __init__(self, cfg: Audio2ExpConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.per_frame = PerFrameNet(cfg)
        self.filter = ExpressionFilter(cfg)
        self.closure = nn.Linear(64, 1) if cfg.closure_head else None

    def frame_outputs(self, windows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Per-frame audio-expressions ``(B, A)`` and closure logits ``(B,)`` (None without the closure
        head) for feature windows ``(B, W, D)``."""
        h = self.per_frame.hidden(windows)
        raw = self.per_frame.fc[-2:](h)
        return raw, (self.closure(h)[:, 0] if self.closure is not None else None)

    def sequence(self, windows: torch.Tensor, use_filter: bool = True, batch: int = 2048) -> torch.Tensor:
        """Audio-expressions ``(T, A)`` for a whole sequence of feature windows ``(T, W, D)``."""
        raw = torch.cat([self.per_frame(windows[s : s + batch]) for s in range(0, len(windows), batch)])
        return self.smooth(raw, batch) if use_filter else raw

    def smooth(self, raw: torch.Tensor, batch: int = 2048) -> torch.Tensor:
        """The expression-aware filter over a whole sequence of per-frame predictions ``(T, A)``.

        Frame t is filtered over per-frame predictions t-F/2 … t+F/2-1 (edge-padded), so the output is
        aligned with the input frames.
        """
        f = self.cfg.filter_window
        padded = torch.cat([raw[:1].expand(f // 2, -1), raw, raw[-1:].expand(f - f // 2 - 1, -1)])
        stacks = padded.unfold(0, f, 1).transpose(1, 2)  # (T, F, A)
        out = [self.filter(stacks[s : s + batch])[0] for s in range(0, len(stacks), batch)]
        return torch.cat(out)


class VertexMetric:
    """Squared vertex-space distance of expression-coefficient differences, mouth weighted.

    ``|B d|_W^2 = d^T G d`` with ``G = B^T W B / sum(W)`` (B the expression basis flattened to
    ``(3V, K_exp)``, W the per-vertex weights: ``mouth_weight`` on the mouth region, 1 elsewhere), so the
    loss never needs to build vertices.
    """

    def __init__(self, exp_basis: np.ndarray, mouth: np.ndarray, mouth_weight: float = 10.0) -> None:
        w = np.where(mouth, mouth_weight, 1.0)
        b = exp_basis.astype(np.float64)  # (K, V, 3)
        g = np.einsum("kvc,v,lvc->kl", b, w, b) / w.sum()
        self.gram = torch.from_numpy(g.astype(np.float32))

    def sq(self, diff: torch.Tensor) -> torch.Tensor:
        """Weighted mean squared vertex distance ``(...)`` for coefficient differences ``(..., K_exp)``."""
        return torch.einsum("...k,kl,...l->...", diff, self.gram, diff)

    def loss(self, pred: torch.Tensor, target: torch.Tensor, temporal_weight: float = 20.0) -> torch.Tensor:
        """RMS vertex error plus the temporal term, for three consecutive frames ``(B, 3, K_exp)``.

        Temporal term: RMS of the vertex-space error of the forward (x1-x0), backward (x2-x1) and central
        ((x2-x0)/2) differences.
        """
        return self.loss_from_sums(self.loss_sums(pred, target), temporal_weight)

    def loss_sums(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``(4,)``: sum and count of the squared vertex errors, then of the squared difference errors (the
        parts of :meth:`loss` that add up over shares of a batch)."""
        err = self.sq(pred - target)
        if pred.shape[1] < 3:
            return torch.stack([err.sum(), err.new_tensor(err.numel()), err.new_zeros(()), err.new_zeros(())])
        e = pred - target
        diffs = self.sq(torch.stack([e[:, 1] - e[:, 0], e[:, 2] - e[:, 1], (e[:, 2] - e[:, 0]) / 2], 1))
        return torch.stack(
            [err.sum(), err.new_tensor(err.numel()), diffs.sum(), diffs.new_tensor(diffs.numel())]
        )

    @staticmethod
    def loss_from_sums(sums: torch.Tensor, temporal_weight: float = 20.0) -> torch.Tensor:
        """:meth:`loss` from the (possibly summed over processes) :meth:`loss_sums`."""
        rms = (sums[0] / sums[1]).clamp_min(1e-12).sqrt()
        if sums[3] == 0:
            return rms
        return rms + temporal_weight * (sums[2] / sums[3]).clamp_min(1e-12).sqrt()


@dataclass(frozen=True)
class PersonMap:
    """A person's talking style: ``expression = audio_exp @ matrix.T + bias``.

    Attributes:
        matrix: ``(K_exp, A)`` float32.
        bias: ``(K_exp,)`` float32, the person's mean expression (not regularised).
    """

    matrix: np.ndarray
    bias: np.ndarray

    def apply(self, audio_exp: np.ndarray) -> np.ndarray:
        """Expression coefficients ``(T, K_exp)`` for audio-expressions ``(T, A)``."""
        return audio_exp @ self.matrix.T + self.bias


def solve_person_map(audio_exp: np.ndarray, expression: np.ndarray, ridge: float = 1.0) -> PersonMap:
    """Closed-form person map from a person's audio-expressions and tracked expressions.

    Minimises ``sum_t |B (M a_t + b - d_t)|_W^2 + ridge * |B M|_W^2`` (vertex space, mouth weighted).
    Because both terms use the same vertex metric, the weighting cancels and the minimiser is ordinary
    ridge regression on centred data: ``M = D_c^T A_c (A_c^T A_c + ridge I)^-1``, ``b = mean(d) - M mean(a)``
    — milliseconds for any video length.

    Args:
        audio_exp: ``(T, A)`` generic-net outputs on the person's frames.
        expression: ``(T, K_exp)`` the person's tracked expression coefficients.
        ridge: regularisation (in units of frames × squared audio-expression).
    """
    if len(audio_exp) != len(expression):
        raise ValueError(f"audio_exp has {len(audio_exp)} frames, expression has {len(expression)}")
    a = audio_exp.astype(np.float64)
    d = expression.astype(np.float64)
    am, dm = a.mean(0), d.mean(0)
    ac, dc = a - am, d - dm
    m = np.linalg.solve(ac.T @ ac + ridge * np.eye(a.shape[1]), ac.T @ dc).T
    return PersonMap(matrix=m.astype(np.float32), bias=(dm - m @ am).astype(np.float32))


def audio_expressions(net: Audio2ExpressionNet, windows: np.ndarray, use_filter: bool = True) -> np.ndarray:
    """Generic-net outputs ``(T, A)`` for feature windows ``(T, W, D)`` (inference, no gradients)."""
    net.eval()
    with torch.no_grad():
        return net.sequence(torch.from_numpy(windows), use_filter=use_filter).numpy()


def network_outputs(
    net: Audio2ExpressionNet, blocks: Iterable[np.ndarray]
) -> tuple[np.ndarray, np.ndarray | None]:
    """Filtered audio-expressions ``(T, A)`` and closure probabilities ``(T,)`` (None for a network
    without the closure head) for feature windows ``(T, W, D)`` given as consecutive blocks ``(≤ T, W, D)``
    (so a long file's windows need not be in memory at once); one pass of the per-frame net, no gradients."""
    net.eval()
    raw, shut = [], []
    with torch.no_grad():
        for w in blocks:
            r, c = net.frame_outputs(torch.from_numpy(np.asarray(w)))
            raw.append(r)
            if c is not None:
                shut.append(torch.sigmoid(c))
        audio_exp = net.smooth(torch.cat(raw)) if raw else torch.zeros(0, net.cfg.audio_exp_dim)
    if net.closure is None:
        return audio_exp.numpy(), None
    return audio_exp.numpy(), torch.cat(shut).numpy() if shut else np.zeros(0, np.float32)


def in_blocks(windows: np.ndarray, block: int = 2048) -> list[np.ndarray]:
    """Feature windows ``(T, W, D)`` as consecutive blocks of at most ``block`` frames (views)."""
    return [windows[s : s + block] for s in range(0, len(windows), block)]


def save_net(net: Audio2ExpressionNet, out: Path, manifest: dict) -> Path:
    """Write ``<out>.npz`` (weights) and ``<out>.json`` (format, config, ``manifest``: provenance)."""
    arrays = {k: v.detach().cpu().numpy() for k, v in net.state_dict().items()}
    return save_artifact(Path(out), "audio2exp", FORMAT_VERSION, arrays, {"net": asdict(net.cfg), **manifest})


def load_net(path: Path) -> tuple[Audio2ExpressionNet, dict]:
    """A saved network (from its ``.json`` manifest or ``.npz``) in eval mode, and its manifest, whose
    ``sha256`` (of the weights file) identifies the network for the person maps made with it."""
    art = load_artifact(path, "audio2exp", FORMAT_VERSION)
    cfg = dict(art.manifest["net"])
    cfg["conv_channels"] = tuple(cfg["conv_channels"])
    net = Audio2ExpressionNet(Audio2ExpConfig(**cfg))
    try:
        net.load_state_dict({k: torch.from_numpy(v) for k, v in art.arrays.items()})
    except RuntimeError as e:
        raise FormatError(f"cannot load Audio2Expression weights {art.path}: {e}") from e
    return net.eval(), art.manifest


def default_audio2exp(kind: str = "phonemes") -> tuple[Audio2ExpressionNet, dict]:
    """The generic network that ships with nvp for a feature kind, and its manifest."""
    path = ASSETS / f"audio2exp_{kind}.json"
    if not path.exists():
        raise FormatError(f"no shipped Audio2ExpressionNet for features '{kind}' ({path} missing)")
    return load_net(path)
