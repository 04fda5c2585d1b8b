"""docs/architecture.md's module table matches the tree, and the docs describe the code as it is.

Every module under ``mcrecon/`` is named in the table of "One line per
module": by its path (``core/stats.py``) or by a package folder named as a
whole (``methods/gem/``); every name in the table exists.  The history of
measurements lives in CHANGELOG.md, so the reference pages under
``docs/`` and the modules of ``mcrecon/`` hold no dated measurement, no
"a -> b" history and no issue reference (:func:`history_lines`
is the grep; ``python tests/test_docs_architecture_table.py`` prints the
counts of each kind for docs/ and for all of mcrecon/).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
PACKAGE = ROOT / "mcrecon"
TABLE = ROOT / "docs" / "architecture.md"

#: The kinds of history line: an arrow between two numbers ("0.72 -> 0.50", "3.8 → 0.6 s"),
#: a date ("2026-12-01"), an issue reference ("issue 12", "before issue 26") and "was ... now".
HISTORY = {
    "arrow": re.compile(r"\d[\d.,%x×]*\s*(?:→|->)\s*[-+~≈]?\.?\d"),
    "date": re.compile(r"\b20\d\d-\d\d\b"),
    "issue": re.compile(r"\bissues? #?\d+|\bbefore issue\b", re.I),
    "was_now": re.compile(r"\bwas\b.*\bnow\b", re.I),
}


def history_lines(paths, kinds=tuple(HISTORY)) -> list[tuple[str, int, str, str]]:
    """(file, line number, kind, line) of every line of ``paths`` that matches one of ``kinds``."""
    found = []
    for path in paths:
        for number, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
            for kind in kinds:
                if HISTORY[kind].search(line):
                    name = Path(path).relative_to(ROOT) if Path(path).is_relative_to(ROOT) else Path(path)
                    found.append((str(name), number, kind, line.strip()))
    return found


def _docs_pages() -> list[Path]:
    return sorted((ROOT / "docs").rglob("*.md"))


def _modules() -> list[str]:
    """Every module of the package, as a path relative to mcrecon/ (``core/stats.py``)."""
    return sorted(str(p.relative_to(PACKAGE)).replace("\\", "/") for p in PACKAGE.rglob("*.py")
                  if "__pycache__" not in p.parts)


def _table_names(text: str) -> set[str]:
    """The backquoted names in the first column of the table under "One line per module"."""
    section = text.split("## One line per module", 1)[1]
    names = set()
    for line in section.splitlines():
        if line.startswith("| `"):
            names.update(re.findall(r"`([^`]+)`", line.split("|")[1]))
    return names


def _covered(module: str, names: set[str]) -> bool:
    parts = module.split("/")
    return module in names or any("/".join(parts[:i]) + "/" in names for i in range(1, len(parts)))


def test_every_module_is_in_the_architecture_table():
    names = _table_names(TABLE.read_text(encoding="utf-8"))
    missing = [m for m in _modules() if not _covered(m, names)]
    assert not missing, f"modules missing from docs/architecture.md's table: {missing}"


def test_every_name_in_the_architecture_table_exists():
    names = _table_names(TABLE.read_text(encoding="utf-8"))
    stale = sorted(n for n in names if not (PACKAGE / n).exists())
    assert not stale, f"docs/architecture.md names what is not in mcrecon/: {stale}"


def test_a_module_left_out_of_the_table_is_found():
    names = _table_names(TABLE.read_text(encoding="utf-8")) - {"core/features.py"}
    assert not _covered("core/features.py", names)
    assert _covered("methods/gem/selection.py", {"methods/gem/"})
    assert not _covered("methods/gemini.py", {"methods/gem/"})


def test_the_history_grep_finds_each_kind(tmp_path):
    sample = tmp_path / "history.md"
    sample.write_text("caustic 0.757 -> 0.522\nflat 5.2 → 2.9×\nmeasured 2026-12-01\n"
                      "the default before issue 26\nper target of issue 12\nit was 3 s, now 1 s\n"
                      "a method (Rousselle et al. 2011) of 1 -> many\n", encoding="utf-8")
    kinds = [kind for _, _, kind, _ in history_lines([sample])]
    assert kinds == ["arrow", "arrow", "date", "issue", "issue", "was_now"]


@pytest.mark.parametrize("kind", sorted(HISTORY))
def test_docs_pages_hold_no_dated_measurement_or_issue_reference(kind):
    found = history_lines(_docs_pages(), kinds=(kind,))
    assert not found, "history belongs in CHANGELOG.md:\n" + "\n".join(f"{f}:{n}: {s}" for f, n, _, s in found)


@pytest.mark.parametrize("kind", sorted(HISTORY))
def test_modules_hold_no_dated_measurement_or_issue_reference(kind):
    paths = sorted(PACKAGE.rglob("*.py"))
    assert len(paths) > 100
    found = history_lines(paths, kinds=(kind,))
    assert not found, "history belongs in CHANGELOG.md:\n" + "\n".join(f"{f}:{n}: {s}" for f, n, _, s in found)


if __name__ == "__main__":  # the counts: python tests/test_docs_architecture_table.py [-v]
    for name, paths in (("docs", _docs_pages()), ("mcrecon", sorted(PACKAGE.rglob("*.py")))):
        found = history_lines(paths)
        lines = {(f, n) for f, n, _, _ in found}
        kinds = {k: sum(1 for _, _, kind, _ in found if kind == k) for k in HISTORY}
        print(f"{name}: {len(lines)} lines {kinds}")
        if "-v" in sys.argv:
            for f, n, kind, s in found:
                print(f"  {f}:{n}: [{kind}] {s[:120]}")


def test_docs_pages_name_no_scratch_file_of_the_machine_they_were_measured_on():
    """A page's numbers come with the command that regenerates them, not a path to one machine's scratch runs
    (``/work/...``), which a reader cannot open."""
    scratch = re.compile(r"(?<![\w.])/work/")
    found = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in _docs_pages()
             for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if scratch.search(line)]
    assert not found, "\n".join(found)
