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


def data_missing(folder: Path = SHARED) -> bool:
    """True, saying so, when ``folder`` of the team's data is not there (an evaluation then has nothing to
    read and ends at once, successfully: a fresh clone without the data is not an error)."""
    if folder.is_dir():
        return False
    print(f"no evaluation data: {folder} does not exist")
    return True
