"""Audio-driven face animation as glTF 2.0 (``nvp predict --export anim.glb``), for any 3D pipeline.

One mesh (the person's neutral face, or the face model's mean face) with one morph target per expression
coefficient (the expression basis) and one animation of the morph weights, a keyframe per video frame:
keyframe ``j`` is at ``j / fps`` seconds, where second 0 is the first sample of the audio, so the
animation plays in sync when it starts with the audio. Weights are the expression coefficients: signed and
roughly standard normal (|w| up to about 4), not limited to [0, 1].

Coordinates follow glTF: metres, +Y up, +Z towards the viewer (the face looks along +Z); the face model's
camera frame (cm, +Y down, +Z away from the camera) is turned 180° about X. Written and read with
pygltflib.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nvp.errors import FormatError

CM_TO_GLTF = np.array([0.01, -0.01, -0.01], np.float32)
"""Face-model camera frame (cm; x right, y down, z away) → glTF (m; x right, y up, z towards the viewer)."""


EYE_NODES = ("eye_left", "eye_right")
"""Names of the two eye nodes whose rotations carry the gaze."""


@dataclass(frozen=True)
class MorphAnimation:
    """A mesh animated by morph targets.

    Attributes:
        base: ``(V, 3)`` float32 vertices with all weights 0 (glTF frame and units).
        targets: ``(K, V, 3)`` float32 displacement of each morph target at weight 1.
        triangles: ``(F, 3)`` int64 vertex indices, counter-clockwise seen from the front.
        weights: ``(T, K)`` float32 morph weights of each keyframe.
        fps: keyframes per second (keyframe ``j`` at ``j / fps`` s).
        target_names: ``K`` names.
        info: provenance, stored as the file's ``asset.extras``.
        eyes: ``(2, 3)`` float32 rotation centres of the left and right eye (glTF frame), None: no eyes.
        gaze: ``(T, 2)`` float32 yaw and pitch (radians, :mod:`nvp.gaze`) of both eyes at each keyframe,
            written as the rotations of two nodes ``eye_left`` / ``eye_right`` (children of the face) that
            a rig can bind its eyeballs to.
    """

    base: np.ndarray
    targets: np.ndarray
    triangles: np.ndarray
    weights: np.ndarray
    fps: float
    target_names: tuple[str, ...]
    info: dict
    eyes: np.ndarray | None = None
    gaze: np.ndarray | None = None

    def vertices(self, frame: int) -> np.ndarray:
        """``(V, 3)`` vertices of keyframe ``frame``."""
        return self.base + np.einsum("k,kvc->vc", self.weights[frame], self.targets)


def face_animation(
    template: np.ndarray,
    exp_basis: np.ndarray,
    triangles: np.ndarray,
    expression: np.ndarray,
    fps: float,
    info: dict,
    eyes: np.ndarray | None = None,
    gaze: np.ndarray | None = None,
) -> MorphAnimation:
    """The animation of face-model ``expression`` ``(T, K_exp)`` on the neutral face ``template``
    ``(V, 3)`` (face-model frame, cm; e.g. ``FaceModel.vertices(identity)``), morph targets from
    ``exp_basis`` ``(K_exp, V, 3)``; ``triangles`` ``(F, 3)`` (the turn about X keeps them
    counter-clockwise seen from the front, as glTF wants); ``eyes`` ``(2, 3)`` the eyes' rotation centres
    (face-model frame, :func:`nvp.gaze.eye_centres`) and ``gaze`` ``(T, 2)`` their yaw and pitch."""
    return MorphAnimation(
        base=(template * CM_TO_GLTF).astype(np.float32),
        targets=(exp_basis * CM_TO_GLTF).astype(np.float32),
        triangles=np.asarray(triangles).astype(np.int64),
        weights=np.asarray(expression, np.float32),
        fps=float(fps),
        target_names=tuple(f"expression_{k:02d}" for k in range(exp_basis.shape[0])),
        info=info,
        eyes=None if eyes is None else (np.asarray(eyes) * CM_TO_GLTF).astype(np.float32),
        gaze=None if gaze is None else np.asarray(gaze, np.float32),
    )


def write_glb(anim: MorphAnimation, path: Path) -> Path:
    """Write ``anim`` as a binary glTF (``.glb``) file (atomically)."""
    import pygltflib as g

    from nvp.artifact import atomic_path

    t, k = anim.weights.shape
    times = (np.arange(t) / anim.fps).astype(np.float32)
    blobs: list[bytes] = []
    views: list[g.BufferView] = []
    accessors: list[g.Accessor] = []

    def add(array: np.ndarray, kind: str, component: int, target: int | None, minmax: bool) -> int:
        data = np.ascontiguousarray(array).tobytes()
        offset = sum(len(b) for b in blobs)
        blobs.append(data + b"\0" * (-len(data) % 4))
        views.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=len(data), target=target))
        flat = array.reshape(len(array), -1)
        acc = g.Accessor(
            bufferView=len(views) - 1,
            componentType=component,
            count=len(array),
            type=kind,
            min=flat.min(0).tolist() if minmax else None,
            max=flat.max(0).tolist() if minmax else None,
        )
        accessors.append(acc)
        return len(accessors) - 1

    pos = add(anim.base, g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True)
    idx = add(
        anim.triangles.astype(np.uint32).reshape(-1, 1),
        g.SCALAR,
        g.UNSIGNED_INT,
        g.ELEMENT_ARRAY_BUFFER,
        False,
    )
    morphs = [{"POSITION": add(d, g.VEC3, g.FLOAT, g.ARRAY_BUFFER, True)} for d in anim.targets]
    key_in = add(times.reshape(-1, 1), g.SCALAR, g.FLOAT, None, True)
    key_out = add(anim.weights.reshape(-1, 1), g.SCALAR, g.FLOAT, None, False)
    samplers = [g.AnimationSampler(input=key_in, output=key_out, interpolation="LINEAR")]
    channels = [g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=0, path="weights"))]
    nodes = [g.Node(mesh=0, name="face")]
    if anim.eyes is not None and anim.gaze is not None:
        from nvp.gaze import gaze_quaternions

        turn = add(gaze_quaternions(anim.gaze), g.VEC4, g.FLOAT, None, False)
        samplers.append(g.AnimationSampler(input=key_in, output=turn, interpolation="LINEAR"))
        for name, centre in zip(EYE_NODES, anim.eyes, strict=True):
            nodes[0].children.append(len(nodes))
            nodes.append(g.Node(name=name, translation=[float(c) for c in centre]))
            target = g.AnimationChannelTarget(node=len(nodes) - 1, path="rotation")
            channels.append(g.AnimationChannel(sampler=1, target=target))
    blob = b"".join(blobs)
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="nvp", extras=anim.info),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=nodes,
        meshes=[
            g.Mesh(
                name="face",
                primitives=[
                    g.Primitive(
                        attributes=g.Attributes(POSITION=pos), indices=idx, targets=morphs, mode=g.TRIANGLES
                    )
                ],
                weights=[0.0] * k,
                extras={"targetNames": list(anim.target_names)},
            )
        ],
        animations=[g.Animation(name="speech", samplers=samplers, channels=channels)],
        buffers=[g.Buffer(byteLength=len(blob))],
        bufferViews=views,
        accessors=accessors,
    )
    gltf.set_binary_blob(blob)
    path = Path(path)
    with atomic_path(path) as tmp:
        gltf.save_binary(str(tmp))
    return path


def read_glb(path: Path) -> MorphAnimation:
    """Read an animation written by :func:`write_glb` (or any glTF with one morph-animated mesh)."""
    import pygltflib as g

    try:
        gltf = g.GLTF2().load(str(path))
    except Exception as e:  # pygltflib raises many kinds on a damaged file
        raise FormatError(f"{path} is not a readable glTF file: {e}") from e
    if gltf is None or not gltf.meshes or not gltf.animations:
        raise FormatError(f"{path} holds no animated mesh")
    blob = gltf.binary_blob()
    sizes = {g.FLOAT: np.float32, g.UNSIGNED_INT: np.uint32, g.UNSIGNED_SHORT: np.uint16}
    width = {g.SCALAR: 1, g.VEC3: 3, g.VEC4: 4}

    def read(i: int) -> np.ndarray:
        acc = gltf.accessors[i]
        view = gltf.bufferViews[acc.bufferView]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        n = acc.count * width[acc.type]
        return np.frombuffer(blob, sizes[acc.componentType], n, start).reshape(acc.count, width[acc.type])

    prim = gltf.meshes[0].primitives[0]
    sampler = gltf.animations[0].samplers[0]
    times = read(sampler.input)[:, 0]
    targets = np.stack([read(m["POSITION"]) for m in prim.targets])
    weights = read(sampler.output).reshape(len(times), len(targets))
    fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else float("nan")
    names = (gltf.meshes[0].extras or {}).get("targetNames", [f"target_{i}" for i in range(len(targets))])
    eyes, gaze = None, None
    found = {n.name: i for i, n in enumerate(gltf.nodes) if n.name in EYE_NODES}
    turns = {c.target.node: c.sampler for c in gltf.animations[0].channels if c.target.path == "rotation"}
    if set(found) == set(EYE_NODES) and all(found[n] in turns for n in EYE_NODES):
        from nvp.gaze import gaze_direction

        eyes = np.array([gltf.nodes[found[n]].translation for n in EYE_NODES], np.float32)
        gaze = gaze_direction(read(gltf.animations[0].samplers[turns[found[EYE_NODES[0]]]].output))
    return MorphAnimation(
        base=read(prim.attributes.POSITION).astype(np.float32),
        targets=targets.astype(np.float32),
        triangles=read(prim.indices).reshape(-1, 3).astype(np.int64),
        weights=weights.astype(np.float32),
        fps=fps,
        target_names=tuple(names),
        info=dict(gltf.asset.extras or {}),
        eyes=eyes,
        gaze=gaze,
    )
