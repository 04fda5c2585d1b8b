"""The shell commands of README.md and docs/**/*.md run as written, so the docs cannot drift.

Every ```sh block is run, its lines in order, one temporary directory per
file (not the repository root), with a copy of data_tools/ in it as the
README implies (its commands are typed in the clone) and this
interpreter's directory first on PATH, as after `. .venv/bin/activate`.
A block that cannot run here says why on the line before its fence,
which this test reports as a skip:

    <!-- docs-test skip: REASON -->     never run here (a cluster, your own files, minutes of benchmark)
    <!-- docs-test needs: hdf5 -->      run when pkg-config finds the HDF5 C library, else skipped, saying so

README's "Command line" block is parsed here but run by
tests/test_new_user_commands.py, which runs it as this test would (the same
calls, the same checks) from a scratch folder without data_tools/, and
checks the files it leaves: one run of the block checks both.

The set-up line's install is not run (.ci/run and a Debian chroot prove
it): `python3 -m venv` and `pip install` are skipped, `.venv/bin/NAME` runs
NAME of this environment, and `python -m pytest` is this suite.  `mcrecon`
runs in this process (`mcrecon.cli.main`, the same argument list);
every other program runs as a process, never through a shell: `&&` is
the only shell syntax allowed, and anything else fails the test (mark the
block or write the command without it).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import run_cli

ROOT = Path(__file__).parents[1]
FILES = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
_FENCE = re.compile(r"^```(sh|bash|shell)\n(.*?)^```", re.M | re.S)
_MARK = re.compile(r"<!-- docs-test (skip|needs): (.*?) -->\s*\Z", re.S)
_SHELL = re.compile(r"[|;<>`$*?\[\]]|^~")  # what only a shell would do with an unquoted word


def _blocks(path: Path):
    """(line number, block text, mark kind or None, mark text) of each sh block of ``path``."""
    text = path.read_text(encoding="utf-8")
    for m in _FENCE.finditer(text):
        before = text[:m.start()]
        mark = _MARK.search(before[-400:])
        yield (before.count("\n") + 1, m.group(2), mark.group(1) if mark else None,
               mark.group(2) if mark else "")


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT))


RUN = [p for p in FILES if any(kind != "skip" for _, _, kind, _ in _blocks(p))]
SKIPPED = [(f"{_name(p)}:{line}", why) for p in FILES for line, _, kind, why in _blocks(p) if kind == "skip"]


def _words(line: str, posix: bool) -> list[str]:
    lexer = shlex.shlex(line, posix=posix, punctuation_chars="&|;<>")
    lexer.whitespace_split, lexer.commenters = True, "#"
    return list(lexer)


def _commands(block: str):
    """(argument list, its line) of each command of a block, in order: continuation lines joined, comments
    dropped, split at ``&&``; any other shell syntax fails (an operator, an unquoted ``$``, glob, ``~``,
    ``VAR=``)."""
    for line in block.replace("\\\n", " ").splitlines():
        raw, words = _words(line, posix=False), _words(line, posix=True)  # with and without their quotes
        assert len(raw) == len(words), f"{line!r}: cannot split it as a shell would; mark the block"
        argv = []
        for r, word in zip(raw, words):
            if r == "&&":
                yield argv, line
                argv = []
                continue
            quoted = r[:1] in "'\""
            assert quoted or not (_SHELL.search(r) or (not argv and "=" in r)), \
                f"{line!r}: {r!r} needs a shell; write the command without it or mark the block"
            argv.append(word)
        if argv:
            yield argv, line


def _not_run(argv) -> bool:
    """The install and the suite itself (see the module docstring)."""
    return (argv[1:3] == ["-m", "venv"] or Path(argv[0]).name in ("pip", "pip3")
            or argv[1:3] == ["-m", "pytest"])


def _run(argv, cwd: Path, capsys, where: str) -> None:
    if argv[0].startswith(".venv/bin/"):
        argv = [Path(argv[0]).name] + argv[1:]
    if _not_run(argv):
        return
    if argv[0] == "mcrecon":
        code, _, err = run_cli(argv[1:], capsys)
        assert code == 0 and "mcrecon: error" not in err, f"{where} exited {code}: {err.strip()}"
        return
    proc = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{where} exited {proc.returncode}: {proc.stderr.strip()[-2000:]}"


def _hdf5_dev() -> str | None:
    """Why the HDF5 C tools cannot be built here, or None."""
    if not (shutil.which("gcc") or shutil.which("cc")):
        return "no C compiler (apt install gcc)"
    if not shutil.which("make"):
        return "make not installed (apt install make)"
    if shutil.which("pkg-config") is None:
        return "pkg-config not installed (apt install pkg-config libhdf5-dev)"
    if subprocess.run(["pkg-config", "--exists", "hdf5"]).returncode != 0:
        return "pkg-config finds no HDF5 C library (apt install libhdf5-dev)"
    return None


def _run_elsewhere(path: Path, block: str) -> bool:
    """README's "Command line" block: tests/test_new_user_commands.py runs it (see the module docstring)."""
    if path != ROOT / "README.md":
        return False
    text = path.read_text(encoding="utf-8")
    section = text[text.index("\n## Command line\n"):]
    m = _FENCE.search(section)
    return m is not None and m.group(2) == block


@pytest.mark.parametrize("path", RUN, ids=_name)
def test_documented_commands_run_as_written(path, tmp_path, monkeypatch, capsys):
    shutil.copytree(ROOT / "data_tools", tmp_path / "data_tools",
                    ignore=shutil.ignore_patterns("__pycache__", "mcrecon_log_writer", "mcrecon_c_renderer", "*.o"))
    monkeypatch.chdir(tmp_path)
    # as after `. .venv/bin/activate`: `python` and `mcrecon` are this environment's
    monkeypatch.setenv("PATH", os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
    skipped = []
    for line, block, kind, why in _blocks(path):
        if kind == "skip":
            continue
        if kind == "needs":
            assert why == "hdf5", f"{_name(path)}:{line}: unknown need {why!r}"
            reason = _hdf5_dev()
            if reason is not None:
                skipped.append(f"{_name(path)}:{line}: {reason}")
                continue
        commands = list(_commands(block))  # every block is parsed: shell syntax fails here
        if _run_elsewhere(path, block):
            continue
        for argv, text in commands:
            _run(argv, tmp_path, capsys, f"{_name(path)}:{line}: {text.strip()}")
    if skipped:
        pytest.skip("; ".join(skipped))


@pytest.mark.parametrize("where, why", SKIPPED, ids=[w for w, _ in SKIPPED])
def test_documented_commands_not_run_here(where, why):
    pytest.skip(f"{where}: {why}")


def test_the_readme_block_run_elsewhere_is_the_one_the_new_user_test_runs():
    from test_new_user_commands import _readme_block

    blocks = [block for _, block, _, _ in _blocks(ROOT / "README.md")]
    assert [b for b in blocks if _run_elsewhere(ROOT / "README.md", b)] == [_readme_block("Command line")]
    assert all(not _run_elsewhere(p, b) for p in FILES[1:] for _, b, _, _ in _blocks(p))


def test_every_mark_is_right_before_a_sh_block():
    for path in FILES:
        for m in re.finditer(r"<!-- docs-test (\w+): (.*?) -->\n(.*)", path.read_text(encoding="utf-8")):
            assert m.group(1) in ("skip", "needs") and m.group(2).strip(), f"{_name(path)}: {m.group(0)!r}"
            assert re.match(r"```(sh|bash|shell)$", m.group(3)), f"{_name(path)}: {m.group(0)!r} is before no sh block"


def test_ci_runs_the_readme_set_up_and_ends_with_its_test_command():
    """CI judges the README's test command: .ci/run makes the README's venv and ends with that command."""
    setup = next(block for _, block, _, _ in _blocks(ROOT / "README.md") if "pip install" in block)
    commands = [argv for argv, _ in _commands(setup)]
    assert commands[0] == ["python3", "-m", "venv", ".venv"] and commands[1][:2] == [".venv/bin/pip", "install"]
    test_cmd = commands[-1]
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()
          if line.strip() and not line.strip().startswith("#")]
    assert ci[-1] == shlex.join(test_cmd)
    assert '"$PYTHON" -m venv .venv' in ci and 'PYTHON="${PYTHON:-python3}"' in ci
    assert not [line for line in ci if re.search(r'"\$PYTHON" -m pip', line)]  # never outside the venv


def test_docs_index_links_every_page():
    index = (ROOT / "docs" / "index.md").read_text()
    linked = set(re.findall(r"\]\(([^)#]+\.md)\)", index))
    pages = {str(p.relative_to(ROOT / "docs")) for p in (ROOT / "docs").rglob("*.md")} - {"index.md"}
    assert pages - linked == set()
