"""What limits a re-creation's mouth box (issue 15): where its error lies and what fine detail could give.

For each video, on the renderer and mouth bank ``scripts/eval/lower_face.py`` made (``--out``, same folder;
run that first), every ``--step``-th held-out frame ``t`` is re-created as ``nvp eval`` re-creates it
visually (tracked geometry, fine detail moved from held-out frame ``s`` ≥ 1 s away, the mouth bank: the
``teeth`` variant of eval_lower_face) and compared with the real frame in the mouth box:

- ``psnr``: pooled over the frames (one MSE), so that the parts below add up;
- ``coarse`` / ``fine``: shares of that MSE in the error's coarse part (a Gaussian low-pass of ``--sigma``
  frame pixels) and in the rest; ``coarse_lips``: the share of the coarse error inside the real lips' hull
  (outer lip landmarks, grown by 2 pixels) and ``lips_area`` that hull's share of the box;
- ``psnr_perfect_coarse`` / ``psnr_perfect_fine``: the PSNR if either part were exact;
- ``psnr_oracle_detail`` / ``hf_oracle_detail``: the render's coarse part plus the fine part of frame ``s``
  aligned to the real frame ``t`` by dense optical flow on the whole frame (OpenCV DIS): the best that
  moving another frame's detail could do, with a registration no renderer has (the real frame is the
  answer); ``hf`` is the shipped high-frequency ratio (grey levels, 5×5 blur, as ``nvp eval``);
- ``shared_next`` / ``shared_far``: correlation of the real footage's fine detail (image minus its 5×5 blur)
  on the skin of the box (outside the lips' hull grown by 3 pixels) between frame ``t`` and frame ``t + 1``
  / frame ``s``, each aligned to ``t`` the same way: how much of the detail another frame shares at all.

Writes ``lower_face_limits.{json,md}`` into ``--out``. Reads ``../shared/data/video``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from scripts.common import VIDEOS, data_missing

SHARED = VIDEOS


def _aligned(source: np.ndarray, target: np.ndarray, flow) -> np.ndarray:
    """``source`` warped onto ``target`` (both RGB uint8) by dense optical flow, float32."""
    import cv2

    grey = [cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (target, source)]
    f = flow.calc(grey[0], grey[1], None)
    h, w = grey[0].shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    moved = cv2.remap(source, gx + f[..., 0], gy + f[..., 1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return moved.astype(np.float32)


def _fine(img: np.ndarray) -> np.ndarray:
    import cv2

    g = img.astype(np.float32)
    return g - cv2.GaussianBlur(g, (5, 5), 0)


def limits(video: Path, out: Path, cache: Path, step: int, max_frames: int, sigma: float) -> dict:
    import cv2

    from nvp.app.corpus import tracked_cached
    from nvp.app.evaluate import detail_sources
    from nvp.face_model import default_face_model
    from nvp.image_metrics import high_frequency_energy, mouth_box
    from nvp.media import frames_at
    from renderer.render import FrameRenderer
    from scripts.eval.lower_face import registered_tracking
    from tracking.landmarks import LandmarkDetector

    rdir = out / video.stem
    if not (rdir / "registration.npy").exists():  # its renderer, registration and mouth bank
        raise SystemExit(f"no registered renderer in {rdir}: run eval_lower_face.py --out {out} first")
    model = default_face_model()
    seq = registered_tracking(video, tracked_cached(video, cache, progress=False), rdir)
    split = int(round(seq.num_frames * 0.8))
    held = np.arange(split, seq.num_frames)
    test = held[:-1][::step][:max_frames]
    sources = dict(zip(held.tolist(), detail_sources(seq, held, count=len(held)).tolist(), strict=True))
    need = sorted({*test.tolist(), *(test + 1).tolist(), *(sources[int(t)] for t in test)})
    frames = dict(zip(need, frames_at(video, np.array(need), seq.fps), strict=True))
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    lips = model.landmark_groups["lips_outer"]

    def low(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(x, (0, 0), sigma)

    sums = dict.fromkeys(("n", "se", "coarse", "fine", "lips", "lips_n", "oracle"), 0.0)
    hf = dict.fromkeys(("real", "made", "oracle"), 0.0)
    shared = {k: np.zeros(3) for k in ("next", "far")}  # cross, energy of t, energy of the other
    count = 0
    with FrameRenderer(rdir, model, seq, detail=True) as fr, LandmarkDetector() as det:
        for t in test.tolist():
            real = frames[t]
            found = det.detect(real, t / seq.fps)
            if found is None:
                continue
            count += 1
            box = mouth_box(found.points[lips, :2], real.shape[:2])
            b = (slice(box[0], box[1]), slice(box[2], box[3]))
            s = sources[t]
            made = fr.render(real, t, fr.tracked(t), source=(frames[s], s, fr.tracked(s))).astype(np.float32)
            r = real.astype(np.float32)
            hull = np.zeros(real.shape[:2], np.uint8)
            cv2.fillConvexPoly(hull, cv2.convexHull(np.round(found.points[lips, :2]).astype(np.int32)), 1)
            in_lips = cv2.dilate(hull, np.ones((5, 5)))[b].astype(bool)
            skin = (cv2.dilate(hull, np.ones((7, 7))) == 0)[b][..., None]
            error = (made - r)[b]
            coarse = (low(made) - low(r))[b]
            sums["n"] += error.size
            sums["se"] += float((error**2).sum())
            sums["coarse"] += float((coarse**2).sum())
            sums["fine"] += float(((error - coarse) ** 2).sum())
            sums["lips"] += float((coarse[in_lips] ** 2).sum())
            sums["lips_n"] += float(in_lips.sum() * 3)
            other = _aligned(frames[s], real, flow)
            oracle = low(made) + other - low(other)
            sums["oracle"] += float(((oracle - r)[b] ** 2).sum())
            oracle8 = np.clip(np.round(oracle), 0, 255).astype(np.uint8)
            for k, img in (("real", real), ("made", made.astype(np.uint8)), ("oracle", oracle8)):
                hf[k] += high_frequency_energy(img, box)
            ft = _fine(real)[b] * skin
            for k, u in (("next", t + 1), ("far", s)):
                fu = _fine(_aligned(frames[u], real, flow))[b] * skin
                shared[k] += [float((ft * fu).sum()), float((ft**2).sum()), float((fu**2).sum())]

    def psnr(se: float) -> float:
        return float(10 * np.log10(255**2 / (se / sums["n"])))

    return {
        "video": video.name,
        "size": f"{seq.width}x{seq.height}",
        "frames": count,
        "psnr": psnr(sums["se"]),
        "hf": hf["made"] / hf["real"],
        "coarse": sums["coarse"] / sums["se"],
        "fine": sums["fine"] / sums["se"],
        "coarse_lips": sums["lips"] / sums["coarse"],
        "lips_area": sums["lips_n"] / sums["n"],
        "psnr_perfect_coarse": psnr(sums["fine"]),
        "psnr_perfect_fine": psnr(sums["coarse"]),
        "psnr_oracle_detail": psnr(sums["oracle"]),
        "hf_oracle_detail": hf["oracle"] / hf["real"],
        **{f"shared_{k}": float(v[0] / np.sqrt(v[1] * v[2])) for k, v in shared.items()},
    }


def main(argv: list[str] | None = None) -> int:
    from nvp.app.report import markdown_table

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", nargs="+", default=["dfrf__cnn2_25fps.mp4", "edtalk__pose_source2.mp4"])
    ap.add_argument("--out", type=Path, default=Path("out/eval_renderer"), help="eval_lower_face's renderers")
    ap.add_argument("--cache", type=Path, default=Path("out/a2e/cache"), help="tracking/feature cache")
    ap.add_argument("--step", type=int, default=5, help="every n-th held-out frame")
    ap.add_argument("--max-frames", type=int, default=60, help="at most this many frames per video")
    ap.add_argument("--sigma", type=float, default=2.0, help="coarse / fine split: Gaussian σ, frame pixels")
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    rows = []
    for v in args.videos:
        video = Path(v) if Path(v).is_file() else SHARED / v
        rows.append(limits(video, args.out, args.cache, args.step, args.max_frames, args.sigma))
    (args.out / "lower_face_limits.json").write_text(json.dumps(rows, indent=2) + "\n")
    table = markdown_table(rows, digits=3)
    (args.out / "lower_face_limits.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
