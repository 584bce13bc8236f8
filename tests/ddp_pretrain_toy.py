"""Pre-train the tiny renderer of test_renderer on two saved frame caches: run by test_renderer under plain
python (one process) and under ``torchrun --nproc_per_node 2`` (two), which must give the same run.

    python tests/ddp_pretrain_toy.py CACHE_DIR OUT_DIR
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from test_renderer import TINY  # noqa: E402

from nvp.app.distributed import process_group  # noqa: E402
from renderer.train import RendererTrainConfig, train_renderer  # noqa: E402
from renderer.train_data import FrameCache  # noqa: E402

if __name__ == "__main__":
    import torch

    torch.set_num_threads(1)
    caches = [FrameCache.load(p) for p in sorted(Path(sys.argv[1]).glob("*.json"))]
    cfg = RendererTrainConfig(steps=6, lr=3e-3, init=None, checkpoint_every=2, preview_every=10**6)
    train_renderer(caches, cfg, Path(sys.argv[2]), progress=False, preset=TINY, group=process_group())
