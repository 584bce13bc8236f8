"""Lip-sync behaviour of audio → expressions on the held-out people of ``scripts/data_split.json``.

    python scripts/eval_lipsync.py [--set test] [--cache /tmp/nvp-cache] [--out out/eval_lipsync]

Per video of the chosen split (default: test, people never used for training or choosing anything): the
person map is solved on the first 80 % of the frames (as ``nvp.app.train_audio2exp.evaluate_person``), the
last 20 % is predicted from audio by the shipped phoneme network, and the tracked mesh's inner-lip gap of
the prediction is compared with the tracked gap of the real frames (expression level; nothing is rendered).
The predicted expressions blend towards the person's rest mouth where there is no voice, by one of three
gates: none (the network alone), the old loudness gate (``nvp.vad.energy_voice_activity``) and the voice
activity detector (``nvp.vad.voice_activity``, what ``nvp dub`` uses). The held-out audio is used clean and
with white noise mixed in at 10 and 0 dB SNR (noise level relative to the clean held-out speech's active
level); features and gates then see the noisy audio, while the truth (real mouth, bilabial frames, pauses)
comes from the real video and its clean audio.

Metrics (``nvp.metrics``), output next to the real video's own number where one exists:

- closure precision / recall / F1: frames whose gap is below the real video's closed level (``min + 0.15
  (p95 - min)`` of its tracked gap on the first 80 %);
- bilabial closure rate: frames where the clean audio says p, b or m (phoneme recogniser's posteriors of
  those phones summing to >= 0.5) with the mouth at or below the closed level at some frame from
  ``BILABIAL_LEAD_S`` (0.16 s) before to the frame (the recogniser marks the release); pooled
  over videos (closed bilabial frames / bilabial frames); the real video's rate is the target;
- opening correlation (predicted vs tracked gap) and opening range (p95 of the predicted gap / p95 real);
- pauses (runs >= 0.3 s of clean-audio frames with speech probability < 0.5): fraction of pause frames
  with the gap at or below the resting level (``min + 0.3 (p95 - min)``), pooled; and the mouth's motion
  in pauses relative to speech (mean |frame-to-frame change of the gap|, pauses / speech).

Tracking and features are cached under ``--cache`` (``nvp.app.corpus.load_sample``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from nvp.app.corpus import load_sample
from nvp.app.report import markdown_table
from nvp.audio2exp import audio_expressions, load_net, solve_person_map
from nvp.audio_features import extract_features, phoneme_labels, speaker_normalized
from nvp.face_model import default_face_model
from nvp.media import read_audio
from nvp.metrics import (
    BILABIAL_LEAD_S,
    bilabial_classes,
    bilabial_closure_rate,
    bilabial_frames,
    closed_level,
    closure_f1,
    opening_range_ratio,
    pause_behaviour,
    pause_mask,
)
from nvp.person import pause_expression, rest_expression
from nvp.vad import energy_voice_activity, frame_speech_probability, rms_envelope_db, voice_activity
from nvp.windows import frame_windows

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[1] / "shared" / "data"
ASSETS = HERE.parent / "nvp" / "assets"
SR = 16000
TRAIN_FRACTION = 0.8
GATES = {"none": None, "energy gate": energy_voice_activity, "VAD": voice_activity}
CONDITIONS = {"clean": None, "noise 10 dB": 10.0, "noise 0 dB": 0.0}


def active_power(audio: np.ndarray) -> float:
    """Mean power of the 20 ms blocks within 30 dB of the loud end (95th percentile)."""
    env = rms_envelope_db(audio, SR, 0.02)
    return float(np.mean(10 ** (env[env > np.percentile(env, 95) - 30] / 10)))


def evaluate_video(
    name: str, lang: str, person: str, args, net, model, labels_idx
) -> tuple[dict, list[dict]]:
    video = SHARED / "video" / name
    s = load_sample(video, args.cache, "phonemes", progress=False)
    seq = s.tracked
    fps, n = seq.fps, seq.num_frames
    split = int(round(n * TRAIN_FRACTION))
    valid = seq.valid
    tr = np.flatnonzero(valid[:split])
    te = np.arange(split, n)
    ok = valid[te]
    audio = read_audio(video, SR)

    gap_all = model.inner_lip_gap(seq.identity, seq.expression)
    closed, rest_lvl = closed_level(gap_all[tr]), closed_level(gap_all[tr], 0.3)
    lead = int(round(BILABIAL_LEAD_S * fps))
    gap_real = np.where(ok, gap_all[te], np.nan)
    pmap = solve_person_map(audio_expressions(net, s.windows)[tr], seq.expression[tr], 10.0)
    rest = rest_expression(seq.expression[tr], gap_all[tr])

    # truth from the clean audio: what is said (bilabials) and where the pauses are
    post = extract_features(audio, SR, kind="phonemes")
    bil = bilabial_frames(post.values, labels_idx, post.rate, fps, n)[te] & ok
    voiced = frame_speech_probability(audio, SR, fps, n) >= 0.5
    if not args.closed_rest:  # what nvp fit does: the person's mouth in the pauses of the fitting part
        in_pause = pause_expression(seq.expression[tr], voiced[tr], fps)
        rest = rest if in_pause is None else in_pause
    pauses, speech = pause_mask(voiced, fps, 0.3)[te] & ok, voiced[te] & ok
    real = {
        "video": name,
        "language": lang,
        "person": person,
        "test_frames": int(ok.sum()),
        "bilabial_frames": int(bil.sum()),
        "bilabial_closed": int(round(bilabial_closure_rate(gap_real, bil, closed, lead) * bil.sum()))
        if bil.any()
        else 0,
        "pause_frames": int(pauses.sum()),
        **{k: v for k, v in pause_behaviour(gap_real, pauses, speech, rest_lvl).items()},
        "pause_closed": int(np.sum(gap_real[pauses] <= rest_lvl)),
    }

    rows = []
    start = int(round(split / fps * SR))
    seed = int(hashlib.sha256(name.encode()).hexdigest()[:8], 16)
    for cond, snr in CONDITIONS.items():
        x = audio
        windows = s.windows
        if snr is not None:
            held = audio[start:]
            noise = np.random.default_rng(seed).standard_normal(len(held))
            noise *= np.sqrt(active_power(held) / 10 ** (snr / 10) / np.mean(noise**2))
            x = audio.copy()
            x[start:] = np.clip(held + noise, -1, 1)
            feats = speaker_normalized(extract_features(x, SR, kind="phonemes"))
            windows = frame_windows(feats, fps, num_frames=n).astype(np.float32)
        raw = pmap.apply(audio_expressions(net, windows)[te])
        for gate, fn in GATES.items():
            pred = raw
            if fn is not None:
                v = fn(x, SR, fps, n)[te, None]
                pred = rest + v * (raw - rest)
            gap = model.inner_lip_gap(seq.identity, pred)
            varies = gap[ok].std() > 1e-9 and gap_real[ok].std() > 1e-9
            rate = bilabial_closure_rate(gap, bil, closed, lead) if bil.any() else float("nan")
            pb = pause_behaviour(np.where(ok, gap, np.nan), pauses, speech, rest_lvl)
            rows.append(
                {
                    "video": name,
                    "language": lang,
                    "person": person,
                    "condition": cond,
                    "gate": gate,
                    **closure_f1(gap[ok], gap_real[ok], closed),
                    "opening_corr": float(np.corrcoef(gap[ok], gap_real[ok])[0, 1]) if varies else 0.0,
                    "opening_range_ratio": opening_range_ratio(gap[ok], gap_real[ok]),
                    "bilabial_closed": int(round(rate * bil.sum())) if bil.any() else 0,
                    "pause_closed": int(np.sum(gap[pauses] <= rest_lvl)),
                    "pause_motion_ratio": pb["pause_motion_ratio"],
                }
            )
    return real, rows


def _f(x: float, digits: int = 3) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.{digits}f}"


def summarise(reals: list[dict], rows: list[dict], key) -> list[dict]:
    """Rows per (group, condition, gate): pooled bilabial and pause rates, means over videos otherwise."""
    real_by = {r["video"]: r for r in reals}
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(key(r), r["condition"], r["gate"])].append(r)
    out = []
    for (g, cond, gate), sel in groups.items():
        rl = [real_by[r["video"]] for r in sel]
        bil = sum(r["bilabial_frames"] for r in rl)
        pf = sum(r["pause_frames"] for r in rl)
        b_out = sum(r["bilabial_closed"] for r in sel) / bil if bil else float("nan")
        b_real = sum(r["bilabial_closed"] for r in rl) / bil if bil else float("nan")
        p_out = sum(r["pause_closed"] for r in sel) / pf if pf else float("nan")
        p_real = sum(r["pause_closed"] for r in rl) / pf if pf else float("nan")
        mot_out = np.nanmean([r["pause_motion_ratio"] for r in sel]) if pf else float("nan")
        mot_real = np.nanmean([r["pause_motion_ratio"] for r in rl]) if pf else float("nan")
        out.append(
            {
                "group": g,
                "condition": cond,
                "gate": gate,
                "videos": len(sel),
                "closure P": _f(np.mean([r["closure_precision"] for r in sel])),
                "closure R": _f(np.mean([r["closure_recall"] for r in sel])),
                "closure F1": _f(np.mean([r["closure_f1"] for r in sel])),
                "bilabial closed (real)": f"{_f(b_out)} ({_f(b_real)})",
                "bilabial ratio": _f(b_out / b_real if b_real else float("nan"), 2),
                "opening corr": _f(np.mean([r["opening_corr"] for r in sel])),
                "opening range": _f(np.nanmean([r["opening_range_ratio"] for r in sel]), 2),
                "pause closed (real)": f"{_f(p_out)} ({_f(p_real)})",
                "pause motion (real)": f"{_f(mot_out, 2)} ({_f(mot_real, 2)})",
                "bilabial / pause frames": f"{bil} / {pf}",
            }
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", type=Path, default=HERE / "data_split.json")
    ap.add_argument("--set", default="test", choices=["test", "validation", "train"])
    ap.add_argument("--net", type=Path, default=ASSETS / "audio2exp_phonemes.json")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--out", type=Path, default=Path("out/eval_lipsync"))
    ap.add_argument("--videos", nargs="*", help="only these clips of the set")
    ap.add_argument(
        "--closed-rest", action="store_true", help="rest = most closed mouth (before: the mouth in pauses)"
    )
    args = ap.parse_args(argv)
    if not SHARED.is_dir():
        print(f"no evaluation data: {SHARED} does not exist")
        return 0
    split = json.loads(args.split.read_text())
    who = {c: (p, v["language"]) for p, v in split["people"].items() for c in v["clips"]}
    names = [c for c in split[args.set] if not args.videos or c in args.videos]
    model = default_face_model()
    net, manifest = load_net(args.net)
    trained_on = set(manifest["split"]["train"]) | set(manifest["split"]["validation"])
    if args.set == "test" and trained_on & set(names):
        raise SystemExit(f"test clips used by the network: {sorted(trained_on & set(names))}")
    labels_idx = bilabial_classes(phoneme_labels())
    args.out.mkdir(parents=True, exist_ok=True)
    reals, rows = [], []
    t0 = time.perf_counter()
    for i, name in enumerate(names):
        person, lang = who[name]
        real, r = evaluate_video(name, lang, person, args, net, model, labels_idx)
        reals.append(real)
        rows += r
        print(
            f"[{i + 1}/{len(names)}] {name}: {real['test_frames']} frames ({time.perf_counter() - t0:.0f} s)"
        )

    overall = summarise(reals, rows, key=lambda r: f"all {args.set}")
    per_lang = summarise(reals, [r for r in rows if r["condition"] == "clean"], key=lambda r: r["language"])
    per_lang.sort(key=lambda r: (r["group"], r["gate"]))
    per_video = summarise(
        reals,
        [r for r in rows if r["condition"] == "clean" and r["gate"] != "none"],
        key=lambda r: r["video"],
    )
    per_video.sort(key=lambda r: (r["group"], r["gate"]))
    cols = list(overall[0])
    people = len({r["person"] for r in reals})
    text = (
        f"## Lip sync on the {args.set} split: {len(names)} videos, {people} people, "
        f"{sum(r['test_frames'] for r in reals)} held-out frames\n\n"
        "Network: " + args.net.name + f" (sha256 {manifest['sha256'][:12]}). Person map on the first 80 %, "
        "last 20 % predicted. Rates in parentheses: the real video's (the target).\n\n"
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
