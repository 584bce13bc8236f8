"""``nvp info``: a person bundle summarised, every file it lists checked."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from nvp.bundle import PersonBundle
from nvp.person import PersonStyle
from nvp.tracked import TrackedSequence


def _eyes(seq: TrackedSequence) -> str:
    """What ``--gaze`` can do with a person: their tracking's iris (size) or why not."""
    from nvp.gaze import iris_size
    from renderer.eyes import MIN_IRIS_PX

    if seq.iris is None:
        return "no iris in the tracking (fitted before nvp measured gaze; a new nvp fit adds it for --gaze)"
    radius = iris_size(seq)
    if radius < MIN_IRIS_PX:
        return f"iris {radius:.1f} px: too small to turn with --gaze (needs {MIN_IRIS_PX:.0f} px)"
    return f"iris {radius:.1f} px: --gaze camera turns them into the lens"


def bundle_summary(path: Path) -> Iterator[str]:
    """The lines of ``nvp info`` for the person bundle at ``path``, one by one: its format, target video,
    features and preset, talking style, stages and files (every file the bundle lists is checked first,
    at the size and sha256 the fit wrote; a damaged one raises)."""
    b = PersonBundle.load(path, verify=False)
    checked = b.check()  # every file the bundle lists, at the size and sha256 the fit wrote
    m = b.manifest
    t = m["target"]
    yield f"person bundle {b.root} (format {m['format']} v{m['version']}, made by nvp {m['nvp_version']})"
    yield (
        f"  target: {Path(t['source']).name}, {t['width']}x{t['height']}, {t['fps']:.3f} fps, "
        f"{t['frames']} frames ({t['duration_s']:.1f} s)"
    )
    yield f"  speech features: {m['feature_kind']}; renderer preset: {m['preset']}"
    style = PersonStyle.load(b.path("style"))
    opening = style.info.get("opening", "none (fitted before nvp's opening model)")
    opening = "calibrated" if style.opening else opening
    yield f"  talking style: rest mouth from {style.info.get('rest', '?')}; mouth-opening model: {opening}"
    yield f"  eyes: {_eyes(TrackedSequence.load(b.path('tracked')))}"
    for name, facts in m["stages"].items():
        extra = ", ".join(f"{k} {v}" for k, v in facts.items() if k != "seconds")
        yield f"  {name}: {facts.get('seconds', 0):.1f} s" + (f" ({extra})" if extra else "")
    yield f"  files: {checked} checked, each at the size and sha256 the fit wrote"
