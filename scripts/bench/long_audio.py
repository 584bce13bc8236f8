"""What predicting a long dub's expressions in blocks (``nvp.long_audio``) costs and changes.

    python -m scripts.bench.long_audio [AUDIO ...] [--person PERSON_DIR] [--minutes 6]
                                       [--block 120] [--contexts 0 2 5 10]
    python -m scripts.bench.long_audio --footage CLIP ... [--cache /tmp/nvp-cache] [--block 3]

The audio files (any format; default: nvp's synthetic voice) are mixed to 16 kHz mono and joined, one after
the other and repeated, to ``--minutes``. Their expressions are predicted for the person (default: a bundle
made from nvp's demo target, as ``scripts.bench.dub`` makes it) as a whole file
(``nvp.person.predict_expressions``) and in blocks of ``--block`` seconds with each ``--contexts`` value.
Prints the CPU, then per way the compute time and how far its mouth is from the whole file's: the
correlation of the inner-lip gap (cm, the face model's), the median and largest difference of the gap and
the share of frames that differ by more than 0.05 cm, over all frames and over the frames within 2 s of a
block's edge, and the largest frame-to-frame step of the gap at an edge (the whole file's 99th percentile
of steps is printed above). The first row is the yardstick: the whole-file prediction of the same audio
with its last second cut, on the frames both have (the whole file's own dependence on its length).

``--footage``: against real mouths instead. Each clip's person is fitted on the whole clip (tracking and
features cached under ``--cache``; its style as ``nvp fit`` makes it), then its own audio is predicted as a
whole and in blocks of ``--block`` seconds (short, so that clips of a few seconds have edges) with each
``--contexts`` value; prints the correlation of each with the clip's tracked inner-lip gap.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from scripts.bench.dub import cpu_name, demo_person

EDGE_S = 2.0
"""Frames within this many seconds of a block's edge are also reported apart."""
DIFFERS_CM = 0.05
"""A frame whose inner-lip gap differs by more than this (cm) counts as changed."""


def joined_audio(files: list[Path], minutes: float) -> np.ndarray:
    """The files' 16 kHz mono audio one after the other, repeated or cut to ``minutes``."""
    from nvp.media import read_audio

    if files:
        parts = [read_audio(f, sample_rate=16000) for f in files]
    else:
        from nvp.app.demo_voice import speech_script, synth_voice

        rng = np.random.default_rng(3)
        parts = [synth_voice(speech_script(20.0, rng), 20.0, rng, 16000).astype(np.float32)]
    one = np.concatenate(parts)
    n = int(minutes * 60 * 16000)
    return np.tile(one, int(np.ceil(n / len(one))))[:n]


def compare(gap: np.ndarray, ref: np.ndarray, edges: np.ndarray, fps: float) -> str:
    """One row's figures: ``gap`` against ``ref`` over all frames and near ``edges`` (frame indices)."""
    d = np.abs(gap - ref)
    near = np.zeros(len(d), bool)
    for e in edges:
        near[max(0, e - int(EDGE_S * fps)) : e + int(EDGE_S * fps)] = True

    def figures(mask: np.ndarray) -> str:
        if not mask.any():
            return "— | — | — | —"
        r = np.corrcoef(gap[mask], ref[mask])[0, 1]
        return (
            f"{r:.4f} | {np.median(d[mask]):.4f} | {d[mask].max():.3f} | {np.mean(d[mask] > DIFFERS_CM):.3%}"
        )

    steps = np.abs(np.diff(gap))[edges - 1] if len(edges) else np.zeros(1)
    return f"{figures(np.ones(len(d), bool))} | {figures(near)} | {steps.max():.3f}"


def footage(clips: list[Path], cache: Path, block: float, contexts: list[float]) -> None:
    """The ``--footage`` table (see the module docstring)."""
    import dataclasses

    from nvp.app.corpus import load_sample
    from nvp.audio2exp import default_audio2exp
    from nvp.face_model import default_face_model
    from nvp.long_audio import BlockedExpressions
    from nvp.media import read_audio
    from nvp.opening import default_opening_model
    from nvp.person import predict_expressions, style_from_sample, voiced_frames

    net, manifest = default_audio2exp("phonemes")
    opening, model = default_opening_model(), default_face_model()
    print(f"blocks of {block:g} s; correlation of the inner-lip gap with the footage's (valid frames)\n")
    print("| clip | frames | whole file | " + " | ".join(f"blocks, context {c:g} s" for c in contexts) + " |")
    print("|---" * (3 + len(contexts)) + "|")
    sums = np.zeros(1 + len(contexts))
    for clip in clips:
        s = load_sample(clip, cache, "phonemes", progress=False)
        ow = load_sample(clip, cache, opening.feature_kind, progress=False).windows
        seq = s.tracked
        voiced = voiced_frames(clip, seq.fps, seq.num_frames)
        sample = dataclasses.replace(s, opening_windows=ow)
        style = style_from_sample(net, manifest, sample, model, voiced=voiced, opening=opening)
        audio, n = read_audio(clip, 16000), seq.num_frames
        ways = [predict_expressions(audio, 16000, seq.fps, style, net, num_frames=n)]
        for context in contexts:
            stream = BlockedExpressions(style, net, seq.fps, block_s=block, context_s=context)
            for at in range(0, len(audio), 4096):
                stream.push(audio[at : at + 4096])
            ways.append(stream.finish(n))
        real = model.inner_lip_gap(seq.identity, seq.expression)[seq.valid]
        corr = [np.corrcoef(model.inner_lip_gap(seq.identity, e)[seq.valid], real)[0, 1] for e in ways]
        sums += corr
        print(
            f"| {clip.name} | {int(seq.valid.sum())} | " + " | ".join(f"{c:.3f}" for c in corr) + " |",
            flush=True,
        )
    print(f"| mean of {len(clips)} | | " + " | ".join(f"{c:.3f}" for c in sums / len(clips)) + " |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("audio", type=Path, nargs="*")
    ap.add_argument("--person", type=Path)
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--block", type=float, default=None, help="seconds (default nvp.long_audio.BLOCK_S)")
    ap.add_argument("--contexts", type=float, nargs="+", default=None, help="seconds (default CONTEXT_S)")
    ap.add_argument("--footage", type=Path, nargs="+", help="clips of real footage (see the docstring)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    args = ap.parse_args(argv)
    from nvp.app.dub import load_person
    from nvp.bundle import PersonBundle
    from nvp.long_audio import BLOCK_S, CONTEXT_S, BlockedExpressions
    from nvp.person import predict_expressions

    contexts = [CONTEXT_S] if args.contexts is None else args.contexts
    if args.footage:
        print(f"# bench_long_audio --footage ({cpu_name()}, {os.cpu_count()} CPUs)")
        footage(args.footage, args.cache, 3.0 if args.block is None else args.block, contexts)
        return 0
    block = BLOCK_S if args.block is None else args.block
    audio = joined_audio(args.audio, args.minutes)
    print(f"# bench_long_audio ({cpu_name()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f})")
    source = f"{len(args.audio)} file(s)" if args.audio else "synthetic voice"
    print(f"{len(audio) / 16000 / 60:.1f} min of audio ({source}), blocks of {block:g} s")
    with tempfile.TemporaryDirectory() as tmp:
        person = load_person(PersonBundle.load(args.person or demo_person(Path(tmp), 256)))
        style, net, fps = person.style, person.net, person.tracked.fps
        ident = np.zeros(person.model.num_id, np.float32)
        t0 = time.process_time()
        whole = predict_expressions(audio, 16000, fps, style, net)
        whole_s = time.process_time() - t0
        ref = person.model.inner_lip_gap(ident, whole)
        steps = np.abs(np.diff(ref))
        print(f"the whole file's gap, frame to frame: steps' 99th percentile {np.percentile(steps, 99):.3f}")
        n = len(whole)
        edges = np.arange(int(round(block * fps)), n, int(round(block * fps)))
        head = "way | CPU s | corr | median diff | largest | frames > 0.05 cm | near edges: corr | median"
        print(f"| {head} | largest | > 0.05 cm | largest step at an edge |\n" + "|---" * 11 + "|")
        cut = predict_expressions(audio[:-16000], 16000, fps, style, net)
        m = len(cut)
        row = compare(person.model.inner_lip_gap(ident, cut), ref[:m], edges[edges < m], fps)
        print(f"| whole file, last second cut | — | {row} |")
        print(f"| whole file | {whole_s:.1f} | 1 | 0 | 0 | 0 | | | | | {steps[edges - 1].max():.3f} |")
        for context in contexts:
            stream = BlockedExpressions(style, net, fps, block_s=block, context_s=context)
            t0 = time.process_time()
            for at in range(0, len(audio), 4096):  # pieces as the decoder gives them
                stream.push(audio[at : at + 4096])
            parts = stream.finish(n)
            seconds = time.process_time() - t0
            gap = person.model.inner_lip_gap(ident, parts)
            row = compare(gap, ref, edges, fps)
            print(f"| blocks, context {context:g} s | {seconds:.1f} | {row} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
