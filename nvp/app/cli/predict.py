"""``nvp predict``: a person's expressions (and mesh, or a glTF animation) for new audio."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
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
