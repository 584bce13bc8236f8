"""Markdown tables for evaluation and benchmark reports."""

from __future__ import annotations


def markdown_table(rows: list[dict], cols: list[str] | None = None, digits: int = 4) -> str:
    """A markdown table of ``rows`` (dicts) with columns ``cols`` (default: the first row's keys); floats
    are printed with ``digits`` decimals."""
    cols = cols or list(rows[0])
    out = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    for r in rows:
        cells = (f"{r[c]:.{digits}f}" if isinstance(r[c], float) else str(r[c]) for c in cols)
        out += "| " + " | ".join(cells) + " |\n"
    return out
