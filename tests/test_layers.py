"""The layers of docs/architecture.md hold: every import of the package (module-level, function-level
and type-checking ones, read by an AST walk) goes to the importing module's own layer or a layer
above it, and no modules import each other in a circle.  The layer table is read from the document,
so the document and the test cannot drift apart."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "kneenlp"
DOC = ROOT / "docs" / "architecture.md"

def layer_table() -> list[list[str]]:
    """The modules of each layer, top (imported by all) first, from docs/architecture.md."""
    text = DOC.read_text()
    table = text[text.index("| layer | modules |"):].split("\n\n")[0].splitlines()[2:]
    return [re.findall(r"`([\w.]+)`", row.split("|")[2]) for row in table]


def modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its own name)."""
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = f.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The package modules ``name`` imports anywhere in its source."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, *([node.module] if node.module else [])])
            for a in node.names:  # ``from pkg import module`` imports the module
                found.add(f"{base}.{a.name}" if f"{base}.{a.name}" in known else base)
    return {m for m in found if m in known}


def layer_of(module: str, table: list[list[str]]) -> int:
    """The row of the longest dotted prefix of ``module`` (``kneenlp`` names the package alone)."""
    best, row = "", None
    for i, names in enumerate(table):
        for n in names:
            hit = module == n or (n != "kneenlp" and module.startswith(n + "."))
            if hit and len(n) > len(best):
                best, row = n, i
    assert row is not None, f"{module} is in no layer of docs/architecture.md"
    return row


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {m: imports(m, p, set(mods)) - {m} for m, p in mods.items()}


def test_every_module_has_a_layer():
    table = layer_table()
    assert len(table) >= 10
    for m in modules():
        layer_of(m, table)


def test_no_import_goes_down_the_layers():
    table = layer_table()
    names = [row[0] for row in table]
    bad = sorted((m, i) for m, targets in graph().items() for i in targets
                 if layer_of(i, table) > layer_of(m, table))
    found = [f"{m} ({names[layer_of(m, table)]}) imports {i} ({names[layer_of(i, table)]})" for m, i in bad]
    assert not found, "imports against the layers of docs/architecture.md:\n" + "\n".join(found)


def test_no_import_cycle():
    g = graph()
    state: dict[str, int] = {}  # 1 on the path, 2 done
    cycles = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(g[m]):
            if state.get(n) == 1:
                cycles.append(" -> ".join([*path[path.index(n):], n]))
            elif n not in state:
                visit(n, [*path, n])
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m, [m])
    assert not cycles, "modules importing each other in a circle:\n" + "\n".join(cycles)


def test_the_walk_sees_function_level_and_relative_imports(tmp_path):
    pkg = tmp_path / "kneenlp" / "model"
    pkg.mkdir(parents=True)
    (pkg / "a.py").write_text("def f():\n    from kneenlp.solvers import forward\n    from . import b\n")
    known = {"kneenlp.solvers.forward", "kneenlp.model.b", "kneenlp.model.a"}
    assert imports("kneenlp.model.a", pkg / "a.py", known) == {"kneenlp.solvers.forward", "kneenlp.model.b"}
