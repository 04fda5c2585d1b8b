"""The layers of docs/architecture.md, enforced: every import in mcrecon/ goes to its own layer or a lower one.

Imports are read from the source (module level and inside functions alike), so a
lazy import cannot hide an upward dependency.  Also: no import circle among the
modules at module level, every module at most 700 lines, and each paper's method
package imports only the contract, the shared layers and itself.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mcrecon"

#: Layer of each top-level part of the package, lowest first (docs/architecture.md).
LAYERS = {
    "errors": 0, "_lazy": 0,
    "filters": 1,
    "core": 2,
    "io": 3,
    "methods": 4, "renderers": 4,
    "offline": 5, "adaptive": 5,
    "distributed": 6, "experiments": 6,
    "cli": 7, "restoration": 7, "__init__": 7, "__main__": 7,
}
#: Parts of one layer that must not import each other.
PEERS_APART = [("methods", "renderers"), ("offline", "adaptive"), ("distributed", "experiments")]
MAX_LINES = 700


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        yield ".".join(parts), path, is_pkg


def _imports(mod: str, path: Path, is_pkg: bool, *, top_only: bool = False):
    """(target module, line) of every mcrecon import in a file (targets resolved to modules where they are)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_only else ast.walk(tree)
    for node in nodes:
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("mcrecon"):
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                sub_path = PACKAGE.parent / sub.replace(".", "/")
                yield (sub if sub_path.with_suffix(".py").exists() or (sub_path / "__init__.py").exists()
                       else target), node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("mcrecon"):
                    yield a.name, node.lineno


def _part(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_every_module_belongs_to_a_layer():
    unknown = sorted({_part(m) for m, _, _ in _modules()} - set(LAYERS))
    assert not unknown, f"parts without a layer (add them to docs/architecture.md and LAYERS): {unknown}"


def test_imports_go_to_the_same_layer_or_below():
    bad = []
    for mod, path, is_pkg in _modules():
        src = _part(mod)
        for target, line in _imports(mod, path, is_pkg):
            dst = _part(target)
            if dst == src or target == "mcrecon":
                if target == "mcrecon" and src not in ("cli", "__init__", "__main__", "restoration"):
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} imports the top package")
                continue
            if LAYERS[dst] > LAYERS[src]:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} ({src}, layer {LAYERS[src]}) imports "
                           f"{target} ({dst}, layer {LAYERS[dst]})")
            elif {src, dst} in [set(p) for p in PEERS_APART]:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} {src} imports its peer {target}")
    assert not bad, "\n".join(bad)


def test_methods_never_open_files_and_each_method_imports_only_the_contract_and_itself():
    """A method package reads the shared layers (core, filters) and the contract (mcrecon.methods,
    mcrecon.methods.base); another method only through the registry (get_method)."""
    bad = []
    for mod, path, is_pkg in _modules():
        parts = mod.split(".")
        if len(parts) < 2 or parts[1] != "methods":
            continue
        own = ".".join(parts[:3])
        contract = len(parts) < 3 or parts[2] == "base"  # the registry and the contract
        for target, line in _imports(mod, path, is_pkg):
            tparts = target.split(".")
            if len(tparts) >= 2 and tparts[1] == "io":
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} opens files through {target}")
            if not contract and len(tparts) >= 3 and tparts[1] == "methods" and tparts[2] != "base" \
                    and ".".join(tparts[:3]) != own:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} ({own}) imports another method: {target}")
    assert not bad, "\n".join(bad)


def test_only_io_opens_hdf5_and_exr_files():
    """h5py and OpenEXR are imported by io/ alone, and by the out-of-process renderer, whose request and
    reply files are its protocol with the renderer (docs/architecture.md); never by a method."""
    allowed = ("mcrecon.io", "mcrecon.renderers.command")
    bad = []
    for mod, path, _ in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            for n in names:
                if n.split(".")[0] in ("h5py", "OpenEXR") and not mod.startswith(allowed):
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} imports {n}")
    assert not bad, "\n".join(bad)


def test_no_import_circle_at_module_level():
    graph = {}
    for mod, path, is_pkg in _modules():
        graph[mod] = {t for t, _ in _imports(mod, path, is_pkg, top_only=True) if t != mod}
    # a package's __init__ importing its own sub-modules is how packages re-export: not a circle
    # unless a sub-module imports the package back at module level
    index, low, stack, on, circles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(comp))

    import sys
    sys.setrecursionlimit(10000)
    for v in graph:
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


@pytest.mark.parametrize("mod,path", [(m, p) for m, p, _ in _modules()], ids=lambda x: str(x))
def test_no_module_over_700_lines(mod, path):
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, f"{path.relative_to(PACKAGE.parent)}: {n} lines (at most {MAX_LINES}: split it)"
