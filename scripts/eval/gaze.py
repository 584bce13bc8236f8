"""Eye contact (issue 50): do ``nvp dub --gaze`` eyes look where asked, and do they still look like the
footage's?

    python -m scripts.eval.gaze [--videos V ...] [--cache /tmp/nvp-cache] [--out out/eval_gaze]

For each video (default: one clip of each of ten test people of ``scripts/data_split.json``), every frame of
the footage has its eyes turned as ``nvp dub`` turns them (:func:`renderer.eyes.eye_moves`,
:func:`renderer.eyes.move_eyes`: the dub's eye region is the footage's, since the networks paint the lower
face only) for two requests: into the lens (``--gaze camera``) and 10 degrees to the face's left and 5 up
(a gaze file's ``10,5``). The output frames are read again by a fresh mediapipe landmarker, and the
gaze measured from its iris landmarks the way tracking measures it (:func:`nvp.gaze.gaze_from_iris`, the
tracked head's eyeballs) is compared with the request: the angle between them per eye, over the frames
whose eyes are open enough to move all the way: per eye, and of the two eyes' mean direction (the way
gaze trackers report it: the two eyes' errors partly cancel).

Beside it, the measurement's own error on real footage: the footage's gaze against the lens (news anchors
reading a teleprompter look into it to within a few degrees, so for them this bounds the measurement's
error from above), and the angle between the two eyes' directions in the footage (both look at the same
point, over a metre away: under 2 degrees apart; what the measurement adds is its noise).

Picture: in an eye box (the opening's bounding box grown by half its width) and inside the opening, the
output's high-frequency energy over the footage's; the gradient ratio in the band around the opening's
outline (:func:`nvp.image_metrics.seam_gradient_ratio`); crops of open, blinking and far-turned frames.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from nvp.app.corpus import tracked_cached
from nvp.app.report import markdown_table
from nvp.face_model import default_face_model
from nvp.gaze import (
    angle_between,
    footage_gaze,
    gaze_angles,
    gaze_from_iris,
    gaze_vectors,
    iris_circles,
    towards_camera,
)
from nvp.image_metrics import high_frequency, high_frequency_energy, mouth_box, seam_gradient_ratio
from nvp.media import iter_frames
from renderer.eyes import OPEN_FULL, eye_moves, move_eyes, openness
from scripts.common import SPLIT, VIDEOS, data_missing

ASIDE = np.radians([10.0, 5.0])
"""The second request: yaw 10 degrees to the face's left, pitch 5 degrees up (face frame)."""


def default_videos() -> list[str]:
    """One clip of each of the first ten test people (sorted by person) with a clip of 5 s or more."""
    split = json.loads(SPLIT.read_text())
    clips = []
    for _, v in sorted(split["people"].items()):
        test = [c for c in v["clips"] if c in split["test"]]
        if test:
            clips.append(test[0])
    return clips[:10]


def eye_box(outline: np.ndarray, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The eye box: the opening's bounding box grown by half its width (the mouth box's rule)."""
    return mouth_box(outline, shape, grow=0.5)


def evaluate(video: Path, cache: Path, out: Path, crops: bool = True) -> dict:
    from tracking.landmarks import LandmarkDetector

    model = default_face_model()
    seq = tracked_cached(video, cache, progress=False)
    centres, footage = footage_gaze(model, seq)
    lens = towards_camera(centres)
    aside = np.einsum("tij,j->ti", seq.rotation, gaze_vectors(ASIDE))[:, None].repeat(2, 1)
    requests = {"camera": lens, "aside": aside}
    groups = [model.landmark_groups[g] for g in ("left_eye", "right_eye")]
    kinds = ("err", "both", "short", "hf_box", "hf_open", "seam")
    rows = {k: {**{kind: [] for kind in kinds}, "by_frame": {}} for k in requests}
    full_open = []
    detectors = {k: LandmarkDetector() for k in requests}
    saved = {}
    try:
        for k, frame in enumerate(iter_frames(video, seq.fps)):
            if k >= seq.num_frames:
                break
            t = k / seq.fps
            outlines = [seq.landmarks[k, g] for g in groups]
            opened = np.isfinite(seq.iris[k]).all() and all(
                openness(o, r) >= OPEN_FULL for o, r in zip(outlines, seq.iris[k, :, 2], strict=True)
            )
            full_open.append(opened)
            for name, wanted in requests.items():
                moves = eye_moves(model, seq, k, wanted[k], centres[k])
                made, weight = move_eyes(frame, moves, with_weight=True)
                seen = detectors[name].detect(made, t)
                if seen is None or not opened:
                    continue
                measured = gaze_from_iris(centres[k], iris_circles(seen.points)[:, :2], seq.focal, seq.center)
                r = rows[name]
                r["err"].append(angle_between(measured, wanted[k]))
                r["both"].append(angle_between(measured.mean(0), wanted[k].mean(0)))  # the two eyes' mean
                r["by_frame"][k] = measured.mean(0)
                # how much of the asked turn the measurement sees, in yaw and pitch (face frame)
                face = [gaze_angles(x @ seq.rotation[k]) for x in (footage[k], wanted[k], measured)]
                r["short"].append(np.degrees((face[1] - face[2]).mean(0)))
                for o in outlines:
                    box = eye_box(o, frame.shape[:2])
                    r["hf_box"].append(high_frequency_energy(made, box) / high_frequency_energy(frame, box))
                    inside = weight[box[0] : box[1], box[2] : box[3]] > 0.5
                    hf = [(high_frequency(x, box)[inside] ** 2).sum() for x in (made, frame)]
                    r["hf_open"].append(hf[0] / hf[1] if hf[1] > 0 else np.nan)
                r["seam"].append(seam_gradient_ratio(made, frame, weight))
                turn = float(angle_between(footage[k], wanted[k]).mean())
                if crops and name == "camera" and turn > saved.get("far", (0, None))[0]:
                    saved["far"] = (turn, _crop(frame, made, outlines))
            if crops and not opened and np.isfinite(seq.landmarks[k]).all() and "blink" not in saved:
                made = move_eyes(frame, eye_moves(model, seq, k, lens[k], centres[k]))
                saved["blink"] = (0, _crop(frame, made, outlines))
            if crops and k == seq.num_frames // 2 and opened:
                made = move_eyes(frame, eye_moves(model, seq, k, lens[k], centres[k]))
                saved["open"] = (0, _crop(frame, made, outlines))
    finally:
        for d in detectors.values():
            d.close()
    import cv2

    out.mkdir(parents=True, exist_ok=True)
    for what, (_, img) in saved.items():
        cv2.imwrite(str(out / f"{video.stem}_{what}.png"), img[..., ::-1])
    opened = np.array(full_open)
    off_lens = angle_between(footage, lens)[opened]
    between = angle_between(footage[:, 0], footage[:, 1])[opened]
    # how much the gaze moves from one open frame to the next (flicker): the footage's, then the outputs'

    def both_open(k: int) -> bool:
        return k + 1 < len(opened) and bool(opened[k] and opened[k + 1])

    steady = {"footage": dict(enumerate(footage.mean(1))), **{k: r["by_frame"] for k, r in rows.items()}}
    jitter = {
        name: float(np.nanmedian([angle_between(d[k], d[k + 1]) for k in d if k + 1 in d and both_open(k)]))
        for name, d in steady.items()
    }
    result = {
        "video": video.name,
        "jitter_deg": jitter,
        "frames": seq.num_frames,
        "open": int(np.sum(full_open)),
        "iris_px": float(np.nanmedian(seq.iris[..., 2])),
        "footage_to_lens": float(np.nanmedian(off_lens)),
        "between_eyes": float(np.nanmedian(between)),
    }
    for name, r in rows.items():
        err = np.concatenate(r["err"]) if r["err"] else np.array([np.nan])
        result[name] = {
            "median_deg": float(np.nanmedian(err)),
            "both_eyes_median_deg": float(np.nanmedian(r["both"])) if r["both"] else np.nan,
            "p90_deg": float(np.nanpercentile(err, 90)),
            "hf_box": float(np.nanmedian(r["hf_box"])),
            "hf_open": float(np.nanmedian(r["hf_open"])),
            "seam": float(np.nanmedian(r["seam"])),
            "yaw_pitch_short_deg": np.nanmedian(r["short"], 0).round(2).tolist() if r["short"] else None,
        }
    return result


def _crop(frame: np.ndarray, made: np.ndarray, outlines: list[np.ndarray]) -> np.ndarray:
    """Both eyes of the footage (top) and of the output (bottom), enlarged 3x."""
    import cv2

    both = np.concatenate(outlines)
    y0, y1, x0, x1 = eye_box(both, frame.shape[:2])
    tiles = [
        cv2.resize(x[y0:y1, x0:x1], None, fx=3, fy=3, interpolation=cv2.INTER_CUBIC) for x in (frame, made)
    ]
    return np.concatenate(tiles, 0)


def _errors(r: dict) -> str:
    return f"{r['both_eyes_median_deg']:.1f} / {r['median_deg']:.1f} ({r['p90_deg']:.1f})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", nargs="*", help="clips of ../shared/data/video (default: ten test people)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--out", type=Path, default=Path("out/eval_gaze"))
    args = ap.parse_args(argv)
    if data_missing(VIDEOS):
        return 0
    results = []
    for name in args.videos or default_videos():
        r = evaluate(VIDEOS / name, args.cache, args.out)
        results.append(r)
        print(json.dumps(r), file=sys.stderr, flush=True)
    rows = [
        [
            r["video"],
            f"{r['open']}/{r['frames']}",
            f"{r['iris_px']:.1f}",
            f"{r['footage_to_lens']:.1f}",
            f"{r['between_eyes']:.1f}",
            _errors(r["camera"]),
            _errors(r["aside"]),
            f"{r['camera']['hf_box']:.3f} / {r['camera']['hf_open']:.3f}",
            f"{r['camera']['seam']:.3f}",
            f"{r['jitter_deg']['footage']:.2f} → {r['jitter_deg']['camera']:.2f}",
        ]
        for r in results
    ]
    head = [
        "video",
        "open frames",
        "iris radius px",
        "footage: gaze to lens °",
        "footage: between the eyes °",
        "camera: error °, both eyes / each eye (p90)",
        "aside: error °, both eyes / each eye (p90)",
        "HF eye box / opening",
        "seam",
        "gaze change frame to frame °: footage → camera",
    ]
    table = markdown_table([dict(zip(head, r, strict=True)) for r in rows])
    print(table)
    (args.out / "gaze.md").write_text(table + "\n")
    (args.out / "gaze.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
