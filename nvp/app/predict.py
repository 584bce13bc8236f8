"""``nvp predict``: a person's expressions (and their mesh, or a glTF animation) for new audio."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nvp.app.dub import load_person, load_style
from nvp.artifact import atomic_path, check_output_file
from nvp.audio2exp import default_audio2exp
from nvp.bundle import PersonBundle, check_output_place
from nvp.errors import NvpError
from nvp.face_model import default_face_model
from nvp.gaze import read_gaze_file
from nvp.media import read_audio
from nvp.person import predict_expressions
from nvp.tracked import TrackedSequence


def predict(
    audio: Path,
    style_path: Path,
    fps: float,
    mesh: Path | None = None,
    output: Path | None = None,
    export: Path | None = None,
    gaze: str | Path = "camera",
) -> tuple[int, str, list[Path]]:
    """Predict the expressions of the person of ``style_path`` (a person bundle folder or a person-map
    ``.json``) for ``audio`` at ``fps``; write them to ``output`` (``.npz``: expression, and vertices and
    triangles when a face is known) and/or ``export`` (a glTF 2.0 ``.glb`` animation). The face is
    ``mesh``'s (a tracked sequence folder), else the bundle's, else the face model's mean face.

    The upper face, which audio does not decide, moves as the person's does in their footage when the style
    knows it (their blinks at their rate, their brows with the speech's emphasis:
    :func:`nvp.person.predict_expressions` with ``upper_face``); the export's two eye
    nodes look as ``gaze`` asks (``"camera"`` or a gaze file, :mod:`nvp.gaze`).

    Returns the number of frames, whose face it is and the files written.
    """
    if output is None and export is None:
        raise NvpError("give -o (expressions .npz) and/or --export (animation .glb)")
    outputs = [check_output_file(p, inputs=(audio, style_path)) for p in (output, export) if p]
    for out in outputs:  # never over an input, nor inside a person bundle
        check_output_place(out, (audio, style_path, mesh))
    if export is not None and export.suffix.lower() != ".glb":
        raise NvpError(f"--export writes binary glTF: name the file .glb, not {export.name}")
    model = default_face_model()
    identity, whose = np.zeros(model.num_id, np.float32), "the face model's mean face"
    track = mesh
    if style_path.is_dir():  # a person bundle: its style, checked against the network, and its face
        person = load_person(PersonBundle.load(style_path))
        style, net = person.style, person.net
        if track is None:
            identity, whose = person.tracked.identity, f"the face of {style_path}"
    else:
        style = load_style(style_path)
        net, manifest = default_audio2exp(style.feature_kind)
        if manifest["sha256"] != style.audio2exp_sha256:
            raise NvpError(
                f"{style_path} was made with another Audio2ExpressionNet; rebuild it (nvp person-map)"
            )
    if track is not None:
        identity, whose = TrackedSequence.load(Path(track)).identity, f"the face of {track}"
    face_given = track is not None or style_path.is_dir()
    gaze_file = None if str(gaze) == "camera" else Path(gaze)
    if gaze_file is not None:
        read_gaze_file(gaze_file)  # a bad file is refused before any work
    samples = read_audio(audio, 16000)
    expr = predict_expressions(samples, 16000, fps, style, net, upper_face=True)
    if output is not None:
        out = {"expression": expr.astype(np.float32), "fps": np.float32(fps)}
        if face_given:
            out["vertices"] = model.vertices(identity, expr).astype(np.float32)
            out["triangles"] = model.triangles
        with atomic_path(outputs[0]) as tmp:
            np.savez_compressed(tmp, **out)
    if export is not None:
        from nvp.gaze import eye_centres, eye_loops, gaze_track
        from nvp.gltf import face_animation, write_glb

        face = model.vertices(identity)

        info = {
            "nvp": "audio-driven face animation (Neural Voice Puppetry)",
            "audio": Path(audio).name,
            "fps": fps,
            "timing": "keyframe j at j / fps seconds; second 0 = the first audio sample",
            "face": whose,
            "style": str(style.info.get("video", style_path)),
        }
        write_glb(
            face_animation(
                face,
                model.exp_basis,
                model.triangles,
                expr,
                fps,
                info,
                eye_centres(face, eye_loops(model)),
                gaze_track(gaze, len(expr), fps),
            ),
            outputs[-1],
        )
    return len(expr), whose, outputs
