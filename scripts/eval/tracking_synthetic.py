"""Tracker accuracy on synthetic sequences with known identity, pose and expression (numbers for the notes).

    python -m scripts.eval.tracking_synthetic

Sequences are made from the face model (tracking.synthetic), projected with a 1024 px focal length onto a
512² image with Gaussian landmark noise; the tracker sees only the 2D landmarks. Reported: mean vertex error
as a fraction of face width (camera frame, centroid and depth normalised, as in tests/test_fit.py), the
correlation of the recovered mouth opening with the truth, the median reprojection error and the estimated
focal length.
"""

from __future__ import annotations

import numpy as np

from nvp.face_model import default_face_model
from tracking.synthetic import synthetic_sequence
from tracking.track import fit_detections


def normalised(cam: np.ndarray) -> np.ndarray:
    return (cam - cam.mean(1, keepdims=True)) / cam[..., 2:3].mean(1, keepdims=True)


def main() -> None:
    model = default_face_model()
    print("| noise px | seed | vertex err / face width | mouth corr | median reproj px | focal (true 1024) |")
    print("|---|---|---|---|---|---|")
    for noise in (0.5, 1.0, 2.0):
        for seed in (0, 1, 2):
            det, truth = synthetic_sequence(model, frames=100, noise_px=noise, seed=seed)
            seq = fit_detections(det, model)
            verts = model.vertices(seq.identity, seq.expression)
            cam = np.einsum("tij,tvj->tvi", seq.rotation, verts) + seq.translation[:, None]
            cam_t = (
                np.einsum("tij,tvj->tvi", truth["rotation"], truth["vertices"])
                + truth["translation"][:, None]
            )
            err = np.linalg.norm(normalised(cam) - normalised(cam_t), axis=-1).mean()
            width = model.face_width(truth["identity"]) / truth["translation"][:, 2].mean()
            gap = np.linalg.norm(verts[:, 13] - verts[:, 14], axis=-1)
            gap_t = np.linalg.norm(truth["vertices"][:, 13] - truth["vertices"][:, 14], axis=-1)
            corr = np.corrcoef(gap, gap_t)[0, 1]
            print(
                f"| {noise} | {seed} | {err / width:.4f} | {corr:.3f} | {np.median(seq.fit_error):.2f} | "
                f"{seq.focal:.0f} |"
            )


if __name__ == "__main__":
    main()
