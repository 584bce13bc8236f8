"""What the scripts share: where the repository, the team's data and the fixed data split are."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The repository."""

SHARED = ROOT.parent / "shared" / "data"
"""The team's data beside the repository: ``video/`` (talking heads), ``video_wide/``, ``audio/`` (speech)."""

VIDEOS = SHARED / "video"
"""The talking-head videos the evaluations read."""

SPLIT = ROOT / "scripts" / "data_split.json"
"""The fixed train / validation / test split of the real videos by person."""
