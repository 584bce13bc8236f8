"""Evaluate the tracker on real footage: accuracy, validity, jitter, speed; stills to look at.

    python -m scripts.eval.tracking [VIDEO ...] [--out out/eval_tracking]

Without arguments it runs on a fixed list of clips from ../shared/data/video (says so and exits if that
folder is absent). Per video it reports frames valid/total, the reprojection error of the fitted model to
the detected landmarks (pixels, and as a fraction of the interocular distance, for all landmarks and for
the lips), temporal jitter (mean second difference of landmark positions / IOD) of the detections and of
the fit, and end-to-end frames/s (decode + detect + fit). For each video it writes a PNG with the fitted
mesh over three frames: mouth widest open, mouth closed, head turned furthest.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from nvp.face_model import default_face_model
from nvp.geometry import pinhole, posed
from nvp.media import iter_frames
from nvp.metrics import inner_lip_gap, interocular_distance, jitter, landmark_error
from scripts.common import VIDEOS
from tracking.preview import draw_overlay, mesh_edges
from tracking.track import track_video

DATA = VIDEOS
DEFAULT_VIDEOS = [
    "dfrf__cnn2_25fps.mp4",  # 71 s, 512²
    "edtalk__pose_source2.mp4",  # 60 s, 256²
    "wav2lipgfpgan__kim_7s_raw.mp4",  # 1920×1080
    "spectre_mead__M003_level_1_disgusted_015.mp4",  # 1920×1080, emotional
    "latentsync__demo3_video.mp4",  # 1080×1920 HEVC, small face
    "styletalk__Obama_clip2_av.mp4",  # 30 s, 30 fps
    "styletalk__feifeili_clip1_av.mp4",  # 3/4 view, head often turned
    "mimictalk__German_20s.mp4",  # German
    "sadtalker__WDA_KatieHill_000.mp4",  # mpeg4
    "megactor__audio_ENTF_2.mp4",  # 3/4 view
]


def stills(video: Path, seq, model, frames: dict[str, int], out: Path) -> None:
    """Side-by-side crops (original | fitted mesh) of the chosen frames, one row per frame."""
    import cv2

    verts = model.vertices(seq.identity, seq.expression)
    uv = pinhole(posed(verts, seq.rotation, seq.translation), seq.focal, seq.center)
    edges = mesh_edges(model.triangles)
    want = {i: name for name, i in frames.items()}
    rows = []
    for i, frame in enumerate(iter_frames(video, fps=seq.fps, max_frames=max(want) + 1)):
        if i not in want:
            continue
        lo, hi = np.nanmin(uv[i], 0), np.nanmax(uv[i], 0)
        c, half = (lo + hi) / 2, (hi - lo).max() * 0.75
        x0, y0 = int(max(c[0] - half, 0)), int(max(c[1] - half, 0))
        x1, y1 = int(min(c[0] + half, frame.shape[1])), int(min(c[1] + half, frame.shape[0]))
        over = draw_overlay(frame, uv[i], edges, model, seq.landmarks[i], bool(seq.valid[i]))
        pair = np.concatenate([frame[y0:y1, x0:x1], over[y0:y1, x0:x1]], 1)
        pair = cv2.resize(pair, (512, 256), interpolation=cv2.INTER_AREA)
        cv2.putText(
            pair, f"{want[i]} (frame {i})", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1
        )
        rows.append(pair)
    cv2.imwrite(str(out), cv2.cvtColor(np.concatenate(rows, 0), cv2.COLOR_RGB2BGR))


def evaluate(video: Path, out_dir: Path) -> dict:
    model = default_face_model()
    g = model.landmark_groups
    t0 = time.perf_counter()
    seq, det = track_video(video, progress=False)
    seconds = time.perf_counter() - t0
    seq.save(out_dir / video.stem)
    verts = model.vertices(seq.identity, seq.expression)[:, model.landmark_vertices]
    fitted = pinhole(posed(verts, seq.rotation, seq.translation), seq.focal, seq.center)
    lm = seq.landmarks
    ok = seq.valid
    iod = interocular_distance(lm, g["left_eye"], g["right_eye"])
    lips = np.unique(np.concatenate([g["lips_outer"], g["lips_inner"]]))
    upper = np.flatnonzero(model.vertex_regions["upper_face"] & ~model.vertex_regions["eyes"])
    err_all = landmark_error(fitted, lm)
    err_lips = landmark_error(fitted, lm, lips)
    iod_mid = iod[1:-1]
    ok3 = ok[2:] & ok[1:-1] & ok[:-2]
    gap = inner_lip_gap(lm) / iod
    yaw = np.abs(Rotation.from_matrix(seq.rotation).as_euler("yxz", degrees=True)[:, 0])
    frames = {
        "mouth open": int(np.nanargmax(np.where(ok, gap, -np.inf))),
        "mouth closed": int(np.nanargmin(np.where(ok, gap, np.inf))),
        "head turned": int(np.argmax(np.where(ok, yaw, -1))),
    }
    stills(video, seq, model, frames, out_dir / f"{video.stem}_stills.png")
    return {
        "video": video.name,
        "size": f"{seq.width}x{seq.height}",
        "frames": seq.num_frames,
        "valid": int(ok.sum()),
        "err_px": float(np.nanmean(err_all[ok])),
        "err_iod": float(np.nanmean(err_all[ok] / iod[ok])),
        "lip_err_iod": float(np.nanmean(err_lips[ok] / iod[ok])),
        "lip_err_iod_p95": float(np.nanpercentile(err_lips[ok] / iod[ok], 95)),
        "jitter_lips_detected": float(np.nanmean((jitter(lm, lips) / iod_mid)[ok3])),
        "jitter_lips_fitted": float(np.nanmean((jitter(fitted, lips) / iod_mid)[ok3])),
        "jitter_upper_detected": float(np.nanmean((jitter(lm, upper) / iod_mid)[ok3])),
        "jitter_upper_fitted": float(np.nanmean((jitter(fitted, upper) / iod_mid)[ok3])),
        "max_yaw_deg": float(yaw[ok].max()),
        "focal_px": seq.focal,
        "iod_px": float(np.nanmedian(iod)),
        "fps_end_to_end": seq.num_frames / seconds,
        "detect_s": seq.info["detect_seconds"],
        "fit_s": seq.info["fit_seconds"],
        "stills": frames,
    }


COLUMNS = [
    ("video", "{}"),
    ("size", "{}"),
    ("frames", "{}"),
    ("valid", "{}"),
    ("err_px", "{:.2f}"),
    ("err_iod", "{:.4f}"),
    ("lip_err_iod", "{:.4f}"),
    ("lip_err_iod_p95", "{:.4f}"),
    ("jitter_lips_detected", "{:.4f}"),
    ("jitter_lips_fitted", "{:.4f}"),
    ("jitter_upper_detected", "{:.4f}"),
    ("jitter_upper_fitted", "{:.4f}"),
    ("max_yaw_deg", "{:.0f}"),
    ("fps_end_to_end", "{:.1f}"),
]


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(c for c, _ in COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    return head + "".join("| " + " | ".join(f.format(r[c]) for c, f in COLUMNS) + " |\n" for r in rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("videos", nargs="*", type=Path)
    ap.add_argument("--out", type=Path, default=Path("out/eval_tracking"))
    args = ap.parse_args(argv)
    videos = args.videos or [DATA / v for v in DEFAULT_VIDEOS]
    if not args.videos and not DATA.is_dir():
        print(f"no evaluation data: {DATA} does not exist; pass video paths explicitly")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for v in videos:
        r = evaluate(v, args.out)
        rows.append(r)
        print(markdown([r]).splitlines()[-1], flush=True)
    table = markdown(rows)
    (args.out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    (args.out / "results.md").write_text(table)
    print("\n" + table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
