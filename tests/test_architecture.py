"""Import rules of docs/architecture.md, checked on the source tree with no allow-list.

Floors, arrows only downward:

| floor  | packages                 | may import                                   |
|--------|--------------------------|----------------------------------------------|
| roof   | ``nvp.app``              | everything below                             |
| middle | ``tracking``             | ``nvp`` core, ``renderer.raster``            |
| middle | ``renderer``             | ``nvp`` core                                 |
| ground | ``nvp`` (not ``nvp.app``) | ``nvp`` core only                            |

Every import statement counts, at module level or inside a function. On top of that, each module is
imported in a fresh interpreter and the modules it drags in (indirectly, through module-level imports)
must obey the same rules. Inference code never imports training code (``train*`` modules).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("nvp", "tracking", "renderer")


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def imports_of(path: Path, name: str | None = None) -> set[str]:
    """Absolute module names imported anywhere in ``path`` (relative imports resolved).

    ``name``: the module's name when ``path`` is not in the source tree (default: from its place there)."""
    tree = ast.parse(path.read_text())
    here = (name or module_name(path)).split(".")
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = here if path.name == "__init__.py" else here[:-1]
                base = ".".join(pkg[: len(pkg) - node.level + 1] + ([base] if base else []))
            names.add(base)
            names |= {f"{base}.{a.name}" for a in node.names}  # `from nvp.app import fit` is nvp.app.fit
    return names


def floor(module: str) -> str | None:
    if module == "nvp.app" or module.startswith("nvp.app."):
        return "app"
    top = module.split(".")[0]
    return {"nvp": "core", "tracking": "tracking", "renderer": "renderer", "scripts": "scripts"}.get(top)


def allowed(src: str, dst: str) -> bool:
    """Whether module ``src`` may import module ``dst`` (both inside the project)."""
    a, b = floor(src), floor(dst)
    if b is None or a == b:
        return b != "scripts"
    if b == "scripts":
        return False
    if a == "app":
        return True
    if a == "tracking":
        return b == "core" or dst == "renderer.raster" or dst.startswith("renderer.raster.")
    if a == "renderer":
        return b == "core"
    return False  # core imports nothing above it


def is_training(module: str) -> bool:
    return module.rsplit(".", 1)[-1].startswith("train")


def test_the_rules_themselves(tmp_path):
    assert allowed("nvp.app.cli", "renderer.render") and allowed("nvp.app.fit", "tracking.track")
    assert not allowed("nvp.person", "nvp.app.corpus") and not allowed("nvp.media", "tracking.detect")
    assert not allowed("renderer.render", "tracking.fit") and allowed("tracking.track", "renderer.raster")
    assert not allowed("tracking.track", "renderer.render") and not allowed("nvp.app.cli", "scripts.x")
    # a module of nvp's core, written outside the source tree: what it imports, relative imports resolved
    p = tmp_path / "_probe.py"
    p.write_text("from nvp.app import fit\nimport tracking.track\nfrom .app import dub\nfrom . import media")
    found = imports_of(p, "nvp._probe")
    assert {"nvp.app.fit", "tracking.track", "nvp.app.dub", "nvp.media"} <= found
    assert [m for m in found if floor(m) is not None and not allowed("nvp._probe", m)]


@pytest.mark.parametrize("module", sorted(all_modules()))
def test_no_import_points_upward(module):
    path = all_modules()[module]
    project = [m for m in imports_of(path) if floor(m) is not None]
    bad = sorted(m for m in project if not allowed(module, m))
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


@pytest.mark.parametrize(
    "module", sorted(m for m in all_modules() if not is_training(m) and floor(m) != "app")
)
def test_inference_never_imports_training(module):
    path = all_modules()[module]
    bad = sorted(m for m in imports_of(path) if floor(m) is not None and is_training(m))
    assert not bad, f"{path.relative_to(ROOT)} imports training code {bad}"


def test_indirect_imports_obey_the_rules_too():
    """Import every module below the roof in a fresh interpreter; what comes along must be allowed."""
    mods = sorted(m for m in all_modules() if floor(m) != "app")
    code = (
        "import importlib, json, sys\n"
        f"out = {{}}\nfor m in {mods!r}:\n"
        "    before = set(sys.modules)\n"
        "    importlib.import_module(m)\n"
        "    out[m] = sorted(set(sys.modules) - before)\n"
        "    for k in out[m]:\n"
        "        if k.split('.')[0] in ('nvp', 'tracking', 'renderer'): sys.modules.pop(k, None)\n"
        "print(json.dumps(out))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    loaded = json.loads(res.stdout.strip().splitlines()[-1])
    bad = {m: [d for d in deps if floor(d) is not None and not allowed(m, d)] for m, deps in loaded.items()}
    bad = {m: d for m, d in bad.items() if d}
    assert not bad, f"modules that drag in upper floors: {bad}"


def import_cycles(modules: list[str]) -> list[list[str]]:
    """The import cycles among ``modules`` (every import statement counts): strongly connected parts of
    the import graph with more than one module."""
    mods = all_modules()
    graph = {m: sorted(d for d in imports_of(mods[m]) if d in modules and d != m) for m in modules}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = stack[stack.index(v) :]
            del stack[stack.index(v) :]
            if len(part) > 1:
                cycles.append(sorted(part))

    for m in modules:
        if m not in index:
            visit(m)
    return cycles


def test_no_import_cycle():
    """Not even on the roof: the job runners start the CLI by module name (nvp.app.cli.job), never import
    it."""
    assert not import_cycles(sorted(all_modules()))


def test_help_is_instant_no_heavy_imports():
    heavy = "{'torch', 'mediapipe', 'av', 'cv2'}"
    code = f"import sys, nvp.app.cli as c; c.build_parser(); print(sorted({heavy} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
