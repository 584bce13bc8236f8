"""Train the Audio2ExpressionNet on the toy corpus of test_audio2exp: run by test_audio2exp under plain
python (one process) and under ``torchrun --nproc_per_node 2`` (two), which must give the same loss curve.

    python tests/ddp_train_toy.py OUT_DIR
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from test_audio2exp import CFG, fake_sample  # noqa: E402

from nvp.app.train_audio2exp import Audio2ExpTrainConfig, train  # noqa: E402
from nvp.face_model import default_face_model  # noqa: E402

if __name__ == "__main__":
    import torch

    torch.set_num_threads(1)
    model = default_face_model()
    train_set = [fake_sample(model, f"v{i}", i) for i in range(3)]
    val_set = [fake_sample(model, "val", 9)]
    cfg = Audio2ExpTrainConfig(steps=20, batch=16, lr=3e-3, val_every=5, feature_noise=0.3, net=CFG)
    train(train_set, val_set, model, cfg, Path(sys.argv[1]), progress=False)
