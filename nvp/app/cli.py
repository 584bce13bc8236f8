"""The one nvp command line. Heavy modules are imported inside the command that needs them."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from nvp import __version__


def _cmd_track(args: argparse.Namespace) -> int:
    from tracking.fit import TrackingConfig
    from tracking.preview import write_preview
    from tracking.track import track_video

    seq, det = track_video(args.video, progress=not args.quiet, cfg=TrackingConfig())
    out = seq.save(args.output)
    if args.save_detections:
        det.save(Path(args.output) / "detections.npz")
    valid = int(seq.valid.sum())
    print(
        f"tracked {seq.num_frames} frames ({valid} valid, {seq.num_frames - valid} bridged) "
        f"in {seq.info['total_seconds']:.1f} s; median fit error {_nanmedian(seq.fit_error):.2f} px → {out}"
    )
    if args.preview:
        write_preview(args.video, seq, args.preview, progress=not args.quiet)
        print(f"preview → {args.preview}")
    return 0


def _cmd_train_audio2exp(args: argparse.Namespace) -> int:
    from nvp.app.corpus import corpus_split
    from nvp.app.distributed import process_group
    from nvp.app.train_audio2exp import Audio2ExpTrainConfig, train
    from nvp.face_model import default_face_model

    group = process_group()  # one process, or one of torchrun's
    cache = Path(args.cache) if args.cache else Path(args.output) / "cache"
    snrs = tuple(args.noise_snr or ())
    if not group.main:
        group.barrier()  # the main process tracks the corpus into the cache first
    train_set, val_set, split = corpus_split(
        Path(args.corpus), args.val, args.exclude, cache, args.features, not args.quiet and group.main, snrs
    )
    if group.main:
        group.barrier()
    cfg = Audio2ExpTrainConfig(
        kind=args.features,
        steps=args.steps,
        seed=args.seed,
        val_every=args.val_every,
        closure_weight=args.closure_weight,
        noise_snrs=snrs,
    )
    frames = {"train_frames": int(sum(s.valid.sum() for s in train_set))}
    result = train(
        train_set,
        val_set,
        default_face_model(),
        cfg,
        Path(args.output),
        progress=not args.quiet,
        provenance={"split": split, **frames, "corpus": str(args.corpus), "processes": group.world},
    )
    if not group.main:
        return 0
    print(
        f"best validation mouth error {result['best_mouth_error_iod']:.4f} IOD → "
        f"{Path(args.output) / 'best.json'}"
    )
    return 0


def _cmd_train_opening(args: argparse.Namespace) -> int:
    from nvp.app.corpus import corpus_split
    from nvp.app.train_opening import train_opening
    from nvp.face_model import default_face_model
    from nvp.opening import FEATURE_KIND

    kind = args.features or FEATURE_KIND
    cache = Path(args.cache) if args.cache else Path(args.output).parent / "cache"
    train_set, val_set, split = corpus_split(
        Path(args.corpus), args.val, args.exclude, cache, kind, not args.quiet
    )
    out = Path(args.output)
    _, summary = train_opening(
        train_set,
        val_set,
        default_face_model(),
        out,
        provenance={"split": split, "corpus": str(args.corpus)},
        kind=kind,
    )
    print(
        f"ridge {summary['ridge']:g}: validation correlation {summary['validation_corr']:.3f} on "
        f"{len(val_set)} videos, {summary['train_frames']} training frames → {out.with_suffix('.json')}"
    )
    return 0


def _cmd_pretrain_renderer(args: argparse.Namespace) -> int:
    from nvp.app.pretrain_renderer import corpus_videos, pretrain_renderer

    out = Path(args.output)
    cache = Path(args.cache) if args.cache else out.parent / ".nvp-cache"
    videos = corpus_videos(Path(args.corpus), args.exclude)
    info = pretrain_renderer(
        videos,
        out,
        cache,
        args.preset,
        args.budget_minutes,
        args.steps,
        args.max_frames,
        _device(args.device),
        progress=not args.quiet,
    )
    print(
        f"generic {args.preset} renderer: {len(info['videos'])} videos, {info['train_frames']} frames, "
        f"{info['steps']} steps in {info['train_seconds'] / 60:.1f} min → {out / 'renderer.json'}"
    )
    return 0


def _cmd_person_map(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from nvp.app.corpus import load_sample
    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.opening import FEATURE_KIND, default_opening_model
    from nvp.person import style_from_sample, voiced_frames

    net, manifest = default_audio2exp(args.features)
    cache = Path(args.cache) if args.cache else Path(args.output).parent / ".nvp-cache"
    sample = load_sample(Path(args.video), cache, args.features, progress=not args.quiet)
    opening_windows = load_sample(Path(args.video), cache, FEATURE_KIND, progress=False).windows
    sample = replace(sample, opening_windows=opening_windows)
    voiced = voiced_frames(Path(args.video), sample.tracked.fps, sample.tracked.num_frames)
    opening = default_opening_model()
    style = style_from_sample(net, manifest, sample, default_face_model(), voiced=voiced, opening=opening)
    js = style.save(Path(args.output))
    print(f"person map from {int(sample.valid.sum())} frames → {js}")
    return 0


def _cmd_predict(args: argparse.Namespace) -> int:
    import numpy as np

    from nvp.app.dub import load_style
    from nvp.artifact import atomic_path, check_output_file
    from nvp.audio2exp import default_audio2exp
    from nvp.errors import NvpError
    from nvp.face_model import default_face_model
    from nvp.media import read_audio
    from nvp.person import predict_expressions
    from nvp.tracked import TrackedSequence

    if args.output is None and args.export is None:
        raise NvpError("give -o (expressions .npz) and/or --export (animation .glb)")
    outputs = [check_output_file(p, inputs=(args.audio, args.style)) for p in (args.output, args.export) if p]
    from nvp.bundle import check_output_place

    for out in outputs:  # never over an input, nor inside a person bundle
        check_output_place(out, (args.audio, args.style, args.mesh))
    if args.export is not None and args.export.suffix.lower() != ".glb":
        raise NvpError(f"--export writes binary glTF: name the file .glb, not {args.export.name}")
    model = default_face_model()
    identity, whose = np.zeros(model.num_id, np.float32), "the face model's mean face"
    track = args.mesh
    if args.style.is_dir():  # a person bundle: its style, checked against the network, and its face
        from nvp.app.dub import load_person
        from nvp.bundle import PersonBundle

        person = load_person(PersonBundle.load(args.style))
        style, net = person.style, person.net
        if track is None:
            identity, whose = person.tracked.identity, f"the face of {args.style}"
    else:
        style = load_style(args.style)
        net, manifest = default_audio2exp(style.feature_kind)
        if manifest["sha256"] != style.audio2exp_sha256:
            raise NvpError(
                f"{args.style} was made with another Audio2ExpressionNet; rebuild it (nvp person-map)"
            )
    if track is not None:
        identity, whose = TrackedSequence.load(Path(track)).identity, f"the face of {track}"
    face_given = track is not None or args.style.is_dir()
    audio = read_audio(args.audio, 16000)
    expr = predict_expressions(audio, 16000, args.fps, style, net)
    if args.output is not None:
        out = {"expression": expr.astype(np.float32), "fps": np.float32(args.fps)}
        if face_given:
            out["vertices"] = model.vertices(identity, expr).astype(np.float32)
            out["triangles"] = model.triangles
        with atomic_path(outputs[0]) as tmp:
            np.savez_compressed(tmp, **out)
    if args.export is not None:
        from nvp.gltf import face_animation, write_glb

        info = {
            "nvp": "audio-driven face animation (Neural Voice Puppetry)",
            "audio": Path(args.audio).name,
            "fps": args.fps,
            "timing": "keyframe j at j / fps seconds; second 0 = the first audio sample",
            "face": whose,
            "style": str(style.info.get("video", args.style)),
        }
        write_glb(
            face_animation(model.vertices(identity), model.exp_basis, model.triangles, expr, args.fps, info),
            outputs[-1],
        )
    print(f"{len(expr)} frames of expressions at {args.fps} fps ({whose}) → " + ", ".join(map(str, outputs)))
    return 0


def _cmd_train_renderer(args: argparse.Namespace) -> int:
    import numpy as np

    from nvp.app.fit import renderer_init
    from nvp.errors import NvpError
    from nvp.face_model import default_face_model
    from nvp.media import probe_video
    from nvp.tracked import TrackedSequence
    from renderer.data import build_cache
    from renderer.preset import get_preset
    from renderer.train import RendererTrainConfig, train_renderer

    seq = TrackedSequence.load(args.track_dir)
    info = probe_video(args.video)
    if (info.width, info.height) != (seq.width, seq.height) or abs(info.num_frames - seq.num_frames) > 1:
        raise NvpError(
            f"{args.video} ({info.width}x{info.height}, {info.num_frames} frames) is not the video "
            f"tracked in {args.track_dir} ({seq.width}x{seq.height}, {seq.num_frames} frames)"
        )
    preset = get_preset(args.preset)
    split = int(round(seq.num_frames * args.train_fraction))
    cache = build_cache(args.video, seq, default_face_model(), preset, np.arange(split), not args.quiet)
    budget = None if args.budget_minutes is None else args.budget_minutes * 60
    vgg = str(args.vgg_weights) if args.vgg_weights else None
    cfg = RendererTrainConfig(
        preset=args.preset,
        steps=args.steps,
        budget_s=budget,
        seed=args.seed,
        vgg_weights=vgg,
        init=renderer_init(args.init),
    )
    result = train_renderer(
        cache, cfg, Path(args.output), device=_device(args.device), progress=not args.quiet
    )
    print(
        f"trained the {args.preset} renderer on {result['train_frames']} frames: {result['steps']} steps in "
        f"{result['train_seconds'] / 60:.1f} min → {Path(args.output) / 'renderer.json'}"
    )
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    import numpy as np

    from nvp.artifact import check_output_file
    from nvp.face_model import default_face_model
    from nvp.media import VideoWriter, audio_rate, has_audio, iter_frames, read_audio
    from nvp.provenance import synthetic_mark
    from nvp.tracked import TrackedSequence
    from renderer.render import FrameRenderer, render_frames

    check_output_file(args.output, inputs=(args.video,))
    seq = TrackedSequence.load(args.track_dir)
    start = args.start_frame
    n = seq.num_frames - start if args.frames is None else min(args.frames, seq.num_frames - start)
    audio, rate = None, 48000
    if has_audio(args.video):
        rate = audio_rate(args.video)
        audio = read_audio(args.video, None, mono=False)[int(start / seq.fps * rate) :]
    tags = synthetic_mark("render", renderer=str(args.renderer_dir))
    with (
        FrameRenderer(args.renderer_dir, default_face_model(), seq, _device(args.device)) as fr,
        VideoWriter(args.output, seq.fps, seq.width, seq.height, audio, rate, metadata=tags) as vw,
    ):
        frames = iter_frames(args.video, seq.fps, start, n)
        for _, made in render_frames(
            fr, frames, np.arange(start, start + n), {"render": None}, not args.quiet
        ):
            vw.write(made["render"])
    print(f"rendered {n} frames → {args.output}")
    return 0


def _cmd_fit(args: argparse.Namespace) -> int:
    from nvp.app.fit import FitConfig, fit

    cfg = FitConfig(
        preset=args.preset,
        budget_minutes=args.budget_minutes,
        steps=args.steps,
        features=args.features,
        device=_device(args.device),
        vgg_weights=str(args.vgg_weights) if args.vgg_weights else None,
        renderer_init=args.init,
    )
    bundle = fit(args.video, args.output, cfg, progress=not args.quiet, force=args.force)
    st = bundle.manifest["stages"]
    total = sum(v.get("seconds", 0) for v in st.values())
    print(f"person bundle → {bundle.root} (fit took {total / 60:.1f} min)")
    return 0


def _cmd_dub(args: argparse.Namespace) -> int:
    from nvp.app.dub import dub
    from nvp.errors import NvpError

    audios = [Path(a) for a in args.audio]
    if args.list:
        try:
            lines = Path(args.list).read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise NvpError(f"cannot read the list {args.list}: {e}") from e
        base = Path(args.list).parent
        audios += [base / x.strip() for x in lines if x.strip() and not x.lstrip().startswith("#")]
    if not audios:
        raise NvpError("give the audio to dub (files, or --list FILE with one per line)")
    several = len(audios) > 1
    transcript = None
    if args.transcript is not None:
        if several:
            raise NvpError("--transcript is the text of one audio file; dub the files one by one")
        try:
            transcript = (Path(args.transcript).read_text(encoding="utf-8"), args.language)
        except (OSError, UnicodeDecodeError) as e:
            raise NvpError(f"cannot read the transcript {args.transcript}: {e}") from e
    if several:
        if Path(args.output).suffix.lower() == ".mp4" or Path(args.output).is_file():
            raise NvpError(
                f"several audio files are dubbed into a folder: -o {Path(args.output).with_suffix('')}/"
            )
        stems = [a.stem for a in audios]
        twice = sorted({x for x in stems if stems.count(x) > 1})
        if twice:
            raise NvpError(f"two audio files would both be written as {twice[0]}.mp4; rename one")
    from nvp.bundle import check_output_place

    for audio in audios:  # before any work: no output over an input, none inside a person bundle
        out = Path(args.output) / f"{audio.stem}.mp4" if several else Path(args.output)
        check_output_place(out, (*audios, args.list, args.person, args.style))
    failed = 0
    for i, audio in enumerate(audios):
        out = Path(args.output) / f"{audio.stem}.mp4" if several else Path(args.output)
        try:
            r = dub(
                audio,
                args.person,
                out,
                device=_device(args.device),
                progress=not args.quiet,
                style=args.style,
                transcript=transcript,
            )
        except NvpError as e:
            if not several:
                raise  # main() prints it as the one error line
            print(f"nvp dub: {audio}: error: {e}", file=sys.stderr)  # the other files still run
            failed += 1
            continue
        print(
            (f"[{i + 1}/{len(audios)}] " if several else "")
            + f"{r.frames} frames ({r.frames / r.fps:.2f} s for {r.audio_seconds:.2f} s of audio) in "
            f"{r.seconds:.1f} s ({r.rendered / r.seconds:.1f} frames/s"
            + ("" if r.rendered == r.frames else f"; resumed, {r.rendered} rendered now")
            + f") → {r.output}"
        )
    if several:
        print(
            f"{len(audios) - failed} of {len(audios)} dubbed → {args.output}"
            + (f"; {failed} failed" if failed else "")
        )
    return 2 if failed else 0


def _cmd_say(args: argparse.Namespace) -> int:
    import tempfile

    import soundfile as sf

    from nvp.app.dub import dub
    from nvp.artifact import check_output_file
    from nvp.tts import have_piper, installed_voices, synthesize

    if args.list_voices:
        voices = installed_voices()
        for name, (model, _) in sorted(voices.items()):
            print(f"{name}\t{model}")
        if not voices:
            print("no piper voice installed (pip install 'nvp[tts]')")
        return 0
    if args.text is None or args.person is None or args.output is None:
        from nvp.errors import NvpError

        raise NvpError("give the text, --person and -o (or --list-voices)")
    check_output_file(args.output)
    if args.wav is not None:
        check_output_file(args.wav)
    from nvp.bundle import check_output_place
    from nvp.errors import NvpError

    for out in (args.output, args.wav):  # never over an input, nor inside a person bundle
        if out is not None:
            check_output_place(out, (args.person, args.style))
    if args.wav is not None and Path(args.wav).resolve() == Path(args.output).resolve():
        raise NvpError(f"-o and --wav both name {args.output}; give the speech another name")
    speech = synthesize(args.text, length_scale=args.slower, voice=args.voice, engine=args.engine)
    with tempfile.TemporaryDirectory() as tmp:
        wav = Path(tmp) / "speech.wav"
        sf.write(wav, speech.audio, speech.rate)
        r = dub(
            wav,
            args.person,
            args.output,
            device=_device(args.device),
            progress=not args.quiet,
            style=args.style,
            details={"speech": f"text to speech ({speech.engine}, voice {speech.voice})"},
            transcript=(args.text, speech.language) if have_piper() else None,  # its phonemizer aligns
        )
        if args.wav is not None:
            import shutil

            shutil.copyfile(wav, args.wav)
    print(
        f"{speech.seconds:.1f} s of speech ({speech.engine}, voice {speech.voice}), {r.frames} frames in "
        f"{r.seconds:.1f} s → {r.output}" + (f"; speech → {args.wav}" if args.wav else "")
    )
    return 0


def _cmd_live(args: argparse.Namespace) -> int:
    import numpy as np

    from nvp.app.live import live

    def status(text: str) -> None:
        if not args.quiet:
            print(f"\rnvp live: {text}   ", end="", file=sys.stderr, flush=True)

    raw = sys.stdout.buffer if args.raw else None
    if raw is not None and not args.quiet:
        from nvp.bundle import PersonBundle

        t = PersonBundle.load(args.person, verify=False).manifest["target"]  # live() checks it in full
        size, fps = f"{t['width']}x{t['height']}", f"{t['fps']:.3f}"
        print(
            f"nvp live: raw RGB24 {size} at {fps} fps on stdout, e.g. | ffplay -f rawvideo "
            f"-pixel_format rgb24 -video_size {size} -framerate {fps} -",
            file=sys.stderr,
        )
    r = live(
        args.source,
        args.person,
        args.output,
        raw,
        device=_device(args.device),
        realtime=args.realtime,
        rate=args.rate,
        style=args.style,
        max_lag_s=args.max_lag,
        status=status,
    )
    lat = r.latency_s[r.latency_s.size // 10 :] if r.latency_s.size > 10 else r.latency_s  # after warm-up
    print(
        ("\n" if not args.quiet else "")
        + f"{r.frames} frames for {r.audio_seconds:.1f} s of audio in {r.seconds:.1f} s; latency median "
        f"{np.median(lat):.2f} s, 95th percentile {np.percentile(lat, 95):.2f} s "
        f"(look-ahead {r.lookahead_s:.2f} s included); "
        f"{r.dropped} frames dropped ({r.dropped / max(r.frames, 1):.0%})"
        + (f" → {args.output}" if args.output else ""),
        file=sys.stderr if args.raw else sys.stdout,
    )
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    from nvp.app.serve import serve

    serve(Path(args.data), args.host, args.port, args.max_upload_mb)
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from nvp.bundle import PersonBundle
    from nvp.person import PersonStyle

    b = PersonBundle.load(args.person, verify=False)
    checked = b.check()  # every file the bundle lists, at the size and sha256 the fit wrote
    m = b.manifest
    t = m["target"]
    print(f"person bundle {b.root} (format {m['format']} v{m['version']}, made by nvp {m['nvp_version']})")
    print(
        f"  target: {Path(t['source']).name}, {t['width']}x{t['height']}, {t['fps']:.3f} fps, "
        f"{t['frames']} frames ({t['duration_s']:.1f} s)"
    )
    print(f"  speech features: {m['feature_kind']}; renderer preset: {m['preset']}")
    style = PersonStyle.load(b.path("style"))
    opening = style.info.get("opening", "none (fitted before nvp's opening model)")
    opening = "calibrated" if style.opening else opening
    print(f"  talking style: rest mouth from {style.info.get('rest', '?')}; mouth-opening model: {opening}")
    for name, facts in m["stages"].items():
        extra = ", ".join(f"{k} {v}" for k, v in facts.items() if k != "seconds")
        print(f"  {name}: {facts.get('seconds', 0):.1f} s" + (f" ({extra})" if extra else ""))
    print(f"  files: {checked} checked, each at the size and sha256 the fit wrote")
    return 0


def _cmd_verify(args: argparse.Namespace) -> int:
    import json

    from nvp.provenance import verify

    r = verify(args.video)
    if args.json:
        print(json.dumps({"path": r.path, "synthetic": r.marked, "tags": r.tags}))
    elif r.marked:
        made = f"nvp {r.tags.get('nvp_version', '?')} ({r.tags.get('nvp_kind', '?')})"
        print(f"{r.path}: SYNTHETIC — made by {made}")
    else:
        print(f"{r.path}: no nvp synthetic-media mark")
    return 0 if r.marked else 1


SUMMARY_METRICS = (
    "psnr_full",
    "ssim_full",
    "psnr_crop",
    "ssim_crop",
    "mouth_landmark_error_iod",
    "closure_f1",
    "av_offset_frames",
    "mouth_jitter_ratio",
)
"""The ``nvp eval`` metrics in the summary table of a multi-video run (every number is in eval.json)."""


def _cmd_eval(args: argparse.Namespace) -> int:
    from nvp.app.evaluate import EvalConfig, evaluate_video
    from nvp.app.report import write_results
    from nvp.errors import NvpError

    cfg = EvalConfig(
        train_fraction=args.train_fraction,
        preset=args.preset,
        budget_minutes=args.budget_minutes,
        steps=args.steps,
        side_by_side=args.side_by_side,
        device=_device(args.device),
        renderer_init=args.init,
    )
    several = len(args.video) > 1
    if args.output:
        root = Path(args.output)
    else:
        root = Path("nvp-eval") if several else Path(args.video[0]).with_suffix("") / "nvp-eval"
    rows, failed = [], 0
    for video in args.video:
        out = root / Path(video).stem if several else root
        try:
            r = evaluate_video(video, out, cfg, progress=not args.quiet)
        except NvpError as e:
            if not several:
                raise  # main() prints it as the one error line
            print(f"nvp eval: {video}: {e}", file=sys.stderr)  # the other videos still run
            failed += 1
            continue
        print((out / "eval.md").read_text())
        print(f"eval.json, eval.md, eval.png → {out} ({r['frames']['test']} held-out frames)")
        for kind in ("visual", "audio"):
            rows.append(
                {
                    "video": r["video"],
                    "driven by": kind,
                    "test frames": r["frames"]["test"],
                    "fit min": r["fit_minutes"],
                    **{k: r[kind][k] for k in SUMMARY_METRICS if k in r[kind]},
                }
            )
    if several and rows:
        print(write_results(rows, root))
    return 2 if failed else 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from nvp.app.demo import run_demo

    result = run_demo(Path(args.output), progress=not args.quiet, budget_minutes=args.budget_minutes)
    print(result)
    return 0


def _nanmedian(x):
    import numpy as np

    return float(np.nanmedian(x)) if np.isfinite(x).any() else float("nan")


def _add_device_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device",
        default="auto",
        help="torch device: auto (cuda when a GPU is available, else cpu), cpu, cuda, cuda:1, ...",
    )


def _add_style_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--style",
        type=Path,
        help="talk in another person's style: their bundle folder or person-map .json (default: their own)",
    )


def _device(name: str) -> str:
    """The torch device for ``--device`` (``auto`` picks cuda when torch sees a GPU)."""
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _add_renderer_training_args(p: argparse.ArgumentParser, budget_minutes: float | None = None) -> None:
    """The renderer-training options shared by train-renderer, fit and eval."""
    from nvp.app.fit import FitConfig

    p.add_argument(
        "--preset", choices=("cpu", "quality", "paper"), default=FitConfig.preset, help="renderer preset"
    )
    p.add_argument("--steps", type=int, help="renderer training steps (default: the preset's)")
    p.add_argument(
        "--budget-minutes",
        type=float,
        default=budget_minutes,
        help="renderer training time (with --steps: whichever ends first)",
    )
    p.add_argument(
        "--init",
        default=FitConfig.renderer_init,
        metavar="generic|scratch|FOLDER",
        help="start renderer training from the shipped generic renderer (default), from scratch, or from "
        "a renderer folder (nvp train-renderer / pretrain-renderer output)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The parser; option defaults come from the config dataclasses (light modules: no torch)."""
    from nvp.app.evaluate import EvalConfig
    from nvp.app.fit import FitConfig
    from nvp.app.pretrain_renderer import MAX_FRAMES
    from nvp.audio_features import FEATURE_KINDS

    # an opening model reads its features as extracted (mel is speaker-normalised only for the network)
    opening_kinds = tuple(k for k in FEATURE_KINDS if k != "mel")

    ap = argparse.ArgumentParser(
        prog="nvp", description="Neural Voice Puppetry: audio-driven facial reenactment."
    )
    ap.add_argument("--version", action="version", version=f"nvp {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="log details")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("track", help="track a talking-head video with the face model")
    p.add_argument("video", type=Path, help="input video (mp4, mov, mkv, ...)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory for tracked.json/.npz")
    p.add_argument("--preview", type=Path, help="also write an mp4 with the fitted mesh over the footage")
    p.add_argument(
        "--save-detections", action="store_true", help="also keep the raw landmarks (detections.npz)"
    )
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("train-audio2exp", help="train the generic Audio2ExpressionNet on a folder of videos")
    p.add_argument("corpus", type=Path, help="folder of talking-head videos with audio")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (checkpoints, best model)")
    p.add_argument(
        "--features", choices=("phonemes", "mel"), default=FitConfig.features, help="speech features"
    )
    p.add_argument(
        "--val", nargs="*", help="file names of validation videos (default: 5 spread over the list)"
    )
    p.add_argument("--exclude", nargs="*", help="file names to leave out entirely")
    p.add_argument("--steps", type=int, default=4000, help="optimisation steps")
    p.add_argument(
        "--val-every", type=int, default=250, help="steps between validations (the best model is kept)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument(
        "--closure-weight",
        type=float,
        default=1.0,
        help="weight of the closure head's loss (0: no closure head)",
    )
    p.add_argument(
        "--noise-snr",
        type=float,
        nargs="*",
        metavar="DB",
        help="also train on the audio with white noise at these SNRs, e.g. 20 10 0 (augmentation)",
    )
    p.add_argument("--cache", type=Path, help="tracking/feature cache (default: OUTPUT/cache)")
    p.set_defaults(func=_cmd_train_audio2exp)

    p = sub.add_parser(
        "train-opening", help="fit the generic mouth-opening model (closed form) on a folder of videos"
    )
    p.add_argument("corpus", type=Path, help="folder of talking-head videos with audio")
    p.add_argument("-o", "--output", type=Path, required=True, help="output model (.npz + .json)")
    p.add_argument(
        "--val", nargs="*", help="file names of validation videos (default: 5 spread over the list)"
    )
    p.add_argument("--exclude", nargs="*", help="file names to leave out entirely")
    p.add_argument("--cache", type=Path, help="tracking/feature cache (default: next to OUTPUT)")
    p.add_argument(
        "--features",
        choices=opening_kinds,
        help="speech features the model reads (default: those of the shipped model; whisper_base_lN: "
        "multilingual Whisper base after layer N)",
    )
    p.set_defaults(func=_cmd_train_opening)

    p = sub.add_parser(
        "pretrain-renderer", help="pre-train a generic neural renderer on a folder of talking-head videos"
    )
    p.add_argument("corpus", type=Path, help="folder of talking-head videos")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (renderer.json/.npz)")
    p.add_argument(
        "--preset", choices=("cpu", "quality", "paper"), default=FitConfig.preset, help="renderer preset"
    )
    p.add_argument("--budget-minutes", type=float, default=45.0, help="training time (resumable)")
    p.add_argument("--steps", type=int, help="train this many steps instead of for a time")
    p.add_argument("--max-frames", type=int, default=MAX_FRAMES, help="frames kept per video (evenly spread)")
    p.add_argument("--exclude", nargs="*", help="file names to leave out")
    p.add_argument("--cache", type=Path, help="tracking/frame cache (default: next to OUTPUT)")
    _add_device_arg(p)
    p.set_defaults(func=_cmd_pretrain_renderer)

    p = sub.add_parser("person-map", help="learn a person's talking style (closed form) from their video")
    p.add_argument("video", type=Path, help="the person talking (video with audio)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output person map (.npz + .json)")
    p.add_argument(
        "--features", choices=("phonemes", "mel"), default=FitConfig.features, help="speech features"
    )
    p.add_argument("--cache", type=Path, help="tracking/feature cache folder")
    p.set_defaults(func=_cmd_person_map)

    p = sub.add_parser("predict", help="predict a person's expressions (and mesh) for new audio")
    p.add_argument("audio", type=Path, help="speech (wav, flac, mp3, m4a, or a video's audio track)")
    p.add_argument(
        "--style",
        type=Path,
        required=True,
        help="person bundle folder (nvp fit) or person map (nvp person-map)",
    )
    p.add_argument("--fps", type=float, default=25.0, help="output frame rate")
    p.add_argument(
        "--mesh",
        type=Path,
        metavar="TRACK_DIR",
        help="face to animate (default: the bundle's, else the mean face)",
    )
    p.add_argument("-o", "--output", type=Path, help="output .npz (expression; vertices with a face)")
    p.add_argument("--export", type=Path, help="output glTF 2.0 animation (.glb): morph targets + weights")
    p.set_defaults(func=_cmd_predict)

    p = sub.add_parser("train-renderer", help="train the neural renderer on a tracked video")
    p.add_argument("track_dir", type=Path, help="output of nvp track for the video")
    p.add_argument("video", type=Path, help="the tracked video")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (renderer.json/.npz)")
    _add_renderer_training_args(p)
    p.add_argument("--train-fraction", type=float, default=1.0, help="train on this first part of the video")
    _add_device_arg(p)
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--vgg-weights", type=Path, help="VGG-16 weights (torchvision .pth) for a perceptual loss")
    p.set_defaults(func=_cmd_train_renderer)

    p = sub.add_parser("render", help="re-render a tracked video with its trained renderer")
    p.add_argument("track_dir", type=Path, help="output of nvp track")
    p.add_argument("renderer_dir", type=Path, help="output of nvp train-renderer")
    p.add_argument("video", type=Path, help="the tracked video")
    p.add_argument("-o", "--output", type=Path, required=True, help="output mp4")
    p.add_argument("--start-frame", type=int, default=0, help="first frame to render")
    p.add_argument("--frames", type=int, help="number of frames (default: to the end)")
    _add_device_arg(p)
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("fit", help="learn a person from 1-3 minutes of their talking video")
    p.add_argument("video", type=Path, help="the person talking (video with audio)")
    p.add_argument("-o", "--output", type=Path, required=True, help="person bundle folder")
    _add_renderer_training_args(p)
    p.add_argument(
        "--features", choices=("phonemes", "mel"), default=FitConfig.features, help="speech features"
    )
    _add_device_arg(p)
    p.add_argument("--vgg-weights", type=Path, help="VGG-16 weights (torchvision .pth) for a perceptual loss")
    p.add_argument(
        "--force", action="store_true", help="replace a finished person bundle of another video at -o"
    )
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("dub", help="make a fitted person say new audio")
    p.add_argument(
        "audio",
        type=Path,
        nargs="*",
        help="speech: wav, flac, mp3, m4a (or a video's audio track); several ok",
    )
    p.add_argument("--list", type=Path, help="a text file naming more audio files, one per line")
    p.add_argument("--person", type=Path, required=True, help="person bundle from nvp fit")
    p.add_argument(
        "--transcript",
        type=Path,
        help="UTF-8 text file: what the audio says; its p, b and m close the lips (needs the tts extra)",
    )
    p.add_argument(
        "--language",
        default="en-us",
        help="the transcript's language, an espeak-ng voice name (en-us, fr, de, es, it, pt, hi, cmn, ...)",
    )
    p.add_argument(
        "-o", "--output", type=Path, required=True, help="output mp4 (a folder for several: <audio name>.mp4)"
    )
    _add_style_arg(p)
    _add_device_arg(p)
    p.set_defaults(func=_cmd_dub)

    p = sub.add_parser("say", help="make a fitted person say a text (offline text to speech, then dub)")
    p.add_argument("text", nargs="?", help="what the person says")
    p.add_argument("--person", type=Path, help="person bundle from nvp fit")
    p.add_argument("-o", "--output", type=Path, help="output mp4")
    p.add_argument(
        "--voice", help="piper voice: an installed voice's name (see --list-voices) or a .onnx voice file"
    )
    p.add_argument(
        "--engine",
        choices=("auto", "piper", "espeak-ng"),
        default="auto",
        help="speech engine (auto: piper when installed, else espeak-ng)",
    )
    p.add_argument("--slower", type=float, default=1.0, help="speaking slowness (>1 slower, <1 faster)")
    p.add_argument("--wav", type=Path, help="also keep the speech here")
    p.add_argument("--list-voices", action="store_true", help="list the installed piper voices and exit")
    _add_style_arg(p)
    _add_device_arg(p)
    p.set_defaults(func=_cmd_say)

    p = sub.add_parser("live", help="dub audio as it arrives (a file in real time, or raw PCM on stdin)")
    p.add_argument(
        "source", help="audio/video file played in real time, or - for raw s16le mono PCM on stdin"
    )
    p.add_argument("--person", type=Path, required=True, help="person bundle from nvp fit")
    p.add_argument("-o", "--output", type=Path, help="fragmented mp4, written as the frames are made")
    p.add_argument("--raw", action="store_true", help="raw RGB24 frames on stdout (for a player or a pipe)")
    p.add_argument("--rate", type=int, default=16000, help="sample rate of the PCM on stdin")
    p.add_argument(
        "--realtime",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="play a file at its real pace (--no-realtime: as fast as it can)",
    )
    p.add_argument(
        "--max-lag", type=float, default=1.0, help="seconds behind the audio after which frames are dropped"
    )
    _add_style_arg(p)
    _add_device_arg(p)
    p.set_defaults(func=_cmd_live)

    p = sub.add_parser("serve", help="a local web app and JSON API: fit people and dub them in a browser")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")
    p.add_argument("--port", type=int, default=7860, help="port")
    p.add_argument(
        "--data", type=Path, default=Path("nvp-data"), help="folder for people, uploads, dubs, jobs"
    )
    p.add_argument("--max-upload-mb", type=float, default=1024, help="largest upload accepted")
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("info", help="summarise a person bundle")
    p.add_argument("person", type=Path, help="person bundle folder")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser(
        "verify", help="check whether a video carries nvp's synthetic-media mark (exit 0 = yes)"
    )
    p.add_argument("video", type=Path, help="video file")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=_cmd_verify)

    p = sub.add_parser("eval", help="self-reenactment: fit on the first part of a video, re-create the rest")
    p.add_argument(
        "video", type=Path, nargs="+", help="talking-head videos with audio (≥ 5 s each; 1-3 min is best)"
    )
    p.add_argument(
        "-o", "--output", type=Path, help="output folder (one subfolder per video when given several)"
    )
    p.add_argument(
        "--train-fraction", type=float, default=EvalConfig.train_fraction, help="part used for fitting"
    )
    _add_renderer_training_args(p, budget_minutes=EvalConfig.budget_minutes)
    p.add_argument("--side-by-side", action="store_true", help="also write real | visual | audio video")
    _add_device_arg(p)
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("demo", help="make a talking person from a photo that ships with nvp, fit and dub it")
    p.add_argument("-o", "--output", type=Path, default=Path("nvp-demo"), help="output directory")
    p.add_argument(
        "--budget-minutes", type=float, default=8.0, help="renderer training time for the demo person"
    )
    p.set_defaults(func=_cmd_demo)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )
    from nvp.allocator import keep_freed_memory
    from nvp.errors import NvpError

    keep_freed_memory()
    try:
        return args.func(args)
    except NvpError as e:
        return _fail(args.command, f"error: {e}", 2)
    except KeyboardInterrupt:
        return _fail(args.command, "interrupted", 130)
    except OSError as e:  # permissions, a vanished file, a full disk outside nvp's own writers, ...
        from nvp.artifact import is_disk_full

        where = e.filename or "a file"
        what = f"disk full while writing {where}" if is_disk_full(e) else f"{e.strerror or e}: {where}"
        return _fail(args.command, f"error: {what}", 2)


def _fail(command: str, message: str, code: int) -> int:
    """Print the one error line on a line of its own (closing any progress bar first)."""
    tqdm = sys.modules.get("tqdm")
    if tqdm is not None:
        for bar in list(getattr(tqdm.tqdm, "_instances", ())):
            bar.close()
    print(f"nvp {command}: {message}", file=sys.stderr)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
