"""The test suite runs the command line and renders jittered samples one way: through ``tests/helpers.py``.

A test module that writes its own runner (a helper calling ``mcrecon.cli.main``), builds its own
``python -m mcrecon`` command line, or copies the jittered test renderer drifts from the shared one
(an exit code read differently, a child without this checkout on its path, a renderer drawing in another
order).  An AST scan of every other module under ``tests/`` finds such copies; nothing is allowed.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
SHARED = TESTS / "helpers.py"


def _cli_entry_names(tree: ast.Module) -> tuple[set[str], set[str]]:
    """Names bound anywhere in the module to ``mcrecon.cli.main``/``run``, and names bound to ``mcrecon.cli``."""
    entries, modules = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "mcrecon.cli":
            entries |= {a.asname or a.name for a in node.names if a.name in ("main", "run")}
        elif isinstance(node, ast.ImportFrom) and node.module == "mcrecon":
            modules |= {a.asname or a.name for a in node.names if a.name == "cli"}
        elif isinstance(node, ast.Import):
            modules |= {a.asname for a in node.names if a.name == "mcrecon.cli" and a.asname}
    return entries, modules


def _dotted(node: ast.AST) -> str:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        parts.append(node.id)
        return ".".join(reversed(parts))
    return ""


def _own_nodes(fn: ast.AST):
    """The nodes of ``fn``'s own body: a function defined inside it is judged on its own."""
    todo = list(ast.iter_child_nodes(fn))
    while todo:
        node = todo.pop()
        yield node
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            todo.extend(ast.iter_child_nodes(node))


def _calls_cli(fn: ast.AST, entries: set[str], modules: set[str]) -> bool:
    for node in _own_nodes(fn):
        if isinstance(node, ast.Call):
            name = _dotted(node.func)
            head, _, attr = name.rpartition(".")
            if name in entries or name in ("mcrecon.cli.main", "mcrecon.cli.run") \
                    or (head in modules and attr in ("main", "run")):
                return True
    return False


def _is_mcrecon_command(node: ast.AST) -> bool:
    """A list or tuple ``[sys.executable, ..., "-m", "mcrecon", ...]``: a ``python -m mcrecon`` command line."""
    if not isinstance(node, (ast.List, ast.Tuple)) or not node.elts or _dotted(node.elts[0]) != "sys.executable":
        return False
    words = [e.value if isinstance(e, ast.Constant) else None for e in node.elts[1:]]
    return any(a == "-m" and b == "mcrecon" for a, b in zip(words, words[1:]))


def _is_jittered_renderer(fn: ast.AST) -> bool:
    """A function drawing ``jittered_positions`` for a request's own counts: a copy of the test renderer."""
    for node in _own_nodes(fn):
        if isinstance(node, ast.Call) and _dotted(node.func).rpartition(".")[2] == "jittered_positions" \
                and node.args and any(isinstance(n, ast.Attribute) and n.attr == "counts"
                                      for n in ast.walk(node.args[0])):
            return True
    return False


def copies(source: str, where: str) -> list[str]:
    """What ``source`` defines that ``tests/helpers.py`` already provides, one line each naming ``where:line``."""
    tree = ast.parse(source)
    entries, modules = _cli_entry_names(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            name = getattr(node, "name", "<lambda>")
            if name.startswith("test"):  # a test calling main or drawing positions itself is not a second helper
                continue
            if _calls_cli(node, entries, modules):
                found.append(f"{where}:{node.lineno}: {name} runs mcrecon.cli itself: use helpers.run_cli "
                             "(the `cli` fixture)")
            if _is_jittered_renderer(node):
                found.append(f"{where}:{node.lineno}: {name} copies the jittered test renderer: use "
                             "helpers.jittered_renderer")
        if _is_mcrecon_command(node):
            found.append(f"{where}:{node.lineno}: builds `python -m mcrecon` itself: use helpers.run_cli_process "
                         "(or helpers.MCRECON with helpers.cli_env)")
    return found


def test_no_test_module_but_helpers_runs_the_cli_or_renders_jittered_samples_itself():
    modules = sorted(p for p in TESTS.glob("*.py") if p != SHARED)
    assert len(modules) > 50 and Path(__file__) in modules  # the scan sees the suite
    found = [line for p in modules for line in copies(p.read_text(), p.name)]
    assert found == [], "\n".join(found)


@pytest.mark.parametrize("source, what", [
    ("""
     from mcrecon.cli import main
     def _cli(argv, capsys):
         return main([str(a) for a in argv]), capsys.readouterr()
     """, "runs mcrecon.cli itself"),
    ("""
     def run(argv):
         from mcrecon.cli import main as entry
         return entry(argv)
     """, "runs mcrecon.cli itself"),
    ("""
     from mcrecon import cli
     def test_x(argv):
         helper = lambda: cli.run()
     """, "runs mcrecon.cli itself"),
    ("""
     import sys, subprocess
     def test_x(tmp_path):
         subprocess.run([sys.executable, "-m", "mcrecon", "info", tmp_path])
     """, "builds `python -m mcrecon` itself"),
    ("""
     import numpy as np
     from mcrecon.core.requests import jittered_positions
     def _renderer(req):
         rng = np.random.default_rng(req.seed)
         return jittered_positions(req.counts, rng)
     """, "copies the jittered test renderer"),
])
def test_the_scan_finds_each_kind_of_copy(source, what):
    found = copies(textwrap.dedent(source), "m.py")
    assert len(found) == 1 and what in found[0], found


def test_the_scan_leaves_uses_of_the_shared_helpers_and_direct_calls_in_tests():
    source = textwrap.dedent("""
        import sys
        import numpy as np
        from mcrecon.cli import main
        from mcrecon.core.requests import jittered_positions
        from helpers import MCRECON, jittered_renderer, run_cli

        def test_a(capsys):
            assert main(["scenes"]) == 0
            assert run_cli(["scenes"], capsys)[0] == 0
            cmd = [*MCRECON, "info"]
            other = [sys.executable, "-m", "mcrecon.renderers.example"]

        def test_b(rng):
            pos = jittered_positions(np.full((4, 4), 2), rng)  # samples for a filter, not a renderer
            r = jittered_renderer(lambda pos, rng, req: np.ones((len(pos), 3)), width=4, height=4)
    """)
    assert copies(source, "m.py") == []
