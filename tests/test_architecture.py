"""Import rules from DESIGN.md, checked on the source tree."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# nvp modules that are allowed to reach into tracking/renderer (pipeline level and the CLI)
PIPELINE = {"cli.py", "demo.py", "pipeline.py", "corpus.py", "evaluate.py"}


def imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_core_imports_neither_tracking_nor_renderer():
    for path in (ROOT / "nvp").rglob("*.py"):
        if path.name in PIPELINE:
            continue
        bad = imported_packages(path) & {"tracking", "renderer", "scripts"}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_renderer_never_imports_tracking():
    for path in (ROOT / "renderer").rglob("*.py"):
        assert "tracking" not in imported_packages(path), path


def test_packages_never_import_scripts():
    for pkg in ("nvp", "tracking", "renderer"):
        for path in (ROOT / pkg).rglob("*.py"):
            assert "scripts" not in imported_packages(path), path


def test_help_is_instant_no_heavy_imports():
    code = "import sys, nvp.cli; print(sorted({'torch','mediapipe','av','cv2'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
