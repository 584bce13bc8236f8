"""Markdown tables for evaluation and benchmark reports."""

from __future__ import annotations

import json
from pathlib import Path


def markdown_table(rows: list[dict], cols: list[str] | None = None, digits: int = 4) -> str:
    """A markdown table of ``rows`` (dicts) with columns ``cols`` (default: the first row's keys); floats
    are printed with ``digits`` decimals."""
    cols = cols or list(rows[0])
    out = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    for r in rows:
        cells = (f"{r[c]:.{digits}f}" if isinstance(r[c], float) else str(r[c]) for c in cols)
        out += "| " + " | ".join(cells) + " |\n"
    return out


def write_results(rows: list[dict], out_dir: Path, digits: int = 3) -> str:
    """Write ``results.md`` (markdown table) and ``results.json`` into ``out_dir``; returns the table."""
    text = markdown_table(rows, digits=digits)
    (out_dir / "results.md").write_text(text)
    (out_dir / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    return text
