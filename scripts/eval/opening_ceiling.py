"""How much of each clip's mouth opening its own audio explains: a read-out fitted on the clip itself.

    python -m scripts.eval.opening_ceiling [--set test] [--cache /tmp/nvp-cache]

For every clip of the set (``scripts/data_split.json``), a ridge regression from the clip's own feature
windows (every other sample of the 16, as the opening model reads them; Whisper tiny.en states and the
phoneme recogniser's posteriors in turn) to its own tracked inner-lip gap is fitted on four of five
consecutive folds and predicts the fifth; the correlation of the held-out predictions with the gap, best of
:data:`RIDGES` (optimistic, the same for every clip). It knows nothing of other people: it learns the clip's
speaker, language and audio-video offset from the seconds the other folds hold. A clip where it stays near
zero has a mouth that does not follow its sound as the tracker sees it; one where nvp's generic model
(``scripts.eval.lipsync``) stays far below it has a speaker the generic model does not read. Prints a row
per clip and the mean per language.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from scripts.common import SHARED, SPLIT, data_missing

RIDGES = (0.3, 1.0, 3.0, 10.0, 30.0)
"""Ridge strengths, in units of the mean squared norm of the standardised training windows."""
FOLDS = 5


def in_clip_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """The best over :data:`RIDGES` of the correlation of ``y`` ``(n,)`` with its predictions from ``x``
    ``(n, d)``, each fold predicted by a ridge fitted on the others (features standardised on those)."""
    n = len(y)
    held = {r: np.zeros(n) for r in RIDGES}
    for test in np.array_split(np.arange(n), FOLDS):
        train = np.setdiff1d(np.arange(n), test)
        mu, sd = x[train].mean(0), x[train].std(0) + 1e-6
        a, b = (x[train] - mu) / sd, (x[test] - mu) / sd
        gram, mean = a @ a.T, y[train].mean()
        scale = np.trace(gram) / len(train)
        for r in RIDGES:  # the dual form: n is a few hundred frames, d thousands of features
            alpha = np.linalg.solve(gram + r * scale * np.eye(len(train)), y[train] - mean)
            held[r][test] = b @ a.T @ alpha + mean
    return max(float(np.corrcoef(held[r], y)[0, 1]) for r in RIDGES)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", default="test", choices=["test", "validation", "train"])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    args = ap.parse_args(argv)
    if data_missing():
        return 0
    from nvp.app.corpus import load_sample
    from nvp.face_model import default_face_model

    split = json.loads(SPLIT.read_text())
    language = {c: v["language"] for v in split["people"].values() for c in v["clips"]}
    model = default_face_model()
    kinds = ("whisper", "phonemes")
    per_language: dict[str, list[tuple[float, ...]]] = defaultdict(list)
    print("| clip | language | frames | " + " | ".join(f"in-clip, {k}" for k in kinds) + " |")
    print("|---" * (3 + len(kinds)) + "|")
    for clip in split[args.set]:
        path = next((p for p in (SHARED / "video" / clip, SHARED / "video_wide" / clip) if p.exists()), None)
        if path is None:
            print(f"{clip}: not in {SHARED}", file=sys.stderr)
            continue
        samples = [load_sample(path, args.cache, kind, progress=False) for kind in kinds]
        seq = samples[0].tracked
        valid = np.asarray(seq.valid, bool)
        gap = model.inner_lip_gap(seq.identity, seq.expression)[valid].astype(np.float64)
        corr = tuple(
            in_clip_correlation(s.windows[:, ::2].reshape(len(s.windows), -1)[valid].astype(np.float64), gap)
            for s in samples
        )
        lang = language.get(clip, "?")
        per_language[lang].append(corr)
        print(f"| {clip} | {lang} | {int(valid.sum())} | " + " | ".join(f"{c:.3f}" for c in corr) + " |")
    print("\n| language | clips | " + " | ".join(f"in-clip, {k}" for k in kinds) + " |")
    print("|---" * (2 + len(kinds)) + "|")
    for lang, rows in sorted(per_language.items()):
        means = np.mean(rows, axis=0)
        print(f"| {lang} | {len(rows)} | " + " | ".join(f"{m:.3f}" for m in means) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
