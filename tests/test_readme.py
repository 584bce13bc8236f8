"""Every shell command the README shows parses, so the manual cannot rot.

Each line of the README's ``bash`` code blocks is split into its simple commands (at ``&&``, ``|``, ``;``).
Running them is heavy (a fit trains for minutes, setup installs packages), so each is checked as far as it
can be without doing the work:

- ``nvp <command> …`` (also under ``torchrun -m nvp.app.cli``): ``nvp <command> --help`` is run and every
  option the README shows must appear in it; then nvp's own parser must accept the whole command line.
- ``torchrun``, ``python -m pytest``, ``python scripts/….py``: their ``--help`` is run and must show each
  option used.
- ``bash scripts/setup.sh EXTRA``: the script is valid bash and knows each extra named.
- programs from outside the project (``arecord``): when installed, their ``--help`` must show the options.
"""

from __future__ import annotations

import functools
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
QUICK_START = [
    "bash scripts/setup.sh tts && .venv/bin/nvp demo -o nvp-demo",
    "bash scripts/setup.sh && .venv/bin/python -m pytest",
]
EXTERNAL = {"arecord"}  # shown in the README, installed by the system, not by nvp
SEPARATORS = {"&&", "||", "|", ";"}


def code_blocks(text: str) -> list[str]:
    return re.findall(r"^```(?:bash|sh|shell)\n(.*?)^```", text, flags=re.M | re.S)


def readme_commands() -> list[str]:
    lines = []
    for block in code_blocks(README.read_text()):
        for line in block.replace("\\\n", " ").splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                lines.append(line.strip())
    return lines


def simple_commands(line: str) -> list[list[str]]:
    """The line's simple commands as argv lists (comments and leading VAR=value assignments dropped)."""
    lex = shlex.shlex(line, posix=True, punctuation_chars=";&|")
    lex.whitespace_split = True
    lex.commenters = "#"
    out, cur = [], []
    for tok in lex:
        if tok in SEPARATORS:
            out.append(cur)
            cur = []
        else:
            cur.append(tok)
    out.append(cur)
    for argv in out:
        while argv and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", argv[0]):
            argv.pop(0)
    assert all(out), f"empty command in {line!r}"
    return out


def options(argv: list[str]) -> list[str]:
    """The options of an argv (``--name=value`` as ``--name``; ``-`` alone is stdin, not an option)."""
    return [a.split("=", 1)[0] for a in argv if re.match(r"--?[A-Za-z]", a)]


def program(name: str) -> Path:
    """A README program path (``.venv/bin/nvp``) in this checkout, or beside the running interpreter."""
    path = ROOT / name
    if path.exists():
        return path
    return Path(sys.executable).parent / Path(name).name


@functools.cache
def help_text(*argv: str) -> str:
    res = subprocess.run([*argv, "--help"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert res.returncode == 0, f"{' '.join(argv)} --help failed:\n{res.stderr[-2000:]}"
    return res.stdout + res.stderr


def assert_shown(opts: list[str], text: str, what: str) -> None:
    missing = [o for o in opts if not re.search(rf"(?<![\w-]){re.escape(o)}(?![\w-])", text)]
    assert not missing, f"{what} --help does not show {missing}"


def check_nvp(args: list[str], exe: Path) -> None:
    i = 0
    while i < len(args) and args[i].startswith("-"):
        i += 1  # nvp's own flags (-q, -v) take no value
    assert i < len(args), f"no nvp command in {args}"
    assert_shown(options(args[:i]), help_text(str(exe)), "nvp")
    assert_shown(options(args[i + 1 :]), help_text(str(exe), args[i]), f"nvp {args[i]}")
    from nvp.app.cli import build_parser

    try:
        build_parser().parse_args(args)
    except SystemExit as e:
        pytest.fail(f"nvp's parser refuses {args} (exit {e.code})")


def check(argv: list[str]) -> None:
    name, args = argv[0], argv[1:]
    base = Path(name).name
    if base == "nvp":
        check_nvp(args, program(name))
    elif base == "torchrun":
        exe = program(name)
        assert "-m" in args, f"torchrun without -m: {argv}"
        k = args.index("-m")
        assert_shown(options(args[:k]), help_text(str(exe)), "torchrun")
        assert args[k + 1] == "nvp.app.cli", f"torchrun runs {args[k + 1]}, not nvp's CLI"
        check_nvp(args[k + 2 :], program(".venv/bin/nvp"))
    elif base.startswith("python"):
        exe = program(name)
        if args[:2] == ["-m", "pytest"]:
            assert_shown(options(args[2:]), help_text(str(exe), "-m", "pytest"), "pytest")
        else:
            script = ROOT / args[0]
            assert script.is_file() and script.suffix == ".py", f"no script {args[0]}"
            assert_shown(options(args[1:]), help_text(str(exe), str(script)), args[0])
    elif base == "bash":
        script = ROOT / args[0]
        assert script.is_file(), f"no script {args[0]}"
        subprocess.run(["bash", "-n", str(script)], check=True)
        known = set(re.findall(r"^\s*([\w-]+)\)", script.read_text(), flags=re.M))
        unknown = [a for a in args[1:] if a not in known]
        assert not unknown, f"{args[0]} knows {sorted(known)}, not {unknown}"
    elif base in EXTERNAL:
        if shutil.which(base):
            assert_shown(options(args), help_text(base), base)
    else:
        pytest.fail(f"the README shows a command this test cannot check: {argv}")


COMMANDS = readme_commands()


def test_readme_is_a_short_manual_with_the_two_commands_first():
    assert len(README.read_text().splitlines()) <= 250
    assert COMMANDS[:2] == QUICK_START
    assert len(COMMANDS) > 10  # the blocks were found


@pytest.mark.parametrize("line", COMMANDS, ids=[c[:70] for c in COMMANDS])
def test_readme_command_parses(line):
    for argv in simple_commands(line):
        check(argv)


def test_the_checker_catches_what_rots():
    """An option nvp does not have, a missing value, an unknown extra: each is refused."""
    for line in [
        ".venv/bin/nvp fit person.mp4 -o person/ --no-such-option 3",
        ".venv/bin/nvp fit person.mp4 --preset cpu",  # -o is required
        ".venv/bin/nvp fit person.mp4 -o person/ --preset fast",
        "bash scripts/setup.sh tts gpu",
    ]:
        with pytest.raises((AssertionError, pytest.fail.Exception)):
            for argv in simple_commands(line):
                check(argv)
    assert simple_commands("A=1 .venv/bin/nvp serve  # then open") == [[".venv/bin/nvp", "serve"]]
    assert simple_commands("a -x | b - && c") == [["a", "-x"], ["b", "-"], ["c"]]
    assert options(["-o", "x", "--a=1", "-", "--b"]) == ["-o", "--a", "--b"]


SCRIPT_PATH = re.compile(r"(?<![\w./-])scripts/[\w/.-]*\w\.(?:py|sh|json)\b")
SCRIPT_MODULE = re.compile(r"-m (scripts(?:\.\w+)+)(?![\w.])")


def test_every_script_the_docs_and_sources_name_exists():
    """``scripts/…`` paths and ``python -m scripts.…`` modules named in the README, the docs, the tests,
    CI and the sources all exist (scripts move by kind: a stale path would rot silently)."""
    texts = [README, ROOT / ".ci" / "run", *(ROOT / "docs").rglob("*.md")]
    for folder in ("nvp", "tracking", "renderer", "scripts", "tests"):
        texts += list((ROOT / folder).rglob("*.py"))
    texts += list((ROOT / "scripts").rglob("*.sh"))
    dead = set()
    for path in texts:
        text = path.read_text()
        where = path.relative_to(ROOT)
        dead |= {(str(where), m) for m in SCRIPT_PATH.findall(text) if not (ROOT / m).exists()}
        for module in SCRIPT_MODULE.findall(text):
            file = ROOT.joinpath(*module.split("."))
            if not (file.with_suffix(".py").is_file() or (file / "__main__.py").is_file()):
                dead.add((str(where), module))
    assert not dead, sorted(dead)
