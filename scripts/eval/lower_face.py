"""Lower-face quality where nvp paints (issue 15): region / mouth-box PSNR, sharpness, seams, baselines.

For each video: tracking (cached), a renderer trained on the first 80 % (``scripts/eval/renderer.py``'s
output folder, trained here if missing), every frame's tracking registered to it as ``nvp fit`` / ``nvp eval``
do (:mod:`renderer.register`), the person's style solved on the same 80 %; then every ``--step``-th
held-out frame ``t`` is re-created several ways and compared with the real frame (``psnr_frame``: the whole
frame) and in

- the *painted region* (where nvp's render weighs ≥ 0.5 in the output) and
- the *mouth box* (mediapipe lip landmarks of the real frame, grown by 60 % of the mouth width); its
  sharpness ratios are pooled: the high-frequency (Laplacian) energy of all evaluated frames over the real
  frames' (1.0 = as much fine detail as the footage); ``psnr_mouth_open``: the mouth box's PSNR over the
  frames whose real mouth is open (inner-lip gap above :data:`OPEN` of the training part's range), where
  the mouth interior shows; ``hf_in_place``: the correlation of the finest detail with the real frame's,
  pooled (:func:`nvp.image_metrics.detail_in_place`: is the detail the ratios count the footage's own, in
  place, or specks and another frame's stubble?); ``hf_interior`` / ``hf_lips`` / ``hf_skin``: the
  high-frequency ratio inside the real frame's inner lips, between its inner and outer lips, and on the rest
  of the box:

| variant | geometry | fine detail |
|---|---|---|
| ``render`` | tracked | none (the networks' crop only; before issue 15) |
| ``detail_other`` | tracked | moved from held-out frame ``s`` ≥ 1 s away, nearest pose (honest: a dub's |
| | | footage frame shows another mouth too; the farthest frame when none is 1 s away) |
| ``detail_same`` | tracked | moved from frame ``t`` itself (optimistic: the answer's own detail) |
| ``audio`` | mouth from the held-out audio | none |
| ``audio_detail`` | mouth from the held-out audio | moved from frame ``s`` |
| ``teeth`` | tracked | as ``detail_other``, plus the mouth interior from the person's mouth bank |
| | | (:mod:`renderer.mouths`, built from training frames only) |
| ``audio_teeth`` | mouth from the held-out audio | as ``audio_detail``, plus the mouth bank's interior |
| ``dub`` | mouth from the held-out audio | exactly as ``nvp dub``: moved from frame ``t`` itself, plus the |
| | | mouth bank (sharpness as a dub shows it; its PSNR is optimistic: frame ``t``'s real lips move along) |
| ``blur_fill`` (baseline) | — | the painted region inpainted from its border (OpenCV Telea) |
| ``retrieval`` (baseline) | — | nearest-mouth training frame, painted region pasted (box-aligned) |

Writes ``results.md`` / ``results.json`` and, per video, ``crops_<video>.png`` (mouth crops of an open, a
closed and a mid frame; columns in the order of the table, real first). Reads ``../shared/data/video``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from scripts.common import VIDEOS, data_missing

SHARED = VIDEOS
VARIANTS = (
    "render",
    "detail_other",
    "detail_same",
    "audio",
    "audio_detail",
    "teeth",
    "audio_teeth",
    "dub",
    "blur_fill",
    "retrieval",
)
OPTIMISTIC = {"detail_same", "dub"}
OPEN = 0.3


def _style_and_audio_expressions(video: Path, seq, split: int, cache: Path):
    """Person style solved on frames < ``split``; expressions predicted from the audio after it."""
    from nvp.app.corpus import features_cached
    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.media import audio_rate, read_audio
    from nvp.opening import FEATURE_KIND, default_opening_model
    from nvp.person import VideoSample, predict_expressions, style_from_sample, voiced_frames

    net, manifest = default_audio2exp("phonemes")
    windows = features_cached(video, cache, "phonemes", seq.fps, seq.num_frames)
    opening_windows = features_cached(video, cache, FEATURE_KIND, seq.fps, seq.num_frames)
    train = VideoSample(video.name, windows[:split], seq.head(split), opening_windows=opening_windows[:split])
    voiced = voiced_frames(video, seq.fps, seq.num_frames)[:split]
    opening = default_opening_model()
    style = style_from_sample(net, manifest, train, default_face_model(), voiced=voiced, opening=opening)
    rate = audio_rate(video)
    audio = read_audio(video, rate)[int(round(split / seq.fps * rate)) :]
    return predict_expressions(audio, rate, seq.fps, style, net, num_frames=seq.num_frames - split)


def registered_tracking(video: Path, seq, rdir: Path):
    """``seq`` registered to the renderer in ``rdir`` as ``nvp fit`` and ``nvp eval`` register it
    (:mod:`renderer.register`, every frame); the offsets are kept in ``rdir/registration.npy`` (a mouth
    bank built before them, on the unregistered tracking, is removed so that it is built again)."""
    from nvp.face_model import default_face_model
    from renderer.register import registered, registration_offsets

    path = rdir / "registration.npy"
    if not path.exists():
        offsets = registration_offsets(rdir, video, seq, np.arange(seq.num_frames), progress=False)
        for name in ("mouths.json", "mouths.npz"):
            (rdir / name).unlink(missing_ok=True)
        np.save(path, offsets)
    return registered(seq, default_face_model(), np.load(path))


def _retrieval(frames_by_index, seq, model, t: int, train: np.ndarray, boxes, weight, real):
    """Baseline: the training frame whose tracked lip vertices are nearest to frame ``t``'s, its pixels
    pasted into the painted region by the crop-box similarity (full resolution)."""
    import torch

    from renderer.warp import sample_pixels

    lips = np.flatnonzero(model.vertex_regions["lips"])
    v = model.vertices(seq.identity, seq.expression[np.r_[train, t]])[:, lips]
    r = int(train[np.argmin(np.linalg.norm(v[:-1] - v[-1], axis=-1).mean(-1))])
    src = frames_by_index(r)
    (cx, cy, side), (sx, sy, sside) = boxes[t], boxes[r]
    ys, xs = np.mgrid[: real.shape[0], : real.shape[1]].astype(np.float32) + 0.5
    pos = np.stack([(xs - cx) * sside / side + sx, (ys - cy) * sside / side + sy], -1).astype(np.float32)
    img = torch.from_numpy(src).permute(2, 0, 1).float()
    pasted = sample_pixels(img, torch.from_numpy(pos)).permute(1, 2, 0).numpy()
    w = weight[..., None]
    return np.clip(w * pasted + (1 - w) * real, 0, 255).round().astype(np.uint8)


def evaluate(
    video: Path, out: Path, cache: Path, budget_min: float, step: int, max_frames: int, args
) -> dict:
    import cv2

    from nvp.app.corpus import tracked_cached
    from nvp.app.dub import dubbed_vertices
    from nvp.app.evaluate import detail_sources
    from nvp.face_model import default_face_model
    from nvp.image_metrics import (
        MOUTH_REGIONS,
        detail_in_place,
        high_frequency_agreement,
        high_frequency_energy,
        high_frequency_sums,
        laplacian_energy,
        masked_psnr,
        masked_ssim,
        mouth_box,
        mouth_regions,
        seam_gradient_ratio,
    )
    from nvp.media import frames_at
    from nvp.metrics import psnr
    from renderer.render import FrameRenderer
    from tracking.landmarks import LandmarkDetector

    model = default_face_model()
    seq = tracked_cached(video, cache, progress=False)
    split = int(round(seq.num_frames * 0.8))
    rdir = out / video.stem
    trained = rdir / "renderer_eval.json"  # eval_renderer's full-frame and face-crop numbers
    if not trained.exists():
        from scripts.eval.renderer import evaluate as train_and_eval

        numbers = train_and_eval(
            video,
            rdir,
            "cpu",
            budget_min,
            cache,
            steps=args.steps,
            source_input=args.source_input,
            detail_weight=args.detail_weight,
            source_gap_s=args.source_gap,
            adversarial_weight=args.adversarial_weight,
            init=args.init,
            train_options=args.train,
        )
        trained.write_text(json.dumps(numbers, indent=2) + "\n")
    whole = json.loads(trained.read_text())
    if args.register:
        seq = registered_tracking(video, seq, rdir)
    if not (rdir / "mouths.json").exists():  # the person's mouth bank, from training frames only
        from renderer.mouths import bank_frames, build_mouth_bank, sequence_shapes

        training = seq.valid & (np.arange(seq.num_frames) < split)
        gaps = model.inner_lip_gap(seq.identity, seq.expression)
        entries = bank_frames(sequence_shapes(model, seq), gaps, training)
        # the light of every frame is recorded, as a dub's bank records that of the footage behind it
        bank = build_mouth_bank(video, seq, model, frames=entries)
        if bank is not None:  # else the teeth variants render without one
            bank.save(rdir / "mouths")
    expr_audio = _style_and_audio_expressions(video, seq, split, cache)
    test = np.arange(split, seq.num_frames)[::step][:max_frames]
    held = np.arange(split, seq.num_frames)
    # as nvp eval: the nearest head pose ≥ 1 s away (the farthest frame when the held-out part is shorter)
    sources = dict(zip(held.tolist(), detail_sources(seq, held, count=len(held)).tolist(), strict=True))
    train_idx = np.flatnonzero(seq.valid[:split])
    weights = model.mouth_weights()
    lips, inner_lips = model.landmark_groups["lips_outer"], model.landmark_groups["lips_inner"]
    rows: dict[str, list[dict]] = {k: [] for k in VARIANTS}
    energies: dict[str, list[tuple[float, float, float]]] = {k: [] for k in ("real", *VARIANTS)}
    region_energies: dict[str, list[dict[str, float]]] = {k: [] for k in ("real", *VARIANTS)}
    crops: dict[int, list[np.ndarray]] = {}
    gap = model.inner_lip_gap(seq.identity, seq.expression)
    picks = {int(test[np.argmax(gap[test])]), int(test[np.argmin(gap[test])]), int(test[len(test) // 2])}
    # frames whose real mouth is open (inner-lip gap above 30 % of the training part's 5th-95th range):
    # where the mouth interior, teeth and tongue, shows
    lo, hi = np.percentile(gap[train_idx], [5, 95])
    is_open = gap > lo + OPEN * (hi - lo)

    def frame_at(i: int) -> np.ndarray:
        return next(iter(frames_at(video, np.array([i]), seq.fps)))

    with (
        FrameRenderer(rdir, model, seq, detail=False, interiors=False) as plain,
        FrameRenderer(rdir, model, seq, detail=True, interiors=False) as fine,
        FrameRenderer(rdir, model, seq, detail=True) as teeth,
        LandmarkDetector() as det,
    ):
        for t in test:
            t = int(t)
            real = frame_at(t)
            found = det.detect(real, t / seq.fps)
            if found is None:
                continue
            s = sources[t]
            src = (frame_at(s), s, fine.tracked(s))
            tracked = plain.tracked(t)
            spoken = dubbed_vertices(model, seq, t, expr_audio[t - split], weights, tracked)
            made, weight = {}, None
            made["render"], weight = plain.render(real, t, tracked, with_weight=True)
            made["detail_other"] = fine.render(real, t, tracked, source=src)
            made["detail_same"] = fine.render(real, t, tracked)
            made["audio"] = plain.render(real, t, spoken, tracked)
            made["audio_detail"] = fine.render(real, t, spoken, tracked, source=src)
            made["teeth"] = teeth.render(real, t, tracked, source=src)
            made["audio_teeth"] = teeth.render(real, t, spoken, tracked, source=src)
            made["dub"] = teeth.render(real, t, spoken, tracked)
            painted = weight >= 0.5
            made["blur_fill"] = cv2.inpaint(real, painted.astype(np.uint8), 5, cv2.INPAINT_TELEA)
            made["retrieval"] = _retrieval(frame_at, seq, model, t, train_idx, plain.boxes, weight, real)
            box = mouth_box(found.points[lips, :2], real.shape[:2])
            y0, y1, x0, x1 = box
            in_box = np.zeros(painted.shape, bool)
            in_box[y0:y1, x0:x1] = True
            regions = mouth_regions(found.points[lips, :2], found.points[inner_lips, :2], box)
            for k, img in {"real": real, **made}.items():
                energy = high_frequency_energy(img, box), laplacian_energy(img, box)
                energies[k].append((*energy, high_frequency_agreement(img, real, box)))
                region_energies[k].append(high_frequency_sums(img, box, regions))
            for k, img in made.items():
                rows[k].append(
                    {
                        "psnr_frame": psnr(img, real),
                        "psnr_painted": masked_psnr(img, real, painted),
                        "psnr_mouth": masked_psnr(img, real, in_box),
                        "ssim_mouth": masked_ssim(img, real, in_box),
                        "seam_ratio": seam_gradient_ratio(img, real, weight),
                        "psnr_mouth_open": masked_psnr(img, real, in_box) if is_open[t] else np.nan,
                    }
                )
            if t in picks:
                crops[t] = [real[y0:y1, x0:x1]] + [made[k][y0:y1, x0:x1] for k in VARIANTS]
    result = {
        "video": video.name,
        "size": f"{seq.width}x{seq.height}",
        "test_frames": len(rows["render"]),
        "open_frames": int(np.isfinite([r["psnr_mouth_open"] for r in rows["render"]]).sum()),
        **{k: whole[k] for k in ("init", "steps", "train_minutes", "psnr_full", "psnr_crop") if k in whole},
    }
    real_energy = np.array(energies["real"]).reshape(-1, 3)
    for k in VARIANTS:
        keys = rows[k][0].keys() if rows[k] else ()
        result[k] = {m: float(np.nanmean([r[m] for r in rows[k]])) for m in keys}
        # sharpness pooled over the frames (energy kept / the footage's): a mean of per-frame ratios is
        # pulled up by frames whose detail source is sharper than the frame itself (motion blur varies);
        # and how much of that detail is the footage's own, in place (specks count in the ratios too)
        fake_energy = np.array(energies[k]).reshape(-1, 3)
        ratios = fake_energy[:, :2].sum(0) / real_energy[:, :2].sum(0)
        result[k]["hf_ratio"], result[k]["laplacian_ratio"] = ratios.tolist()
        result[k]["hf_in_place"] = detail_in_place(fake_energy[:, 2], fake_energy[:, 0], real_energy[:, 0])
        for name in MOUTH_REGIONS:  # where in the box the detail is lost (pooled as above)
            kept = sum(e[name] for e in region_energies[k])
            real_sum = sum(e[name] for e in region_energies["real"])
            result[k][f"hf_{name}"] = kept / real_sum if real_sum > 0 else float("nan")
    _save_crops(crops, out / f"crops_{video.stem}.png")
    return result


def _save_crops(crops: dict[int, list[np.ndarray]], path: Path, height: int = 160) -> None:
    import cv2

    lines = []
    for t in sorted(crops):
        tiles = [cv2.resize(c, (int(c.shape[1] * height / c.shape[0]), height)) for c in crops[t]]
        lines.append(np.hstack(tiles))
    if lines:
        width = max(line.shape[1] for line in lines)
        lines = [np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0))) for line in lines]
        cv2.imwrite(str(path), cv2.cvtColor(np.vstack(lines), cv2.COLOR_RGB2BGR))


def main(argv: list[str] | None = None) -> int:
    from nvp.app.report import markdown_table

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", nargs="+", default=["dfrf__cnn2_25fps.mp4", "wav2lipgfpgan__kim_7s_raw.mp4"])
    ap.add_argument("--out", type=Path, default=Path("out/eval_renderer"), help="renderers (eval_renderer)")
    ap.add_argument("--cache", type=Path, default=Path("out/a2e/cache"), help="tracking/feature cache")
    ap.add_argument(
        "--budget-minutes", type=float, default=20.0, help="training time when a renderer is missing"
    )
    ap.add_argument(
        "--steps", type=int, help="train this many steps instead of for a time budget (independent of load)"
    )
    ap.add_argument("--step", type=int, default=5, help="evaluate every n-th held-out frame")
    ap.add_argument("--max-frames", type=int, default=60, help="at most this many frames per video")
    ap.add_argument(
        "--no-register",
        dest="register",
        action="store_false",
        help="keep the tracker's own head placement (as before renderer.register; use another --out: the "
        "mouth bank is built from the tracking)",
    )
    from scripts.eval.renderer import add_variant_arguments

    add_variant_arguments(ap)
    args = ap.parse_args(argv)
    from scripts.eval.renderer import train_options

    args.train = train_options(args.train)  # a bad one refused before any video is tracked
    if data_missing(SHARED):
        return 0
    results = [
        evaluate(SHARED / v, args.out, args.cache, args.budget_minutes, args.step, args.max_frames, args)
        for v in args.videos
    ]
    (args.out / "lower_face.json").write_text(json.dumps(results, indent=2) + "\n")
    rows = []
    for r in results:
        for k in VARIANTS:
            name = k + (" (optimistic)" if k in OPTIMISTIC else "")
            rows.append({"video": r["video"], "size": r["size"], "variant": name, **r[k]})
    table = markdown_table(rows, digits=3)
    training = [
        {k: r.get(k) for k in ("video", "init", "steps", "train_minutes", "psnr_full", "psnr_crop")}
        for r in results
    ]
    table += "\n\nrenderer training and whole held-out frames (eval_renderer):\n\n"
    table += markdown_table(training, digits=2)
    (args.out / "lower_face.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
