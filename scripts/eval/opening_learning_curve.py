"""How the generic opening model's validation correlation grows with its training data.

    python -m scripts.eval.opening_learning_curve [--cache /tmp/nvp-cache] [--repeats 3]

The shipped recipe (``nvp train-opening``: a ridge read-out of Whisper windows, :mod:`nvp.opening`, its
ridge the best of :data:`nvp.app.train_opening.RIDGES` on the validation people) fitted on 25 / 50 / 75 /
100 % of the training clips of ``scripts/data_split.json`` plus ``../shared/data/video_wide`` (random
subsets, ``--repeats`` draws each, fixed seed), scored by the mean correlation with the tracked inner-lip
gap over the validation people's whole clips (:func:`nvp.app.train_opening.correlations`). A curve that has
flattened says more clips of the same kind will not lift the read-out much; the test people are never read.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from scripts.common import SHARED, SPLIT, data_missing

FRACTIONS = (0.25, 0.5, 0.75, 1.0)


def main(argv: list[str] | None = None) -> int:
    from nvp.app.corpus import load_sample
    from nvp.app.train_opening import RIDGES, correlations, opening_targets
    from nvp.face_model import default_face_model
    from nvp.opening import FEATURE_KIND, normal_equations

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", type=Path, default=SPLIT)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nvp-cache"))
    ap.add_argument("--repeats", type=int, default=3, help="random subsets per fraction below 100 %%")
    args = ap.parse_args(argv)
    if data_missing(SHARED):
        return 0
    split = json.loads(args.split.read_text())
    model = default_face_model()

    def samples(paths: list[Path]) -> list:
        return [load_sample(p, args.cache, FEATURE_KIND, progress=False) for p in paths]

    train = samples([SHARED / "video" / n for n in split["train"]])
    train += samples(sorted((SHARED / "video_wide").glob("*.mp4")))
    val = samples([SHARED / "video" / n for n in split["validation"]])
    targets = [opening_targets(s, model) for s in train]
    rng = np.random.default_rng(0)
    print("| training clips | frames (mean) | validation correlation (mean of draws) | draws |")
    print("|---|---|---|---|")
    for fraction in FRACTIONS:
        draws, frames = [], []
        for _ in range(args.repeats if fraction < 1 else 1):
            pick = rng.permutation(len(train))[: max(1, round(fraction * len(train)))]
            sums = normal_equations((train[i].windows for i in pick), [targets[i] for i in pick])
            best = max(np.mean(list(correlations(sums.solve(r), val, model).values())) for r in RIDGES)
            draws.append(float(best))
            frames.append(int(sum(train[i].valid.sum() for i in pick)))
        shown = ", ".join(f"{d:.3f}" for d in draws)
        print(f"| {len(pick)} of {len(train)} | {np.mean(frames):,.0f} | {np.mean(draws):.3f} | {shown} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
