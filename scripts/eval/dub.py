"""End to end on real targets: ``nvp fit`` each target, ``nvp dub`` it with foreign speech, non-English
speech and text to speech, and measure the outputs.

    python -m scripts.eval.dub [--targets A.mp4 ...] [--budget-minutes 10] [--out out/eval_dub]

Per dub: output frames vs audio duration, dub frames/s, and an image-level mouth check: mediapipe run on
the output frames, its lip landmarks (outer + inner loops) compared with the expected geometry (the
projected lips of the mesh that was rendered), as a fraction of the detected interocular distance; plus
the correlation of detected and expected mouth opening. Writes results.{md,json} and a strip of frames per
dub (widest expected mouth, a closed one, a median one).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from scripts.common import SHARED, data_missing

DATA = SHARED
TARGETS = ["edtalk__pose_source2.mp4", "mimictalk__German_20s.mp4", "styletalk__Obama_clip2_av.mp4"]
AUDIOS = {
    "english, another speaker (F, 44.1 kHz stereo)": "audio/videoretalking__1.wav",
    "french (M, 16 kHz)": "audio/dreamtalk__french1.wav",
}
TTS_TEXT = "Good evening. Tonight we look at how a photograph and a short recording can become a video."


def measure(result, bundle_dir: Path) -> dict:
    from nvp.app.dub import dubbed_vertices
    from nvp.face_model import default_face_model
    from nvp.media import probe_video
    from nvp.metrics import interocular_distance
    from nvp.tracked import TrackedSequence
    from tracking.detect import detect_video

    model = default_face_model()
    seq = TrackedSequence.load(bundle_dir / "tracked")
    det = detect_video(result.output, progress=False)
    g = model.landmark_groups
    lips = np.concatenate([g["lips_outer"], g["lips_inner"]])
    expected = []
    weights = model.mouth_weights()
    for j, k in enumerate(result.target_frames):
        tracked = seq.camera_vertices(model, np.array([k]))[0]
        v = dubbed_vertices(model, seq, int(k), result.expression[j], weights, tracked)[
            model.landmark_vertices[lips]
        ]
        expected.append(seq.focal * v[:, :2] / v[:, 2:] + seq.center)
    expected = np.array(expected)
    n = min(len(expected), len(det.points))
    found = det.found[:n]
    pts = det.points[:n, :, :2]
    iod = interocular_distance(pts, g["left_eye"], g["right_eye"])
    err = np.linalg.norm(pts[:, lips] - expected[:n], axis=-1).mean(1) / iod
    gap_det = np.linalg.norm(pts[:, 13] - pts[:, 14], axis=-1)
    inner = list(g["lips_inner"])
    e13, e14 = (
        expected[:n, len(g["lips_outer"]) + inner.index(13)],
        expected[:n, len(g["lips_outer"]) + inner.index(14)],
    )
    gap_exp = np.linalg.norm(e13 - e14, axis=-1)
    ok = found & np.isfinite(err)
    info = probe_video(result.output)
    return {
        "frames": info.num_frames,
        "video_s": info.duration_s,
        "audio_s": result.audio_seconds,
        "dub_fps": result.frames / result.seconds,
        "faces_found": float(found.mean()),
        "mouth_error_iod": float(np.median(err[ok])),
        "opening_corr": float(np.corrcoef(gap_det[ok], gap_exp[ok])[0, 1]),
    }


def strip(result, out: Path) -> None:
    from PIL import Image

    from nvp.face_model import default_face_model
    from nvp.media import iter_frames

    model = default_face_model()
    gap = model.inner_lip_gap(np.zeros(model.num_id, np.float32), result.expression)
    picks = [int(np.argmax(gap)), int(np.argsort(gap)[len(gap) // 2]), int(np.argmin(gap))]
    frames = {i: f for i, f in enumerate(iter_frames(result.output, max_frames=max(picks) + 1)) if i in picks}
    Image.fromarray(np.hstack([frames[i] for i in picks])).save(out)


def main(argv: list[str] | None = None) -> int:
    from nvp.app.report import write_results

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", nargs="+", default=TARGETS)
    ap.add_argument("--budget-minutes", type=float, default=10.0)
    ap.add_argument("--out", type=Path, default=Path("out/eval_dub"))
    args = ap.parse_args(argv)
    if data_missing(DATA):
        return 0
    import soundfile as sf

    from nvp.app.dub import dub
    from nvp.app.fit import FitConfig, fit
    from nvp.provenance import verify
    from nvp.tts import synthesize

    args.out.mkdir(parents=True, exist_ok=True)
    tts = args.out / "tts.wav"
    if not tts.exists():
        speech = synthesize(TTS_TEXT)
        sf.write(tts, speech.audio, speech.rate)
    audios = {**{k: DATA / v for k, v in AUDIOS.items()}, "text to speech (piper)": tts}
    rows = []
    for target in args.targets:
        name = Path(target).stem
        bundle = args.out / name / "person"
        t0 = time.perf_counter()
        if not (bundle / "bundle.json").exists():
            fit(DATA / "video" / target, bundle, FitConfig(budget_minutes=args.budget_minutes))
        fit_min = json.loads((bundle / "bundle.json").read_text())["stages"]
        fit_total = sum(s.get("seconds", 0) for s in fit_min.values()) / 60
        for label, audio in audios.items():
            out = args.out / name / f"dub_{audio.stem}.mp4"
            r = dub(audio, bundle, out)
            row = {"target": target, "audio": label, "fit_min": round(fit_total, 1), **measure(r, bundle)}
            row["marked"] = verify(out).marked
            strip(r, out.with_suffix(".png"))
            rows.append(row)
            print(row, flush=True)
        print(f"{target}: {time.perf_counter() - t0:.0f} s", flush=True)
    print(write_results(rows, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
