"""The code base stays ruff clean (the rules are in pyproject.toml)."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_clean():
    pytest.importorskip("ruff")
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", str(ROOT)], capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stdout[-3000:]


def test_docs_are_reference_not_a_record():
    """docs/ (research notes aside) stays a reference a user reads: at most 1600 lines in all, the
    status file at most 60, and no text that tells when something was done instead of what it is."""
    import re

    docs = sorted((ROOT / "docs").glob("*.md"))
    lines = {d.name: len(d.read_text().splitlines()) for d in docs}
    assert sum(lines.values()) <= 1600, lines
    assert lines["status.md"] <= 60
    record = re.compile(r"\b(this|last|next|previous|earlier) (session|work period)\b|\bsession \d+|\bissue \d+\b",
                        re.IGNORECASE)
    found = [f"{d.name}: {m.group(0)}" for d in docs if d.name != "status.md"  # the status names open issues
             for m in record.finditer(d.read_text())]
    assert not found, found


def test_functions_have_one_job():
    """Every function of the package is at most 80 lines, except the command-line parser (one
    declaration per option) and the compiled contact kernel (one numba loop)."""
    import ast

    exempt = {("cli/parser.py", "build_parser"), ("geometry/kernels.py", "wrench_expansion")}
    long = []
    for f in sorted((ROOT / "kneenlp").rglob("*.py")):
        rel = f.relative_to(ROOT / "kneenlp").as_posix()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and (rel, node.name) not in exempt:
                size = node.end_lineno - node.lineno + 1
                if size > 80:
                    long.append(f"{rel}:{node.name} {size} lines")
    assert not long, long


def test_classes_and_modules_stay_readable():
    """No class of the package is longer than 350 lines and at most three modules are longer than
    500 (a newcomer reads one job at a time: docs/architecture.md)."""
    import ast

    classes, modules = [], []
    for f in sorted((ROOT / "kneenlp").rglob("*.py")):
        text = f.read_text()
        if text.count("\n") > 500:
            modules.append(f.relative_to(ROOT).as_posix())
        sizes = {n.name: n.end_lineno - n.lineno + 1 for n in ast.walk(ast.parse(text)) if isinstance(n, ast.ClassDef)}
        classes += [f"{f.name}:{name} {size} lines" for name, size in sizes.items() if size > 350]
    assert not classes, classes
    assert len(modules) <= 3, modules
