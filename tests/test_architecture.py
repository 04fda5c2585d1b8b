"""The layers of docs/architecture.md, enforced: every import in mcrecon/ goes to its own layer or a lower one.

Imports are read from the source (module level and inside functions alike), so a
lazy import cannot hide an upward dependency or an import circle.  Also: no import
circle among the modules, every module at most 700 lines, each paper's method
package imports only the contract, the shared layers and itself, and the private
names one package imports from another do not grow in number.
"""

from __future__ import annotations

import ast
import functools
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


def _from_target(mod: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    """The module a ``from ... import`` in module ``mod`` reads from, relative levels resolved."""
    if not node.level:
        return node.module or ""
    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
    return ".".join(base + ([node.module] if node.module else []))


def _import_nodes_of(source: str) -> tuple:
    """(statement, at module level) for every ``import`` and ``from ... import`` of a module's text."""
    tree = ast.parse(source)
    top = {id(n) for n in tree.body}
    return tuple((n, id(n) in top) for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)))


@functools.lru_cache(maxsize=None)
def _file_import_nodes(path: Path) -> tuple:
    """:func:`_import_nodes_of` of a file, parsed once for all the tests here (they only read the nodes)."""
    return _import_nodes_of(path.read_text())


def _import_nodes(path: Path, source: str | None = None, *, top_only: bool = False) -> list:
    """The ``import`` and ``from ... import`` statements of a file (``source``: the text read in place of
    its own), those inside functions too unless ``top_only``."""
    nodes = _file_import_nodes(path) if source is None else _import_nodes_of(source)
    return [n for n, top in nodes if top or not top_only]


@functools.lru_cache(maxsize=None)
def _is_module(name: str) -> bool:
    """``mcrecon.a.b`` is a module or a package of the checkout."""
    sub_path = PACKAGE.parent / name.replace(".", "/")
    return sub_path.with_suffix(".py").exists() or (sub_path / "__init__.py").exists()


def _imports(mod: str, path: Path, is_pkg: bool, *, top_only: bool = False, source: str | None = None):
    """(target module, line) of every mcrecon import in a file (targets resolved to modules where they are);
    ``source``: the text to read in place of the file's."""
    for node in _import_nodes(path, source, top_only=top_only):
        if isinstance(node, ast.ImportFrom):
            target = _from_target(mod, is_pkg, node)
            if not target.startswith("mcrecon"):
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                yield (sub if _is_module(sub) else target), node.lineno
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
        for node in _import_nodes(path):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            for n in names:
                if n.split(".")[0] in ("h5py", "OpenEXR") and not mod.startswith(allowed):
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} imports {n}")
    assert not bad, "\n".join(bad)


def _import_graph(*, top_only: bool = False, sources: dict | None = None) -> dict[str, set[str]]:
    """``{module: the mcrecon modules it imports}``, module level and, unless ``top_only``, inside functions
    (``sources``: ``{module: text}`` read in place of those modules' files)."""
    sources = sources or {}
    return {mod: {t for t, _ in _imports(mod, path, is_pkg, top_only=top_only, source=sources.get(mod)) if t != mod}
            for mod, path, is_pkg in _modules()}


def _import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module of an import graph, each sorted, in a stable
    order (Tarjan's algorithm)."""
    index, low, stack, on, circles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10000))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(circles)


def test_no_import_circle():
    """No two modules import each other, directly or through others, counting the imports inside
    functions: a lazy import defers a circle to run time, it does not remove it.  (A package's
    ``__init__`` importing its sub-modules is a circle only where a sub-module imports the package back.)"""
    circles = _import_circles(_import_graph())
    assert not circles, f"import circles (module level and inside functions): {circles}"


def test_the_circle_check_reads_imports_inside_functions():
    """A circle closed by an import inside a function is found (core/features naming its sources through
    core/samples, which imports core/features, was one), and a module-level-only reading misses it."""
    features = PACKAGE / "core" / "features.py"
    lazy = {"mcrecon.core.features": features.read_text() + "\n\ndef _name(src):\n"
            "    from .samples import source_name\n    return source_name(src)\n"}
    pair = ["mcrecon.core.features", "mcrecon.core.samples"]
    assert pair in _import_circles(_import_graph(sources=lazy))
    assert pair not in _import_circles(_import_graph(top_only=True, sources=lazy))


#: Underscore-private names one top-level part of the package imports from another (``from mcrecon.X
#: import _name`` in a module outside X): at most this many.  Lower it as they go (a name another package
#: needs becomes public there); never raise it.
MAX_PRIVATE_IMPORTS_ACROSS_PACKAGES = 0


def _private_imports_across_packages(sources: dict | None = None) -> list[str]:
    """``file:line: target._name`` for every import of an underscore-private name (``_x``, not a dunder)
    whose importing module is in another top-level part of mcrecon (core, io, methods, ...) than the
    module it imports from; imports inside functions count too (``sources``: ``{module: text}`` read in
    place of those modules' files)."""
    sources = sources or {}
    out = []
    for mod, path, is_pkg in _modules():
        text = sources.get(mod)
        for node in _import_nodes(path, text):
            if not isinstance(node, ast.ImportFrom):
                continue
            target = _from_target(mod, is_pkg, node)
            if not target.startswith("mcrecon") or _part(target) == _part(mod):
                continue
            out += [f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {target}.{a.name}" for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")]
    return out


def test_private_names_imported_across_packages_do_not_grow():
    found = _private_imports_across_packages()
    assert len(found) <= MAX_PRIVATE_IMPORTS_ACROSS_PACKAGES, (
        f"{len(found)} underscore-private names imported across packages (at most "
        f"{MAX_PRIVATE_IMPORTS_ACROSS_PACKAGES}): make a name another package needs public in its own "
        "package:\n" + "\n".join(found))


def test_the_private_import_count_reads_relative_and_function_local_imports():
    """Counted: a private name from another package, by a relative import inside a function; not counted:
    one from the module's own package, a public name, a dunder."""
    before = len(_private_imports_across_packages())
    text = (PACKAGE / "methods" / "box.py").read_text() + (
        "\n\ndef _f():\n    from ..core.samples import _LazyKernel\n    from .base import _MISSING\n"
        "    from ..core.samples import source_name, __doc__\n")
    found = _private_imports_across_packages({"mcrecon.methods.box": text})
    assert len(found) == before + 1
    box = [f for f in found if f.startswith("mcrecon/methods/box.py")]
    assert box[-1].endswith(": mcrecon.core.samples._LazyKernel")


@pytest.mark.parametrize("mod,path", [(m, p) for m, p, _ in _modules()], ids=lambda x: str(x))
def test_no_module_over_700_lines(mod, path):
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, f"{path.relative_to(PACKAGE.parent)}: {n} lines (at most {MAX_LINES}: split it)"
