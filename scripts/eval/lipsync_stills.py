"""Stills of p / b / m frames: the real mouth next to two audio-driven predictions of it.

    python -m scripts.eval.lipsync_stills VIDEO [VIDEO ...] --before OLD.json --after NEW.json [--out DIR]
        [--before-opening-weight 0] [--after-opening-weight 0.75] [--before-opening OP.json]
        [--after-opening OP.json]

For each video of ``../shared/data/video`` the person's style is made from the first 80 % of the frames (as
``nvp fit`` does, ``nvp.person.style_from_sample``) with each network, the last 20 % is predicted from the
clip's own audio (``nvp.person.style_expressions`` with the voice activity), and for up to ``--frames``
held-out frames where the audio says p, b or m, a PNG shows the real frame's mouth three times: with the
tracked lips (green: real), with the lips of the prediction made by ``--before`` (red) and by ``--after``
(blue), each outline the model's outer and inner lip contour under the tracked head pose. ``--before-flat``
turns off the range calibration for the ``--before`` network (what nvp did before it existed); the
opening weights set how much of the generic opening model (``nvp.opening``) each side blends in (0: none),
``--before-opening`` / ``--after-opening`` which opening model (default: the shipped one).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from nvp.app.corpus import load_sample
from nvp.audio2exp import load_net
from nvp.audio_features import extract_features, phoneme_labels
from nvp.face_model import default_face_model
from nvp.geometry import posed
from nvp.media import frames_at, read_audio
from nvp.metrics import bilabial_classes, bilabial_frames
from nvp.opening import DEFAULT_PATH, OpeningModel
from nvp.person import OPENING_WEIGHT, RANGE_GAIN_MAX, VideoSample, style_expressions, style_from_sample
from nvp.vad import frame_speech_probability, voice_activity
from scripts.common import SHARED, data_missing

SR = 16000
COLOURS = {"real": (0, 200, 0), "before": (0, 0, 230), "after": (230, 80, 0)}  # BGR


def predictions(
    video: Path, cache: Path, nets: dict, flat: set[str], weights: dict[str, float], openings: dict
) -> tuple:
    s = load_sample(video, cache, "phonemes", progress=False)
    seq = s.tracked
    n = seq.num_frames
    split = int(round(0.8 * n))
    audio = read_audio(video, SR)
    voiced = frame_speech_probability(audio, SR, seq.fps, n) >= 0.5
    voice = voice_activity(audio, SR, seq.fps, n)
    model = default_face_model()
    out = {"real": seq.expression}
    for key, (net, manifest) in nets.items():
        opening = openings[key]
        opening_windows = load_sample(video, cache, opening.feature_kind, progress=False).windows
        part = VideoSample(
            video.name, s.windows[:split], seq.head(split), opening_windows=opening_windows[:split]
        )
        max_gain = 1.0 if key in flat else RANGE_GAIN_MAX
        style = style_from_sample(
            net,
            manifest,
            part,
            model,
            voiced=voiced[:split],
            max_gain=max_gain,
            opening=opening,
            opening_weight=weights[key],
        )
        out[key] = style_expressions(style, net, s.windows, voice, opening_windows=(opening_windows, seq.fps))
    post = extract_features(audio, SR, kind="phonemes")
    bil = bilabial_frames(post.values, bilabial_classes(phoneme_labels()), post.rate, seq.fps, n)
    bil[:split] = False
    return seq, model, out, bil & seq.valid


def still(frame: np.ndarray, seq, model, exprs: dict, t: int) -> np.ndarray:
    groups = model.landmark_groups
    lips = {k: groups[k] for k in ("lips_outer", "lips_inner")}
    real_px = seq.pixels(seq.camera_vertices(model, np.array([t]))[0])
    pts = real_px[np.concatenate(list(lips.values()))]
    (x0, y0), (x1, y1) = pts.min(0), pts.max(0)
    half = 0.9 * max(x1 - x0, y1 - y0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    box = [int(cx - half), int(cy - half), int(cx + half), int(cy + half)]
    panels = []
    for key, colour in COLOURS.items():
        img = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR).copy()
        v = model.vertices(seq.identity, exprs[key][t : t + 1])
        px = seq.pixels(posed(v, seq.rotation[t : t + 1], seq.translation[t : t + 1]))[0]
        for idx in lips.values():
            cv2.polylines(img, [np.round(px[idx]).astype(np.int32)], True, colour, 1, cv2.LINE_AA)
        pad = cv2.copyMakeBorder(img, 400, 400, 400, 400, cv2.BORDER_CONSTANT)
        crop = pad[box[1] + 400 : box[3] + 400, box[0] + 400 : box[2] + 400]
        crop = cv2.resize(crop, (256, 256), interpolation=cv2.INTER_CUBIC)
        cv2.putText(crop, key, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2, cv2.LINE_AA)
        panels.append(crop)
    return np.concatenate(panels, 1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("videos", nargs="+", help="file names in ../shared/data/video")
    ap.add_argument("--before", type=Path, required=True, help="network before (.json)")
    ap.add_argument("--before-flat", action="store_true", help="no range calibration for --before")
    ap.add_argument("--after", type=Path, required=True, help="network after (.json)")
    ap.add_argument("--before-opening-weight", type=float, default=0.0, help="opening model share, --before")
    ap.add_argument(
        "--after-opening-weight", type=float, default=OPENING_WEIGHT, help="opening model share, --after"
    )
    ap.add_argument("--before-opening", type=Path, default=DEFAULT_PATH, help="opening model, --before")
    ap.add_argument("--after-opening", type=Path, default=DEFAULT_PATH, help="opening model, --after")
    ap.add_argument("--frames", type=int, default=4, help="bilabial frames per video")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--out", type=Path, default=Path("out/lipsync_stills"))
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    nets = {"before": load_net(args.before), "after": load_net(args.after)}
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.videos:
        video = SHARED / "video" / name
        seq, model, exprs, bil = predictions(
            video,
            args.cache,
            nets,
            {"before"} if args.before_flat else set(),
            {"before": args.before_opening_weight, "after": args.after_opening_weight},
            {
                "before": OpeningModel.load(args.before_opening),
                "after": OpeningModel.load(args.after_opening),
            },
        )
        idx = np.flatnonzero(bil)
        pick = (
            idx[np.linspace(0, len(idx) - 1, min(args.frames, len(idx))).round().astype(int)]
            if len(idx)
            else []
        )
        rows = [
            still(f, seq, model, exprs, int(t))
            for t, f in zip(pick, frames_at(video, np.asarray(pick), seq.fps), strict=True)
        ]
        if rows:
            path = args.out / f"{Path(name).stem}.png"
            cv2.imwrite(str(path), np.concatenate(rows, 0))
            print(f"{path}: frames {list(map(int, pick))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
