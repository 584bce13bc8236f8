"""``nvp eval``: the self-reenactment protocol — fit on the first part of a video, re-create the held-out
tail, compare with the real frames.

Two re-creations of every held-out frame, both rendered into that real frame with its own tracked pose:

- *visual*: the tracked expression (rendering error alone);
- *audio*: mouth and jaw predicted from the tail's own audio by the person's style (what ``nvp dub``
  does; audio-to-expression plus rendering error), eyes and brows from tracking.

Both take the footage's fine detail from another held-out frame at least a second away
(:func:`detail_sources`): a dub moves the detail of the footage frame it replaces, and moving the real
frame's own detail back onto its re-creation would compare it with itself.

Metrics per frame and summarised: PSNR / SSIM on the full frame and on the stabilised face crop; in a box
around the real frame's lips (grown by 60 % of the mouth width) PSNR and the fine-detail ratios
(high-frequency and Laplacian energy over the real frames', pooled over the frames: where nvp paints, is it
as detailed as the footage?) and the correlation of its finest detail with the real frame's (is that detail
the footage's, in place, or specks and misplaced stubble?); mediapipe run on real and generated frames: lip
landmark distance / interocular distance (the paper's metric), lip-closure precision / recall / F1
(inner-lip gap below the real video's closed level), the audio-visual offset (cross-correlation of mouth
opening, frames; 0 is perfect),
mouth-landmark jitter relative to the real video, and lip-sync behaviour measured on generated and real
frames alike (``*_real`` is the target): the bilabial closure rate (frames where the held-out audio says p,
b or m with the mouth closed from 0.16 s before; ratio to the real rate), the opening range (p95 of the gap
over the real p95) and pauses of at least 0.3 s found by the voice-activity detector (fraction of pause
frames with a closed or resting mouth, mouth motion in pauses relative to speech).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from nvp.errors import MediaError, NvpError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalConfig:
    """Settings of ``nvp eval``."""

    train_fraction: float = 0.8
    """Part of the video used to fit the person; the rest is held out."""
    preset: str = "cpu"
    """Renderer preset."""
    budget_minutes: float | None = None
    """Renderer training time (None: as ``nvp fit``'s default, the preset's time on a CPU, so the numbers are
    those of the person a plain ``nvp fit`` makes)."""
    steps: int | None = None
    """Renderer training steps (None: the preset's, within the budget)."""
    features: str = "phonemes"
    """Speech features."""
    side_by_side: bool = False
    """Also write ``side_by_side.mp4`` (real | visual | audio)."""
    device: str = "cpu"
    """Torch device for renderer training and rendering."""
    renderer_init: str = "generic"
    """Where renderer training starts (``FitConfig.renderer_init``)."""


def _trim(video: Path, out: Path, frames: int, fps: float) -> None:
    """Write the first ``frames`` frames of ``video`` (with their audio) to ``out``."""
    from nvp.media import VideoWriter, audio_rate, iter_frames, probe_video, read_audio

    info = probe_video(video)
    rate = audio_rate(video)
    audio = read_audio(video, None, mono=False)[: int(round(frames / fps * rate))]
    with VideoWriter(out, fps, info.width, info.height, audio=audio, audio_rate=rate) as w:
        for frame in iter_frames(video, fps=fps, max_frames=frames):
            w.write(frame)


def _speech_timing(audio: np.ndarray, rate: int, fps: float, n: int) -> dict:
    """What the held-out audio ``(S,)`` says, per video frame (``(n,)`` bool each): ``bilabial`` frames (the
    phoneme recogniser hears p, b or m), ``speech`` frames (voice-activity probability >= 0.5) and
    ``pauses`` (runs of at least 0.3 s without speech)."""
    from nvp.audio_features import extract_features, phoneme_labels
    from nvp.metrics import bilabial_classes, bilabial_frames, pause_mask
    from nvp.vad import SPEECH_THRESHOLD, frame_speech_probability

    post = extract_features(audio, rate, kind="phonemes")
    bil = bilabial_frames(post.values, bilabial_classes(phoneme_labels()), post.rate, fps, n)
    voiced = frame_speech_probability(audio, rate, fps, n) >= SPEECH_THRESHOLD
    return {"bilabial": bil, "speech": voiced, "pauses": pause_mask(voiced, fps, 0.3), "fps": fps}


def _lip_metrics(real: np.ndarray, gen: np.ndarray, found: np.ndarray, groups: dict, timing: dict) -> dict:
    """Landmark metrics of generated vs real mediapipe landmarks ``(T, 478, 2)`` on frames ``found``, with
    the lip-sync behaviour measured on both (``*_real``: the real video's number, the target) at the
    frames of :func:`_speech_timing` ``timing``."""
    from nvp.metrics import (
        BILABIAL_LEAD_S,
        av_offset,
        bilabial_closure_rate,
        closed_level,
        closure_f1,
        inner_lip_gap,
        interocular_distance,
        jitter,
        opening_range_ratio,
        pause_behaviour,
    )

    lips = np.concatenate([groups["lips_outer"], groups["lips_inner"]])
    iod = interocular_distance(real, groups["left_eye"], groups["right_eye"])
    err = np.linalg.norm(gen[:, lips] - real[:, lips], axis=-1).mean(1) / iod
    gap_r, gap_g = inner_lip_gap(real) / iod, inner_lip_gap(gen) / iod
    closed, rest = closed_level(gap_r[found]), closed_level(gap_r[found], 0.3)
    closure = closure_f1(gap_g[found], gap_r[found], closed)
    lag, corr = av_offset(np.where(found, gap_g, np.nan), np.where(found, gap_r, np.nan))
    jit_r = np.nanmean(jitter(real[found], lips) / iod[found][1:-1])
    jit_g = np.nanmean(jitter(gen[found], lips) / iod[found][1:-1])
    # lip-sync behaviour, generated and real alike, on the frames where both have a face
    gaps = {"": np.where(found, gap_g, np.nan), "_real": np.where(found, gap_r, np.nan)}
    bil, pauses, speech = (timing[k] & found for k in ("bilabial", "pauses", "speech"))
    lead = int(round(BILABIAL_LEAD_S * timing["fps"]))
    sync: dict = {"bilabial_frames": int(bil.sum()), "pause_frames": int(pauses.sum())}
    for suffix, g in gaps.items():
        sync[f"bilabial_closure_rate{suffix}"] = bilabial_closure_rate(g, bil, closed, lead)
        for k, v in pause_behaviour(g, pauses, speech, rest).items():
            sync[f"{k}{suffix}"] = v
    rate_r = sync["bilabial_closure_rate_real"]
    sync["bilabial_closure_ratio"] = sync["bilabial_closure_rate"] / rate_r if rate_r > 0 else float("nan")
    sync["opening_range_ratio"] = opening_range_ratio(gap_g[found], gap_r[found])
    return {
        "mouth_landmark_error_iod": float(np.nanmean(err[found])),
        **{k: float(v) for k, v in closure.items()},
        "av_offset_frames": int(lag),
        "opening_corr": corr,
        "mouth_jitter_ratio": float(jit_g / jit_r),
        **sync,
        "per_frame_error": err.tolist(),
    }


def mouth_box_summary(made: np.ndarray, real: np.ndarray) -> dict[str, float]:
    """Summary of per-frame mouth-box measurements ``(N, 7)`` (PSNR against the real frame, high-frequency
    and Laplacian energy, high-frequency agreement with the real frame, the high-frequency sums over
    :data:`nvp.image_metrics.MOUTH_REGIONS`; NaN rows where the real frame shows no face) of a re-creation
    and of the real frames: mean PSNR, the fine-detail energies pooled over the frames as ratios to the real
    ones (1.0 = as much fine detail as the footage; a mean of per-frame ratios would be pulled up by frames
    whose detail source is sharper than the frame), the same per region, and how much of that detail is the
    footage's, in place (:func:`nvp.image_metrics.detail_in_place`; a ratio counts specks and misplaced
    stubble as detail too)."""
    from nvp.image_metrics import MOUTH_REGIONS, detail_in_place

    ok = np.isfinite(made[:, 1]) & np.isfinite(real[:, 1])  # measured (PSNR may be inf: identical)
    regions = [f"hf_ratio_{name}" for name in MOUTH_REGIONS]
    if not ok.any():
        keys = ("psnr_mouth", "hf_ratio_mouth", "laplacian_ratio_mouth", "hf_in_place_mouth", *regions)
        return dict.fromkeys(keys, float("nan"))
    fin = ok & np.isfinite(made[:, 0])
    energy, ref = made[ok, 1:3].sum(0), real[ok, 1:3].sum(0)
    kept, there = made[ok, 4:].sum(0), real[ok, 4:].sum(0)
    return {
        "psnr_mouth": float(np.mean(made[fin, 0])) if fin.any() else float("inf"),
        "hf_ratio_mouth": float(energy[0] / ref[0]) if ref[0] > 0 else float("nan"),
        "laplacian_ratio_mouth": float(energy[1] / ref[1]) if ref[1] > 0 else float("nan"),
        "hf_in_place_mouth": detail_in_place(made[ok, 3], made[ok, 1], real[ok, 1]),
        **{
            key: float(k / r) if r > 0 else float("nan")
            for key, k, r in zip(regions, kept, there, strict=True)
        },
    }


DETAIL_SOURCES = 16
"""Held-out frames (evenly spread) that the re-creations take their fine detail from (see
:func:`detail_sources`; at most this many decoded frames are held)."""


def detail_sources(seq, indices: np.ndarray, count: int = DETAIL_SOURCES) -> np.ndarray:
    """For each held-out frame of ``indices`` ``(N,)``, the held-out frame its re-creation takes the
    footage's fine detail from: among ``count`` frames spread over ``indices``, the one with the nearest head
    pose at least a second away (the farthest when none is). A dub moves the detail of the footage frame it
    replaces; a re-creation moving its own real frame's detail back would be measured against itself."""
    candidates = indices[np.linspace(0, len(indices) - 1, min(count, len(indices))).round().astype(int)]
    rot = seq.rotation
    yaw = np.degrees(np.arctan2(rot[:, 0, 2], rot[:, 2, 2]))
    pitch = np.degrees(np.arctan2(-rot[:, 1, 2], rot[:, 2, 2]))
    out = np.empty(len(indices), np.int64)
    for j, t in enumerate(indices):
        gap = np.abs(candidates - t)
        far = candidates[gap >= seq.fps]
        if len(far) == 0:
            out[j] = candidates[np.argmax(gap)]
            continue
        out[j] = far[np.argmin(np.hypot(yaw[far] - yaw[t], pitch[far] - pitch[t]))]
    return out


def evaluate_video(
    video: str | Path, out_dir: str | Path, cfg: EvalConfig = EvalConfig(), progress: bool = True
) -> dict:
    """Run the protocol on ``video``; writes ``eval.json``, ``eval.md`` and ``eval.png`` into ``out_dir``."""
    from nvp.app.dub import dubbed_vertices
    from nvp.app.fit import FitConfig, fit
    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.image_metrics import (
        MOUTH_REGIONS,
        high_frequency_agreement,
        high_frequency_energy,
        high_frequency_sums,
        laplacian_energy,
        mouth_box,
        mouth_regions,
    )
    from nvp.media import VideoWriter, audio_rate, frames_at, iter_frames, probe_video, read_audio
    from nvp.metrics import psnr, ssim
    from nvp.person import PersonStyle, predict_expressions
    from nvp.provenance import synthetic_mark
    from nvp.tracked import TrackedSequence
    from renderer.crop import box_slices
    from renderer.loop import render_frames
    from renderer.register import registered, registration_offsets
    from renderer.render import FrameRenderer
    from tracking.landmarks import LandmarkDetector
    from tracking.track import track_video

    video, out = Path(video), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = probe_video(video)
    if not info.has_audio:
        raise MediaError(f"{video} has no audio track: nvp eval drives the held-out part from its audio")
    if not 0.3 <= cfg.train_fraction <= 0.95:
        raise NvpError(f"expected a train fraction between 0.3 and 0.95, found {cfg.train_fraction}")
    t0 = time.perf_counter()
    track_dir = out / "track"
    if (track_dir / "tracked.json").exists():
        seq = TrackedSequence.load(track_dir)
    else:
        seq, _ = track_video(video, progress=progress)
        seq.save(track_dir)
    split = int(round(seq.num_frames * cfg.train_fraction))
    n_test = seq.num_frames - split
    if n_test < seq.fps:
        raise NvpError(
            f"{video}: the held-out part is only {n_test} frames; use a longer video "
            "(at least 5 s; 1-3 minutes is best)"
        )
    train_clip = out / "train_part.mp4"
    if not train_clip.exists():
        _trim(video, train_clip, split, seq.fps)
    fcfg = FitConfig(
        cfg.preset, cfg.budget_minutes, cfg.steps, cfg.features, cfg.device, renderer_init=cfg.renderer_init
    )
    bundle = fit(train_clip, out / "person", fcfg, progress, tracked=seq.head(split))
    # the fit registered the training part to its renderer (renderer.register); the held-out part the same
    offsets = np.zeros((seq.num_frames, 2))
    offsets[split:] = registration_offsets(
        bundle.path("renderer"), video, seq, np.arange(split, seq.num_frames), cfg.device, progress
    )
    head = TrackedSequence.load(bundle.path("tracked"))
    model = default_face_model()
    seq = registered(seq, model, offsets)
    seq = replace(seq, translation=np.concatenate([head.translation, seq.translation[split:]]))
    t_fit = time.perf_counter() - t0

    style = PersonStyle.load(bundle.path("style"))
    net, _ = default_audio2exp(style.feature_kind)
    rate = audio_rate(video)
    audio = read_audio(video, rate)[int(round(split / seq.fps * rate)) :]
    expr_audio = predict_expressions(audio, rate, seq.fps, style, net, num_frames=n_test)
    timing = _speech_timing(audio, rate, seq.fps, n_test)

    kinds = ("real", "visual", "audio")
    marks = {k: np.full((n_test, 478, 2), np.nan) for k in kinds}
    img = {k: np.full((n_test, 4), np.nan) for k in ("visual", "audio")}  # psnr, ssim full; psnr, ssim crop
    # mouth box: PSNR, fine detail (high-frequency and Laplacian energy, agreement with the real frame,
    # high-frequency sums inside the real frame's inner lips, on its lips and on the skin around them)
    mouth = {k: np.full((n_test, 4 + len(MOUTH_REGIONS)), np.nan) for k in kinds}
    lips, inner_lips = model.landmark_groups["lips_outer"], model.landmark_groups["lips_inner"]
    detectors = {k: LandmarkDetector() for k in kinds}
    side = None
    if cfg.side_by_side:
        tags = synthetic_mark("eval-side-by-side", video=video.name)
        side = VideoWriter(out / "side_by_side.mp4", seq.fps, 3 * seq.width, seq.height, metadata=tags)
    weights = model.mouth_weights()

    def spoken(j: int, t: int, tracked: np.ndarray) -> np.ndarray:
        return dubbed_vertices(model, seq, t, expr_audio[j], weights, tracked)

    indices = np.arange(split, split + n_test)
    chosen = detail_sources(seq, indices)
    pool = dict(zip(np.unique(chosen).tolist(), frames_at(video, np.unique(chosen), seq.fps), strict=True))
    t_render, t_other = time.perf_counter(), 0.0  # render time = loop time - measuring time
    try:
        with FrameRenderer(bundle.path("renderer"), model, seq, cfg.device) as fr:
            frames = iter_frames(video, fps=seq.fps, start_frame=split, max_frames=n_test)
            variants = {"visual": None, "audio": spoken}
            tracked_at = {i: fr.tracked(i) for i in pool}

            def source(j: int) -> tuple[np.ndarray, int, np.ndarray]:
                i = int(chosen[j])
                return pool[i], i, tracked_at[i]

            made_frames = render_frames(fr, frames, indices, variants, progress, "eval", sources=source)
            for j, (frame, made) in enumerate(made_frames):
                t_measure = time.perf_counter()
                ys, xs = box_slices(fr.boxes[split + j], seq.height, seq.width)
                for k, m in made.items():
                    img[k][j] = [
                        psnr(frame, m),
                        ssim(frame, m),
                        psnr(frame[ys, xs], m[ys, xs]),
                        ssim(frame[ys, xs], m[ys, xs]),
                    ]
                for k, m in {"real": frame, **made}.items():
                    d = detectors[k].detect(m, j / seq.fps)
                    if d is not None:
                        marks[k][j] = d.points[:, :2]
                if np.isfinite(marks["real"][j, 0, 0]):  # the mouth box of the real frame
                    box = mouth_box(marks["real"][j][lips], frame.shape[:2])
                    regions = mouth_regions(marks["real"][j][lips], marks["real"][j][inner_lips], box)
                    y0, y1, x0, x1 = box
                    for k, m in {"real": frame, **made}.items():
                        sums = high_frequency_sums(m, box, regions)
                        mouth[k][j] = [
                            psnr(frame[y0:y1, x0:x1], m[y0:y1, x0:x1]),
                            high_frequency_energy(m, box),
                            laplacian_energy(m, box),
                            high_frequency_agreement(m, frame, box),
                            *(sums[name] for name in MOUTH_REGIONS),
                        ]
                if side is not None:
                    side.write(np.hstack([frame, made["visual"], made["audio"]]))
                t_other += time.perf_counter() - t_measure
        if side is not None:
            side.close()
    except BaseException:
        if side is not None:
            side.abort()
        raise
    finally:
        for d in detectors.values():
            d.close()
    t_render = time.perf_counter() - t_render - t_other

    has = {k: np.isfinite(marks[k][:, 0, 0]) for k in kinds}
    result = {
        "video": video.name,
        "frames": {
            "total": seq.num_frames,
            "train": split,
            "test": n_test,
            "real_faces_found": int(has["real"].sum()),
        },
        "config": asdict(cfg),
        "fit_minutes": round(t_fit / 60, 1),
        "render_fps": round(2 * n_test / t_render, 2),
        "syncnet": "skipped: no SyncNet weights ship with nvp (LSE-C / LSE-D need them)",
        "detail_source": "another held-out frame >= 1 s away, nearest head pose",
    }
    for k in ("visual", "audio"):
        found = has["real"] & has[k]
        if found.sum() >= 3:
            m = _lip_metrics(marks["real"], marks[k], found, model.landmark_groups, timing)
        else:  # mediapipe finds no face in the generated frames: a failed render, reported as such
            log.warning("%s: mediapipe found a face in only %d %s frames", video.name, found.sum(), k)
            m = {"mouth_landmark_error_iod": float("nan"), "per_frame_error": [float("nan")] * n_test}
        m["faces_found"] = int(found.sum())
        per_frame = m.pop("per_frame_error")
        fin = np.isfinite(img[k][:, 0])
        result[k] = {
            "psnr_full": float(np.mean(img[k][fin, 0])) if fin.any() else float("inf"),
            "ssim_full": float(np.mean(img[k][:, 1])),
            "psnr_crop": float(np.mean(img[k][fin, 2])) if fin.any() else float("inf"),
            "ssim_crop": float(np.mean(img[k][:, 3])),
            **mouth_box_summary(mouth[k], mouth["real"]),
            **m,
        }
        result[k]["_per_frame"] = {"psnr_crop": img[k][:, 2].tolist(), "mouth_error_iod": per_frame}
    _write_reports(result, out)
    return result


def _write_reports(result: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per = {k: result[k].pop("_per_frame") for k in ("visual", "audio")}
    (out / "eval.json").write_text(json.dumps({**result, "per_frame": per}, indent=2) + "\n")
    keys = list(dict.fromkeys([*result["visual"], *result["audio"]]))
    lines = [
        f"# nvp eval: {result['video']}",
        "",
        f"frames: {result['frames']}; fit {result['fit_minutes']} min; "
        f"render {result['render_fps']} frames/s; SyncNet {result['syncnet']}",
        "",
        "| metric | visually driven | audio driven |",
        "|---|---|---|",
    ]
    for k in keys:
        v, a = result["visual"].get(k, float("nan")), result["audio"].get(k, float("nan"))
        fmt = (lambda x: f"{x:.4f}") if isinstance(v, float) else str
        lines.append(f"| {k} | {fmt(v)} | {fmt(a)} |")
    (out / "eval.md").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for k in ("visual", "audio"):
        ax[0].plot(per[k]["psnr_crop"], label=k)
        ax[1].plot(per[k]["mouth_error_iod"], label=k)
    ax[0].set_ylabel("face-crop PSNR (dB)")
    ax[1].set_ylabel("mouth landmark error / IOD")
    ax[1].set_xlabel("held-out frame")
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(out / "eval.png", dpi=100)
    plt.close(fig)
