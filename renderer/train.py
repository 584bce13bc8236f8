"""Training the neural renderer on one person's footage (resumable, seeded, time-budgeted).

Losses (pure functions): L1 on the final image, masked L1 on the interior render, a structural term
(1 - SSIM, kornia) that needs no downloaded weights, and optionally an L1 term on the images' high
frequencies (image minus its Gaussian blur) inside the face, which the other terms let the networks blur.
"""

from __future__ import annotations

import copy
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from nvp.artifact import atomic_path, load_checkpoint
from nvp.errors import FormatError, NvpError
from nvp.threads import ThreadGovernor
from renderer.adversarial import critic_loss, generator_loss
from renderer.divergence import BLOCK, DivergenceGuard
from renderer.inputs import Rasterizer, blank_face, moved_source
from renderer.networks import (
    NeuralRenderer,
    count_parameters,
    generic_renderer_dir,
    load_renderer,
    make_renderer,
    same_structure,
    save_renderer,
)
from renderer.plateau import PlateauSchedule, held_out_blocks, plateaued
from renderer.preset import Preset, get_preset
from renderer.train_data import FrameCache

log = logging.getLogger(__name__)


UNLIMITED_STEPS = 10**9
"""The step limit of a training that only its time budget ends."""


@dataclass(frozen=True)
class RendererTrainConfig:
    """Renderer training settings (saved with the weights)."""

    preset: str = "cpu"
    """Resolution / network size preset (``renderer.preset.PRESETS``)."""
    steps: int | None = None
    """Optimisation steps; None = as many as ``budget_s`` allows, or the preset's default without one."""
    budget_s: float | None = None
    """Stop (and save) after this many seconds of training, whatever ``steps`` says."""
    lr: float = 1e-3
    """Adam learning rate (networks and texture) at the start."""
    lr_final: float = 0.05
    """Learning rate at the end of training, as a fraction of ``lr``: the rate follows a half cosine from
    ``lr`` down to ``lr · lr_final`` over the run (its steps or its time budget, whichever ends first)."""
    ssim_weight: float = 0.5
    """Weight of the 1 - SSIM term."""
    interior_weight: float = 1.0
    """Weight of the masked L1 term on the interior render."""
    detail_weight: float = 0.0
    """Weight of the high-frequency term (:func:`high_frequency_l1`) on the final image inside the mesh."""
    adversarial_weight: float = 0.0
    """Weight of the patch-adversarial term (:mod:`renderer.adversarial`; 0: none)."""
    adversarial_start: float = 0.25
    """Part of the training after which the adversarial term is added (the critic trains from the start)."""
    region_mix: float = 0.5
    """Fraction of training crops whose blanked region is widened to the union with another training
    frame's region, as when a dub's new geometry covers less than the footage's own face: the
    compositing network then learns to paint the footage's neck and collar where a chin was blanked."""
    vgg_weights: str | None = None
    """Optional VGG-16 weights file (torchvision layout) for a perceptual term; never downloaded."""
    vgg_weight: float = 0.1
    """Weight of the perceptual term when ``vgg_weights`` is given."""
    source_gap_s: tuple[float, float] = (0.4, 4.0)
    """With a preset that feeds the footage's moved pixels to the network (``Preset.source_input``), each
    training crop takes them from another training frame this many seconds away (at 25 fps), like a dub,
    whose footage frame shows another mouth."""
    checkpoint_every: int = 250
    """Steps between checkpoints (which also log the mean loss)."""
    checkpoint_seconds: float = 60.0
    """Training seconds after which a checkpoint is written between those of ``checkpoint_every``: a run
    killed at any point loses at most this much training (250 steps take 2 minutes and more on a CPU)."""
    preview_every: int = 500
    """Steps between preview PNGs (ground truth | interior | final)."""
    seed: int = 0
    """Random seed (initial weights, batches)."""
    max_grad_norm: float | None = 1.0
    """The gradient (all parameters together) is scaled down to this norm when it is longer: the usual norm
    is 0.1-0.7, a batch unlike the rest gives 5-10 (None: no clipping)."""
    diverge_ratio: float = 3.0
    """A mean loss over 50 steps this many times the best one so far (or not finite) means the training
    diverged: it goes back to its state at the last healthy 50 steps with half the learning rate
    (:mod:`renderer.divergence`), at most ``max_rollbacks`` times, then stops with an error."""
    max_rollbacks: int = 3
    stop_on_plateau: bool = False
    """End the run when the networks stop improving (:mod:`renderer.plateau`): the learning rate stays at
    ``lr`` while the face's L1 on ``plateau_frames`` held-out frames (in stretches of the footage the training
    leaves out until the decay, ``plateau_reach``) is measured at every checkpoint; when its
    best over the last ``plateau_window`` steps is less than ``plateau_gain`` below its best before them, or
    when the steps or the time budget would run out, the rate falls along a half cosine to ``lr · lr_final``
    over ``decay_fraction`` of the steps trained so far, and the run ends. False: one half cosine over the
    whole run."""
    plateau_window: int = 1000
    plateau_gain: float = 0.01
    plateau_frames: int = 16
    plateau_reach: int = 20
    """Frames (0.8 s at 25 fps) around each held-out frame that the training leaves out until the decay
    (:func:`renderer.plateau.held_out_blocks`)."""
    decay_fraction: float = 0.25
    init: str | None = "generic"
    """Starting weights: ``"generic"`` = the renderer pre-trained on many people that ships for the preset
    (:func:`renderer.networks.generic_renderer_dir`; from scratch when the preset has none), None = from
    scratch, or a renderer folder (its networks and texture; the preset's structure must match)."""


FIRST_PREVIEW = 100
"""Step of the first preview image (then every ``preview_every``), so a short fit shows one early."""


def l1_masked(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over the pixels where ``mask`` ``(B, 1, H, W)`` is 1, averaged over the crops
    (each crop's own mean: a batch split over processes gives the same loss, see :func:`train_renderer`)."""
    err = ((pred - target).abs() * mask).sum((1, 2, 3))
    return (err / (mask.sum((1, 2, 3)) * pred.shape[1]).clamp_min(1.0)).mean()


def high_pass(image: torch.Tensor) -> torch.Tensor:
    """``image`` ``(B, C, H, W)`` minus its 5×5 Gaussian blur (σ 1): the fine detail (stubble, pores, lip
    texture, teeth edges) that an L1-trained renderer averages away."""
    from kornia.filters import gaussian_blur2d

    return image - gaussian_blur2d(image, (5, 5), (1.0, 1.0), border_type="replicate")


def high_frequency_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Masked L1 between the high-pass images (:func:`high_pass`) of ``pred`` and ``target``
    ``(B, 3, H, W)`` where ``mask`` ``(B, 1, H, W)`` is 1."""
    return l1_masked(high_pass(pred), high_pass(target), mask)


def renderer_loss(
    interior: torch.Tensor,
    final: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    cfg: RendererTrainConfig,
) -> torch.Tensor:
    """L1(final) + w_i · masked L1(interior) + w_s · (1 - SSIM(final)) + w_d · high-frequency L1(final,
    inside the mesh) for images ``(B, 3, H, W)``."""
    from kornia.losses import ssim_loss

    loss = (final - target).abs().mean() + cfg.interior_weight * l1_masked(interior, target, mask)
    loss = loss + cfg.ssim_weight * 2 * ssim_loss(final, target, window_size=7)
    if cfg.detail_weight > 0:
        loss = loss + cfg.detail_weight * high_frequency_l1(final, target, mask)
    return loss


def learning_rate(cfg: RendererTrainConfig, progress: float) -> float:
    """Cosine-decayed learning rate at ``progress`` (0 = start, 1 = end of training)."""
    p = min(max(progress, 0.0), 1.0)
    return float(cfg.lr * (cfg.lr_final + (1 - cfg.lr_final) * 0.5 * (1 + np.cos(np.pi * p))))


def held_out_loss(
    net: NeuralRenderer,
    cache: FrameCache,
    rows: np.ndarray,
    texture: nn.Module,
    sources: SourceSampler | None,
    seed: int,
    device: str,
) -> float:
    """The face's L1 (inside the mesh) of ``net``'s render of cache ``rows``, with their own blanked region
    and, for a source-input preset, sources drawn the same way at every call."""
    net.eval()
    total = 0.0
    with torch.no_grad():
        for part in np.array_split(rows, -(-len(rows) // 8)):
            target, geo = cache.batch(part, device)
            source = sources(cache, part, np.random.default_rng([seed, 1])).to(device) if sources else None
            _, final = net(
                geo.uv, geo.mask, geo.mouth, blank_face(target, geo.region), geo.region, source, texture
            )
            total += float(l1_masked(final, target, geo.mask)) * len(part)
    net.train()
    return total / len(rows)


def mix_regions(
    region: torch.Tensor, cache: FrameCache, rng: np.random.Generator, fraction: float
) -> torch.Tensor:
    """``region`` ``(B, 1, S, S)`` with a random ``fraction`` of its crops widened to the union with the
    region of a random other frame of ``cache``."""
    pick = np.flatnonzero(rng.random(region.shape[0]) < fraction)
    if len(pick) == 0:
        return region
    other = torch.from_numpy(cache.region[rng.integers(0, len(cache.frames), len(pick))])
    region = region.clone()
    region[pick, 0] = torch.maximum(region[pick, 0], other.to(region))
    return region


def _preview(path: Path, target: torch.Tensor, interior: torch.Tensor, final: torch.Tensor) -> None:
    from PIL import Image

    row = torch.cat([target[0], interior[0], final[0]], 2).clamp(0, 1)
    Image.fromarray((row.permute(1, 2, 0).detach().cpu().numpy() * 255).round().astype(np.uint8)).save(path)


class SourceSampler:
    """The moved-source input of a training batch: for each target crop, another frame of its cache ``gap``
    seconds away (``cfg.source_gap_s``, assuming 25 fps) moved onto the target's surface."""

    def __init__(self, preset: Preset, gap_s: tuple[float, float]) -> None:
        from nvp.face_model import default_face_model

        model = default_face_model()
        self.gap = (round(gap_s[0] * 25), round(gap_s[1] * 25))
        self.raster = Rasterizer(model, preset.crop, preset.region_grow)
        self.triangles = torch.from_numpy(model.triangles)
        self.movable = torch.from_numpy(~model.triangle_regions["mouth_interior"])

    def close(self) -> None:
        self.raster.close()

    def pick(self, cache: FrameCache, i: int, rng: np.random.Generator) -> int:
        d = np.abs(cache.frames - cache.frames[i])
        ok = np.flatnonzero((d >= self.gap[0]) & (d <= self.gap[1]))
        if len(ok) == 0:
            ok = np.flatnonzero(d > 0) if len(d) > 1 else np.array([i])
        return int(rng.choice(ok))

    def __call__(self, cache: FrameCache, idx: np.ndarray, rng: np.random.Generator) -> torch.Tensor:
        c = cache
        focal, center = float(c.camera[0]), c.camera[1:]
        out = []
        for i in idx:
            j = self.pick(c, int(i), rng)
            geo = self.raster(c.vertices[i], focal, center, c.boxes[i])
            src = self.raster(c.vertices[j], focal, center, c.boxes[j])
            crop = torch.from_numpy(c.crops[j]).permute(2, 0, 1).float() / 255
            moved, _, _ = moved_source(
                geo, crop, c.boxes[j], c.vertices[j], src.depth, (focal, center), self.triangles, self.movable
            )
            out.append(moved)
        return torch.stack(out)


def initial_weights(net: NeuralRenderer, preset: Preset, init: str | None) -> str:
    """Load ``init``'s weights (see :attr:`RendererTrainConfig.init`) into ``net``; returns what was loaded
    (``"scratch"``, ``"generic:<sha256 prefix>"`` or the folder)."""
    if init is None:
        return "scratch"
    folder = generic_renderer_dir(preset) if init == "generic" else Path(init)
    if folder is None:
        log.info("no generic renderer ships for preset %s: training from scratch", preset.name)
        return "scratch"
    start, start_preset, manifest = load_renderer(folder)
    if not same_structure(start_preset, preset) or start.region_input != net.region_input:
        raise FormatError(
            f"{folder} holds a renderer of another structure (preset {start_preset.name}, crop "
            f"{start_preset.crop}, base {start_preset.base}); it cannot start a {preset.name} training"
        )
    net.load_state_dict(start.state_dict())
    return f"generic:{manifest.get('sha256', '')[:16]}" if init == "generic" else str(folder)


def train_renderer(
    caches: FrameCache | Sequence[FrameCache],
    cfg: RendererTrainConfig,
    out_dir: Path,
    device: str = "cpu",
    progress: bool = True,
    preset: Preset | None = None,
    names: Sequence[str] | None = None,
    group=None,
    say_resume: bool = True,
) -> dict:
    """Train on one person's frames, or pre-train on many; resumable from ``out_dir/checkpoint.pt``.
    Writes ``renderer.{npz,json}``.

    A resumed training says so in one warning line (where it goes on from; ``say_resume=False``: the
    caller says it); a checkpoint that cannot be read (damaged from outside) is one :class:`FormatError`
    naming it, to be deleted to start again.

    ``caches``: one ``FrameCache`` (a person), or several (one per video: pre-training a generic renderer;
    the networks are shared, each video has its own texture, every step draws its batch from one video
    chosen at random, and the saved texture is the mean of theirs, the start of a new person's).
    ``preset`` overrides ``cfg.preset`` (e.g. a shrunken preset in tests); the caches must match its crop.
    ``names``: the videos' names (recorded in the manifest).

    ``group``: this process's place among several training processes (``nvp.app.distributed.Group``,
    under ``torchrun``; None: one process). Every process draws the same batches (they depend on the seed
    and the step only) and computes its share of each; the gradients are averaged over the processes with
    ``torch.distributed`` (every loss term is a mean over crops, so N processes follow the one-process run
    up to float rounding). DistributedDataParallel itself is not used: a step updates one video's texture
    and leaves the others without gradient, which its reducer cannot express. The main process writes the
    checkpoints, previews and the result.
    """
    preset = preset or get_preset(cfg.preset)
    caches = [caches] if isinstance(caches, FrameCache) else list(caches)
    if not caches:
        raise ValueError("no training frames")
    for cache in caches:
        if cache.crops.shape[1] != preset.crop:
            raise ValueError(
                f"cache crops are {cache.crops.shape[1]} px, preset {preset.name} needs {preset.crop}"
            )
    steps = cfg.steps or (UNLIMITED_STEPS if cfg.budget_s is not None else preset.steps)
    world, main = (group.world, group.main) if group is not None else (1, True)
    if world > 1 and cfg.adversarial_weight > 0:
        raise ValueError("the adversarial term trains on one process only")
    if cfg.stop_on_plateau and len(caches) > 1:
        raise ValueError("a training on several videos cannot stop on a plateau (it has no one person)")
    schedule = PlateauSchedule(cfg.decay_fraction) if cfg.stop_on_plateau else None
    held_out, left_out = (
        held_out_blocks(caches[0].frames, cfg.plateau_frames, reach=cfg.plateau_reach)
        if schedule
        else (None, None)
    )
    drawn = np.setdiff1d(np.arange(len(caches[0].frames)), left_out) if schedule else None  # until the decay
    out_dir.mkdir(parents=True, exist_ok=True)
    sources = SourceSampler(preset, cfg.source_gap_s) if preset.source_input else None
    torch.manual_seed(cfg.seed)
    net = make_renderer(preset).to(device)
    start = initial_weights(net, preset, cfg.init)
    # one texture per video; the renderer's own is the first one's
    textures = nn.ModuleList([net.texture])
    textures.extend(copy.deepcopy(net.texture) for _ in caches[1:])
    params = [*net.parameters(), *textures[1:].parameters()]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    critic = critic_opt = None
    if cfg.adversarial_weight > 0:
        from renderer.adversarial import PatchCritic

        critic = PatchCritic().to(device)
        critic_opt = torch.optim.Adam(critic.parameters(), lr=2e-4, betas=(0.5, 0.999))
    step, elapsed, log_rows = 0, 0.0, []
    guard = DivergenceGuard(cfg.diverge_ratio)

    def training_state() -> dict:
        """Everything a checkpoint holds (references to the live tensors: copy before training on)."""
        return {
            "net": net.state_dict(),
            "textures": textures.state_dict(),
            "opt": opt.state_dict(),
            "step": step,
            "elapsed": elapsed,
            "log": json.dumps(log_rows),
            "guard": guard.state(),
            **({"schedule": schedule.state()} if schedule else {}),
            **({"critic": critic.state_dict(), "critic_opt": critic_opt.state_dict()} if critic else {}),
        }

    def restore(state: dict) -> tuple[int, list, PlateauSchedule | None, DivergenceGuard]:
        """Load ``state`` (:func:`training_state`) into the networks and optimisers; returns its step, log,
        plateau schedule and guard."""
        net.load_state_dict(state["net"])
        if "textures" in state or len(caches) > 1:  # (older single-video checkpoints have none)
            textures.load_state_dict(state["textures"])
        opt.load_state_dict(state["opt"])
        if critic is not None and "critic" in state:
            critic.load_state_dict(state["critic"])
            critic_opt.load_state_dict(state["critic_opt"])
        return (
            int(state["step"]),
            json.loads(state["log"]),
            PlateauSchedule.from_state(state["schedule"]) if schedule is not None else None,
            DivergenceGuard.from_state(cfg.diverge_ratio, state.get("guard")),
        )

    ckpt = out_dir / "checkpoint.pt"
    if ckpt.exists():
        state = load_checkpoint(ckpt, device)
        try:
            step, log_rows, schedule, guard = restore(state)
            elapsed = float(state["elapsed"])
        except (RuntimeError, KeyError, ValueError, TypeError, AttributeError) as e:
            raise FormatError(
                f"{ckpt} was written by another nvp version, preset or set of videos and cannot be "
                "resumed; delete it to train from scratch"
            ) from e
        del state
        if say_resume and main:
            log.warning(
                "resuming renderer training from %s at step %d (%.1f min trained)", ckpt, step, elapsed / 60
            )

    def save_checkpoint() -> None:
        if not main:
            return
        with atomic_path(ckpt) as tmp:  # flushed and renamed: a kill or power cut keeps the last whole one
            torch.save(training_state(), tmp)

    healthy = copy.deepcopy(training_state())  # where a diverged training goes back to
    candidate = None  # the next one, once the block after it is healthy too
    perceptual = None
    if cfg.vgg_weights:
        from renderer.perceptual import VGGPerceptual

        perceptual = VGGPerceptual(cfg.vgg_weights).to(device)
    # with a time budget the bar counts seconds, so it shows the time left; else it counts steps
    timed = cfg.budget_s is not None
    bar = tqdm(
        total=round(cfg.budget_s) if timed else steps,
        initial=round(elapsed) if timed else step,
        desc=f"train renderer ({preset.name})",
        unit="s" if timed else "it",
        bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s, {remaining} left{postfix}" if timed else None,
        disable=not (progress and main),
    )

    def judge_plateau(step: int, elapsed: float, steps: int) -> None:
        """Measure the held-out loss and start the decay once it stops falling or the limit nears."""
        if schedule.decay_from is not None:
            return
        if len(held_out):
            loss = held_out_loss(net, caches[0], held_out, textures[0], sources, cfg.seed, device)
            schedule.history.append((step, group.mean(loss) if world > 1 else loss))
        if plateaued(schedule.history, cfg.plateau_window, cfg.plateau_gain):
            schedule.start_decay(step, elapsed, "plateau", steps - step)
        elif schedule.must_decay(step, elapsed, steps, cfg.budget_s):
            schedule.start_decay(step, elapsed, "limit", steps - step)

    def go_back(to: dict, at: int, block: float) -> tuple[int, list, PlateauSchedule | None]:
        """Restore the healthy state ``to`` after the block ending at step ``at`` diverged (mean loss
        ``block``) and record it in the guard (the rate halves); one error after ``max_rollbacks``."""
        if len(guard.rollbacks) >= cfg.max_rollbacks:
            raise NvpError(
                f"renderer training diverged at step {at} (mean loss of the last steps {block:.4f}, best "
                f"{guard.best:.4f}) after going back {len(guard.rollbacks)} times with the learning rate "
                f"halved each time (now {cfg.lr * guard.lr_scale:.1e}); look for footage whose frames differ "
                "from the rest (another face, a cut, a broken track)"
            )
        back_to, rows, plateau, _ = restore(copy.deepcopy(to))  # (the optimiser keeps what it is given)
        log.warning(
            "renderer training diverged at step %d (mean loss of the last steps %.4f, best %.4f): going back "
            "to step %d with the learning rate halved",
            at,
            block,
            guard.best,
            back_to,
        )
        guard.rollbacks.append(
            {"step": at, "loss": round(block, 6), "best": round(guard.best, 6), "back_to": back_to}
        )
        return back_to, rows, plateau

    running: list[float] = []  # the losses since the last row of the log
    block_losses: list[float] = []  # since the last judgement of the guard
    saved_at = elapsed  # training seconds at the last checkpoint
    t_last = time.perf_counter()
    governor = ThreadGovernor() if str(device) == "cpu" else None  # threads follow the free cores
    last = schedule.end(steps) if schedule else steps  # where the run ends (moves when a decay starts)

    def goes_on() -> bool:
        return step < last and (cfg.budget_s is None or elapsed < cfg.budget_s)

    while goes_on():
        if governor is not None:
            governor.update()
        net.train()
        if schedule is not None:
            progress = schedule.progress(step, elapsed, cfg.budget_s)
        else:
            progress = step / steps if cfg.budget_s is None else max(step / steps, elapsed / cfg.budget_s)
        for group_params in opt.param_groups:
            group_params["lr"] = learning_rate(cfg, progress) * guard.lr_scale
        rng = np.random.default_rng([cfg.seed, step])
        person = int(rng.integers(len(caches))) if len(caches) > 1 else 0
        cache = caches[person]
        # the held-out stretches are left out until the decay starts, then trained on like the rest
        pool = drawn if schedule is not None and schedule.decay_from is None else np.arange(len(cache.frames))
        idx = pool[rng.integers(0, len(pool), preset.batch)]
        target, geo = cache.batch(idx, device)
        region = mix_regions(geo.region, cache, rng, cfg.region_mix)
        source = sources(cache, idx, rng).to(device) if sources is not None else None
        uv, mask, mouth = geo.uv, geo.mask, geo.mouth
        if world > 1:  # this process's share of the batch (drawn whole, so every process draws alike)
            part = group.share(preset.batch)
            target, uv, mask, mouth, region = target[part], uv[part], mask[part], mouth[part], region[part]
            source = source[part] if source is not None else None
        interior, final = net(uv, mask, mouth, blank_face(target, region), region, source, textures[person])
        loss = renderer_loss(interior, final, target, mask, cfg)
        if perceptual is not None:
            loss = loss + cfg.vgg_weight * perceptual(final, target)
        if critic is not None and progress >= cfg.adversarial_start:
            loss = loss + cfg.adversarial_weight * generator_loss(critic, final, mask)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if world > 1:
            average_gradients(opt, group)
        if cfg.max_grad_norm is not None:
            nn.utils.clip_grad_norm_(params, cfg.max_grad_norm)
        opt.step()
        if critic is not None:
            critic_opt.zero_grad(set_to_none=True)  # also drops what the renderer's loss left on it
            critic_loss(critic, target, final, mask).backward()
            critic_opt.step()
        step += 1
        now = time.perf_counter()
        elapsed += now - t_last
        t_last = now
        value = loss.item()
        if world > 1:  # the processes agree on the time (when to stop) and report the whole batch's loss
            elapsed, value = group.mean(elapsed), group.mean(value)
        running.append(value)
        block_losses.append(value)
        if schedule is not None and step % cfg.checkpoint_every == 0:
            judge_plateau(step, elapsed, steps)
            last = schedule.end(steps)
        if timed:  # the bar counts seconds up to the end the steps or the budget set, whichever comes first
            bar.total = round(min(cfg.budget_s, elapsed * last / step))
            bar.update(min(elapsed, bar.total) - bar.n)
        else:
            bar.total = last
            bar.update(1)
        if step % 50 == 0:
            bar.set_postfix(step=step, loss=f"{np.mean(running[-50:]):.4f}")
        if main and (step % cfg.preview_every == 0 or step == FIRST_PREVIEW):
            _preview(out_dir / f"preview_{step:06d}.png", target, interior, final)
        if step % cfg.checkpoint_every == 0 or step == last:
            row = {"step": step, "loss": float(np.mean(running)), "seconds": round(elapsed, 1)}
            if schedule is not None and schedule.history and schedule.history[-1][0] == step:
                row["held_out"] = round(schedule.history[-1][1], 6)
            log_rows.append(row)
            running = []
            save_checkpoint()
            saved_at = elapsed
        elif elapsed - saved_at >= cfg.checkpoint_seconds:  # by time too: a kill loses a minute at most
            save_checkpoint()
            saved_at = elapsed
        if (step % BLOCK == 0 or not goes_on()) and step > healthy["step"]:
            block, block_losses = float(np.mean(block_losses)), []
            if not guard.diverged(block):  # a state is healthy once the block after it was
                healthy, candidate = candidate or healthy, None
                if step - healthy["step"] >= cfg.checkpoint_every:
                    candidate = copy.deepcopy(training_state())
            else:
                step, log_rows, schedule = go_back(healthy, step, block)
                running, candidate, last = [], None, schedule.end(steps) if schedule else steps
                if not timed:
                    bar.n = step
                save_checkpoint()
                saved_at = elapsed
    bar.close()
    if sources is not None:
        sources.close()
    if running:
        log_rows.append({"step": step, "loss": float(np.mean(running)), "seconds": round(elapsed, 1)})
    save_checkpoint()
    if len(caches) > 1:  # the generic renderer's texture: where a new person's starts
        with torch.no_grad():
            net.texture.texture.copy_(torch.stack([t.texture for t in textures]).mean(0))
    info = {
        "steps": step,
        "train_seconds": round(elapsed, 1),
        "train_frames": int(sum(len(c.frames) for c in caches)),
        "init": start,
        **(
            {"decay": {"from": schedule.decay_from, "steps": schedule.decay_steps, "why": schedule.reason}}
            if schedule
            else {}
        ),
        "processes": world,
        **({"diverged": guard.rollbacks} if guard.rollbacks else {}),
        **({"videos": list(names)} if names is not None else {}),
        "parameters": count_parameters(net),
        "config": asdict(cfg),
        "log": log_rows,
    }
    if main:
        save_renderer(net, out_dir, preset, info)
    if group is not None:
        group.barrier()
    return info


def average_gradients(opt: torch.optim.Optimizer, group) -> None:
    """Replace every gradient of ``opt``'s parameters by its mean over the training processes of ``group``
    (``nvp.app.distributed.Group``; parameters without a gradient, the textures a step did not use, are
    left alone alike everywhere)."""
    grads = [p.grad for g in opt.param_groups for p in g["params"] if p.grad is not None]
    flat = torch.cat([g.reshape(-1) for g in grads])
    group.add_up(flat)
    flat /= group.world
    offset = 0
    for g in grads:
        g.copy_(flat[offset : offset + g.numel()].view_as(g))
        offset += g.numel()
