"""Lip-sync behaviour of audio → expressions on the held-out people of ``scripts/data_split.json``.

    python -m scripts.eval.lipsync [--set test] [--cache /tmp/nvp-cache] [--out out/eval_lipsync]

Per video of the chosen split (default: test, people never used for training or choosing anything), in
``--folds`` (default 5) consecutive parts: each part is predicted from a style made on all the other frames
exactly as ``nvp fit`` makes it (``nvp.person.style_from_sample`` with the voice activity of those frames), so
every frame is held out once (``--folds 1``: the style from the first 80 %, the last 20 % predicted, as
``nvp eval`` does; on clips of 4-13 s that is 1-3 s of speech, and the clip's leading silence is always on the
fitting side). The prediction is made as ``nvp dub`` makes it (``nvp.person.apply_style``: network, person
map, closures, voice activity of ``nvp.vad.voice_activity``; the opening model ``nvp.opening`` blended in with
``--opening-weight``, 0 for none, and deciding the closures; without it the closure head does), and the
tracked mesh's inner-lip gap of the prediction is compared with the tracked gap of the real frames
(expression level; nothing is rendered).

The held-out audio is used clean and with white noise mixed in at 10 and 0 dB SNR (noise level relative to the
clean held-out speech's active level); features and voice activity then see the noisy audio, while the truth
(real mouth, bilabial frames, pauses) comes from the real video and its clean audio.

Metrics (``nvp.metrics``), output next to the real video's own number where one exists:

- closure precision / recall / F1: frames whose gap is below the real video's closed level (``min + 0.15
  (p95 - min)`` of its tracked gap on the whole clip; with ``--folds 1``, on the first 80 %);
- bilabial closure rate: frames where the clean audio says p, b or m (phoneme recogniser's posteriors of
  those phones summing to >= 0.5) with the mouth at or below the closed level at some frame from
  ``BILABIAL_LEAD_S`` (0.16 s) before to the frame (the recogniser marks the release); pooled
  over videos (closed bilabial frames / bilabial frames); the real video's rate is the target;
- opening correlation (predicted vs tracked gap) and opening range (p95 of the predicted gap / p95 real);
- pauses (runs >= 0.3 s of clean-audio frames with speech probability < 0.5): fraction of pause frames
  with the gap at or below the resting level (``min + 0.3 (p95 - min)``), pooled; the fraction of pause
  frames where the mouth rests (within 5 % of the real p95 gap of the person's rest mouth, or below the
  resting level); and the mouth's motion in pauses relative to speech (mean |frame-to-frame change of the
  gap|, pauses / speech);
- lip rounding: correlation of the output's mouth width (corners 61-291) with the real one, and the median
  width on frames where the recogniser hears a rounded vowel (``nvp.rounding.ROUNDED_PHONES``) over that on
  spread vowels (``SPREAD_PHONES``), mean over videos, the real video's in parentheses; and the share of
  rounded-vowel frames with the mouth at or below the closed level (pooled; rounded lips are parted);
- jitter ratio (mean |second difference| of the gap, output / real) and the audio-visual offset in frames
  (``nvp.metrics.av_offset`` of the two gaps within ``RESYNC_MAX_LAG``; positive: the output is late), median
  over videos; the synced correlation is the opening correlation at that offset (the shape of the opening
  whatever the footage's own sync: some test clips are 4-12 frames out of sync with their audio).

Tracking and features are cached under ``--cache`` (``nvp.app.corpus.load_sample``).

``--joined``: the clips are 3-60 s, most under 10 s, while ``nvp fit`` is meant for 1-3 minutes of footage
(and corrects the opening model on footage of 16 s or more, ``nvp.opening.adapted_opening_model``).
Instead of single clips, each person of the set with several clips of one size and frame rate is evaluated
on their clips joined one after another (written once under ``--cache``/joined), cut into folds as a single
clip is.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from collections import defaultdict
from itertools import pairwise
from pathlib import Path

import numpy as np

from nvp.app.corpus import load_sample
from nvp.app.report import markdown_table
from nvp.audio2exp import load_net
from nvp.audio_features import extract_features, phoneme_labels, recogniser_features
from nvp.face_model import default_face_model
from nvp.media import read_audio
from nvp.metrics import (
    BILABIAL_LEAD_S,
    av_offset,
    bilabial_classes,
    bilabial_closure_rate,
    bilabial_frames,
    closed_level,
    closure_f1,
    opening_range_ratio,
    pause_behaviour,
    pause_mask,
)
from nvp.opening import OpeningModel
from nvp.person import (
    CLOSURE_RAMP,
    OPENING_WEIGHT,
    PAUSE_TIMING_MIN_FRAMES,
    RANGE_GAIN_MAX,
    VideoSample,
    style_expressions,
    style_from_sample,
)
from nvp.rounding import rounded_classes
from nvp.vad import frame_speech_probability, voice_activity, with_white_noise
from nvp.windows import frame_windows
from scripts.common import ROOT, SHARED, SPLIT, data_missing

ASSETS = ROOT / "nvp" / "assets"
SR = 16000
TRAIN_FRACTION = 0.8
CONDITIONS = {"clean": None, "noise 10 dB": 10.0, "noise 0 dB": 0.0}


def joined_footage(clips: list[Path], out: Path) -> Path | None:
    """``clips`` of one person one after another as one video ``out`` (made once), None when their frame
    sizes or rates differ. Each clip's audio is cut or padded to its frames, so sound and picture stay in
    step across the joins."""
    from nvp.media import VideoWriter, audio_rate, iter_frames, probe_video

    infos = [probe_video(c) for c in clips]
    if len({(i.width, i.height, float(i.fps)) for i in infos}) != 1:
        return None
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    rate, fps = audio_rate(clips[0]), float(infos[0].fps)
    frames = [list(iter_frames(c, fps=fps)) for c in clips]
    sound = [read_audio(c, rate) for c in clips]
    audio = np.concatenate(
        [
            np.pad(a, (0, max(0, round(len(f) / fps * rate) - len(a))))[: round(len(f) / fps * rate)]
            for a, f in zip(sound, frames, strict=True)
        ]
    )
    with VideoWriter(out, fps, infos[0].width, infos[0].height, audio=audio, audio_rate=rate, crf=14) as w:
        for clip in frames:
            for f in clip:
                w.write(f)
    return out


def fold_parts(n: int, folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(fit, held_out)`` frame indices per fold: with one fold the first ``TRAIN_FRACTION`` of the frames
    make the style and the rest is predicted (``nvp eval``'s protocol); with ``folds`` > 1 the clip is cut
    into that many consecutive parts and each is predicted from a style made on all the others, so every
    frame is held out once and no part of the clip (its leading silence, say) is always on the fitting
    side."""
    if folds == 1:
        split = int(round(n * TRAIN_FRACTION))
        return [(np.arange(split), np.arange(split, n))]
    bounds = np.round(np.linspace(0, n, folds + 1)).astype(int)
    frames = np.arange(n)
    return [(np.setdiff1d(frames, frames[a:b]), frames[a:b]) for a, b in pairwise(bounds)]


RESYNC_MAX_LAG = 12
"""Frames (about 0.5 s) the output may be shifted against the footage for the synced correlation: some test
clips (TV drama, film) are themselves 4-12 frames out of sync with their audio, see
docs/experiments/audio-features.md."""


def synced(gap: np.ndarray, gap_real: np.ndarray, varies: bool) -> tuple[int, float]:
    """``(lag, correlation)``: the shift of the output's gap ``(T,)`` (NaN outside the held-out frames) that
    best matches the real gap, within :data:`RESYNC_MAX_LAG`, and the correlation there; the same for every
    clip and language, so it measures how well the opening's shape follows the footage whatever the
    footage's own audio-visual offset (the lag itself is reported as the AV offset)."""
    if not varies:
        return 0, 0.0
    return av_offset(gap, gap_real, RESYNC_MAX_LAG)


SPREAD_PHONES = ("a", "aɪ", "e", "eɪ", "i", "ɛ", "ɪ", "æ", "ɐ", "ɑ", "ä", "à", "ì", "ĩ", "ẽ", "ã", "ja", "je")
"""Vowels said with spread or neutral lips (the recogniser's IPA set), the reference for rounding."""


def spread_classes() -> np.ndarray:
    return np.array([i for i, label in enumerate(phoneme_labels()) if label in SPREAD_PHONES])


def rounded_narrowing(width: np.ndarray, rounded: np.ndarray, spread: np.ndarray) -> float:
    """Median mouth width on rounded-vowel frames over that on spread-vowel frames (NaN with fewer than 3
    of either): below 1 where the lips round."""
    if rounded.sum() < 3 or spread.sum() < 3:
        return float("nan")
    return float(np.median(width[rounded]) / np.median(width[spread]))


def evaluate_video(
    video: Path, lang: str, who_name: str, args, net, manifest, opening, model, labels_idx
) -> tuple[dict, list[dict]]:
    name = video.name
    s = load_sample(video, args.cache, "phonemes", progress=False)
    kind = opening.feature_kind
    opening_windows = load_sample(video, args.cache, kind, progress=False).windows
    seq = s.tracked
    fps, n = seq.fps, seq.num_frames
    parts = fold_parts(n, args.folds)
    held = np.zeros(n, bool)
    for _, te in parts:
        held[te] = True
    valid = seq.valid
    fitting = np.zeros(n, bool)  # the frames whose real gap sets the closed levels
    fitting[parts[0][0] if args.folds == 1 else np.arange(n)] = True
    tr = np.flatnonzero(valid & fitting)
    ok = valid & held
    audio = read_audio(video, SR)

    gap_all = model.inner_lip_gap(seq.identity, seq.expression)
    closed, rest_lvl = closed_level(gap_all[tr]), closed_level(gap_all[tr], 0.3)
    lead = int(round(BILABIAL_LEAD_S * fps))
    gap_real = np.where(ok, gap_all, np.nan)

    # truth from the clean audio: what is said (bilabials) and where the pauses are
    post = extract_features(audio, SR, kind="phonemes")
    bil = bilabial_frames(post.values, labels_idx, post.rate, fps, n) & ok
    rounded = bilabial_frames(post.values, rounded_classes(), post.rate, fps, n) & ok
    spread = bilabial_frames(post.values, spread_classes(), post.rate, fps, n) & ok
    width_real = model.mouth_width(seq.identity, seq.expression)
    voiced = frame_speech_probability(audio, SR, fps, n) >= 0.5
    # each fold's style from its fitting frames, as nvp fit makes it from footage
    styles, rest_gap = [], np.zeros(n)
    for fit, te in parts:
        fit_part = VideoSample(name, s.windows[fit], seq.frames(fit), opening_windows=opening_windows[fit])
        style = style_from_sample(
            net,
            manifest,
            fit_part,
            model,
            voiced=voiced[fit],
            max_gain=args.range_gain_max,
            opening=opening,
            opening_weight=args.opening_weight,
            pause_timing_min_frames=args.pause_timing_min_frames,
        )
        styles.append(style)
        rest_gap[te] = float(model.inner_lip_gap(seq.identity, style.rest_expression[None])[0])
    rest_tol = 0.05 * float(np.nanpercentile(gap_all[tr], 95))
    pauses, speech = pause_mask(voiced, fps, 0.3) & ok, voiced & ok

    def resting(gap: np.ndarray) -> int:
        return int(np.sum(((gap <= rest_lvl) | (np.abs(gap - rest_gap) <= rest_tol))[pauses]))

    real = {
        "video": name,
        "language": lang,
        "person": who_name,
        "test_frames": int(ok.sum()),
        "bilabial_frames": int(bil.sum()),
        "bilabial_closed": int(round(bilabial_closure_rate(gap_real, bil, closed, lead) * bil.sum()))
        if bil.any()
        else 0,
        "pause_frames": int(pauses.sum()),
        **{k: v for k, v in pause_behaviour(gap_real, pauses, speech, rest_lvl).items()},
        "pause_closed": int(np.sum(gap_real[pauses] <= rest_lvl)),
        "pause_resting": resting(gap_real),
        "rounded_width": rounded_narrowing(width_real, rounded, spread),
        "rounded_frames": int(rounded.sum()),
        "rounded_closed": int(np.sum(gap_real[rounded] <= closed)),
    }

    rows = []
    start = int(round(parts[0][1][0] / fps * SR)) if args.folds == 1 else 0  # noise over what is predicted
    seed = int(hashlib.sha256(name.encode()).hexdigest()[:8], 16)
    for cond, snr in CONDITIONS.items():
        x, windows, ow = audio, s.windows, opening_windows
        if snr is not None:
            x = audio.copy()
            x[start:] = with_white_noise(audio[start:], SR, snr, seed)
            feats, phonetic = recogniser_features(x, SR)
            of = phonetic if kind == "phonetic" else extract_features(x, SR, kind=kind)
            windows = frame_windows(feats, fps, num_frames=n).astype(np.float32)
            ow = frame_windows(of, fps, num_frames=n).astype(np.float32)
        voice = voice_activity(x, SR, fps, n)
        gap, width = np.full(n, np.nan), np.full(n, np.nan)
        for style, (_, te) in zip(styles, parts, strict=True):
            pred = style_expressions(style, net, windows, voice, args.closure_ramp, (ow, fps), opening)
            gap[te] = model.inner_lip_gap(seq.identity, pred[te])
            width[te] = model.mouth_width(seq.identity, pred[te])
        varies = gap[ok].std() > 1e-9 and gap_real[ok].std() > 1e-9
        rate = bilabial_closure_rate(gap, bil, closed, lead) if bil.any() else float("nan")
        pb = pause_behaviour(np.where(ok, gap, np.nan), pauses, speech, rest_lvl)
        d2 = np.abs(np.diff(gap_real[ok], 2)).mean()
        lag, corr_at_lag = synced(np.where(ok, gap, np.nan), gap_real, varies)
        rows.append(
            {
                "video": name,
                "language": lang,
                "person": who_name,
                "condition": cond,
                **closure_f1(gap[ok], gap_real[ok], closed),
                "opening_corr": float(np.corrcoef(gap[ok], gap_real[ok])[0, 1]) if varies else 0.0,
                "opening_range_ratio": opening_range_ratio(gap[ok], gap_real[ok]),
                "jitter_ratio": float(np.abs(np.diff(gap[ok], 2)).mean() / d2) if d2 > 0 else float("nan"),
                "av_offset": lag,
                "opening_corr_synced": corr_at_lag,
                "bilabial_closed": int(round(rate * bil.sum())) if bil.any() else 0,
                "pause_closed": int(np.sum(gap[pauses] <= rest_lvl)),
                "pause_resting": resting(gap),
                "pause_motion_ratio": pb["pause_motion_ratio"],
                "width_corr": float(np.corrcoef(width[ok], width_real[ok])[0, 1]) if varies else 0.0,
                "rounded_width": rounded_narrowing(width, rounded, spread),
                "rounded_closed": int(np.sum(gap[rounded] <= closed)),
            }
        )
    return real, rows


def _f(x: float, digits: int = 3) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.{digits}f}"


def pooled(rows: list[dict], key: str, total: int) -> float:
    return sum(r[key] for r in rows) / total if total else float("nan")


def _both(out: list[dict], real: list[dict], key: str, total: int) -> str:
    """Pooled rate of the output rows, then of the real rows in parentheses."""
    return f"{_f(pooled(out, key, total))} ({_f(pooled(real, key, total))})"


def summarise(reals: list[dict], rows: list[dict], key) -> list[dict]:
    """Rows per (group, condition): pooled bilabial and pause rates, means over videos otherwise."""
    real_by = {r["video"]: r for r in reals}
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(key(r), r["condition"])].append(r)
    out = []
    for (g, cond), sel in groups.items():
        rl = [real_by[r["video"]] for r in sel]
        bil = sum(r["bilabial_frames"] for r in rl)
        pf = sum(r["pause_frames"] for r in rl)
        rf = sum(r["rounded_frames"] for r in rl)

        b_out, b_real = pooled(sel, "bilabial_closed", bil), pooled(rl, "bilabial_closed", bil)
        mot_out = np.nanmean([r["pause_motion_ratio"] for r in sel]) if pf else float("nan")
        mot_real = np.nanmean([r["pause_motion_ratio"] for r in rl]) if pf else float("nan")
        out.append(
            {
                "group": g,
                "condition": cond,
                "videos": len(sel),
                "closure P": _f(np.mean([r["closure_precision"] for r in sel])),
                "closure R": _f(np.mean([r["closure_recall"] for r in sel])),
                "closure F1": _f(np.mean([r["closure_f1"] for r in sel])),
                "bilabial closed (real)": f"{_f(b_out)} ({_f(b_real)})",
                "bilabial ratio": _f(b_out / b_real if b_real else float("nan"), 2),
                "opening corr": _f(np.mean([r["opening_corr"] for r in sel])),
                "synced corr": _f(np.mean([r["opening_corr_synced"] for r in sel])),
                "opening range": _f(np.nanmean([r["opening_range_ratio"] for r in sel]), 2),
                "jitter ratio": _f(np.nanmean([r["jitter_ratio"] for r in sel]), 2),
                "AV offset (median)": f"{np.median([r['av_offset'] for r in sel]):+.0f}",
                "pause closed (real)": _both(sel, rl, "pause_closed", pf),
                "pause resting (real)": _both(sel, rl, "pause_resting", pf),
                "pause motion (real)": f"{_f(mot_out, 2)} ({_f(mot_real, 2)})",
                "width corr": _f(np.mean([r["width_corr"] for r in sel])),
                "rounded width (real)": f"{_f(np.nanmean([r['rounded_width'] for r in sel]))} "
                f"({_f(np.nanmean([r['rounded_width'] for r in rl]))})",
                "rounded closed (real)": _both(sel, rl, "rounded_closed", rf),
                "bilabial / pause / rounded frames": f"{bil} / {pf} / {rf}",
            }
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", type=Path, default=SPLIT)
    ap.add_argument("--set", default="test", choices=["test", "validation", "train"])
    ap.add_argument("--net", type=Path, default=ASSETS / "audio2exp_phonemes.json")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--out", type=Path, default=Path("out/eval_lipsync"))
    ap.add_argument("--videos", nargs="*", help="only these clips of the set")
    ap.add_argument("--joined", action="store_true", help="each person's clips joined into one footage")
    ap.add_argument(
        "--folds",
        type=int,
        default=5,
        help="consecutive parts of each clip, each predicted from a style made on the others (1: the first "
        "80 %% makes the style, the last 20 %% is predicted)",
    )
    ap.add_argument(
        "--closure-ramp",
        type=float,
        nargs=2,
        default=CLOSURE_RAMP,
        metavar=("LO", "HI"),
        help="closure probabilities mapped to weights 0 … 1 (choose it on the validation set, never on test)",
    )
    ap.add_argument(
        "--range-gain-max", type=float, default=RANGE_GAIN_MAX, help="widest person-map gain (1: no widening)"
    )
    ap.add_argument("--opening", type=Path, default=ASSETS / "opening_whisper.json", help="opening model")
    ap.add_argument(
        "--pause-timing-min-frames",
        type=int,
        default=PAUSE_TIMING_MIN_FRAMES,
        help="pause frames from which the footage decides when the lips rest in a pause",
    )
    ap.add_argument(
        "--opening-weight",
        type=float,
        default=OPENING_WEIGHT,
        help="share of the opening model in the mouth opening (0: the person map alone)",
    )
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    split = json.loads(args.split.read_text())
    who = {c: (p, v["language"]) for p, v in split["people"].items() for c in v["clips"]}
    names = [c for c in split[args.set] if not args.videos or c in args.videos]
    videos = {c: SHARED / "video" / c for c in names}
    model = default_face_model()
    net, manifest = load_net(args.net)
    opening = OpeningModel.load(args.opening)
    trained_on = set(manifest["split"]["train"]) | set(manifest["split"]["validation"])
    trained_on |= set(opening.info["split"]["train"]) | set(opening.info["split"]["validation"])
    if args.set == "test" and trained_on & set(names):
        raise SystemExit(f"test clips used by the network: {sorted(trained_on & set(names))}")
    labels_idx = bilabial_classes(phoneme_labels())
    args.out.mkdir(parents=True, exist_ok=True)
    if args.joined:  # people with several clips, each as one footage of their clips
        videos = {}
        for person, v in split["people"].items():
            clips = [c for c in v["clips"] if c in names]
            joined = None
            if len(clips) > 1:
                target = args.cache / "joined" / f"{person}.mp4"
                joined = joined_footage([SHARED / "video" / c for c in clips], target)
            if joined is not None:
                videos[joined.name] = joined
                who[joined.name] = (person, v["language"])
        names = sorted(videos)
    if not names:
        joined = " (people with several clips)" if args.joined else ""
        raise SystemExit(f"no videos to evaluate in the {args.set} split{joined}")
    reals, rows = [], []
    t0 = time.perf_counter()
    for i, name in enumerate(names):
        who_name, lang = who[name]
        real, r = evaluate_video(
            videos[name], lang, who_name, args, net, manifest, opening, model, labels_idx
        )
        reals.append(real)
        rows += r
        print(
            f"[{i + 1}/{len(names)}] {name}: {real['test_frames']} frames ({time.perf_counter() - t0:.0f} s)"
        )

    overall = summarise(reals, rows, key=lambda r: f"all {args.set}")
    per_lang = summarise(reals, [r for r in rows if r["condition"] == "clean"], key=lambda r: r["language"])
    per_lang.sort(key=lambda r: r["group"])
    per_video = summarise(reals, [r for r in rows if r["condition"] == "clean"], key=lambda r: r["video"])
    per_video.sort(key=lambda r: r["group"])
    cols = list(overall[0])
    people = len({r["person"] for r in reals})
    text = (
        f"## Lip sync on the {args.set} split: {len(names)} videos, {people} people, "
        f"{sum(r['test_frames'] for r in reals)} held-out frames\n\n"
        "Network: " + args.net.name + f" (sha256 {manifest['sha256'][:12]}); opening model "
        f"{args.opening.name} at weight {args.opening_weight}. "
        + (
            "Person map on the first 80 %, last 20 % predicted. "
            if args.folds == 1
            else f"{args.folds} folds: each part predicted from a style made on the others. "
        )
        + "Rates in parentheses: the real video's (the target).\n\n"
        + markdown_table(overall, cols)
        + "\n### Per language (clean audio)\n\n"
        + markdown_table(per_lang, cols)
        + "\n### Per video (clean audio)\n\n"
        + markdown_table(per_video, cols)
    )
    (args.out / "results.md").write_text(text)
    (args.out / "results.json").write_text(
        json.dumps({"set": args.set, "real": reals, "rows": rows}, indent=1, default=float) + "\n"
    )
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
