"""Ties: a parameter defined by an expression of others (lmfit's ``expr``).

A tie is arithmetic on other parameters' values in SI (fractions for strains, radians, metres), e.g.
``"MCLm.k_scale" = {expr = "MCLa.k_scale"}`` (two groups share one stiffness scale) or
``"MCL.k" = {expr = "2 * LCL.k"}``.  Allowed: numbers, parameter names (dotted, as in files),
``+ - * / **``, unary minus and ``exp``, ``log``, ``sqrt``, ``abs``.  One evaluator serves
NumPy values and CasADi symbols (the NLP's parameter vector), so a tie is the same function in
every solver.  Ties may refer to tied parameters; a cycle is an error.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Iterable, Mapping

import casadi as ca
import numpy as np

from kneenlp.base.errors import InputError, unknown_name

#: The functions a tie may call, for floats and CasADi symbols alike.
FUNCTIONS: dict[str, Callable] = {"exp": np.exp, "log": np.log, "sqrt": np.sqrt, "abs": np.abs}
_SYMBOLIC = {"exp": ca.exp, "log": ca.log, "sqrt": ca.sqrt, "abs": ca.fabs}
_BINARY = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b, ast.Mult: lambda a, b: a * b,
           ast.Div: lambda a, b: a / b, ast.Pow: lambda a, b: a**b}


def _dotted(node: ast.AST) -> str | None:
    """``ACL.k`` from the AST of a dotted name (None for anything else)."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        head = _dotted(node.value)
        return None if head is None else f"{head}.{node.attr}"
    return None


def parse(expr: str, field: str | None = None) -> ast.AST:
    """The expression's syntax tree, checked to hold only what a tie may (module docstring)."""
    try:
        tree = ast.parse(expr.strip(), mode="eval").body
    except SyntaxError:
        raise InputError(f"cannot read the tie {expr!r}: expected arithmetic on parameter names, e.g. "
                         "'2 * LCL.k'", field=field) from None
    for node in ast.walk(tree):
        ok = isinstance(node, ast.Constant | ast.Name | ast.Attribute | ast.Load | ast.BinOp | ast.UnaryOp
                        | ast.USub | ast.UAdd | ast.Call | ast.operator)
        if isinstance(node, ast.operator):
            ok = type(node) in _BINARY
        if isinstance(node, ast.Constant):
            ok = isinstance(node.value, int | float) and not isinstance(node.value, bool)
        if isinstance(node, ast.Call):
            ok = isinstance(node.func, ast.Name) and node.func.id in FUNCTIONS and len(node.args) == 1 \
                and not node.keywords
        if isinstance(node, ast.Attribute):
            ok = _dotted(node) is not None
        if not ok:
            raise InputError(f"the tie {expr!r} holds {ast.unparse(node)!r}: a tie is arithmetic (+ - * / **) on "
                             f"numbers and parameter names with {', '.join(FUNCTIONS)}", field=field)
    return tree


def names_in(expr: str, field: str | None = None) -> list[str]:
    """The parameter names ``expr`` refers to, in order of first use."""
    out: list[str] = []

    def visit(node: ast.AST) -> None:
        name = _dotted(node)
        if name is not None and not (isinstance(node, ast.Name) and name in FUNCTIONS):
            out.append(name)
            return
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(parse(expr, field))
    return list(dict.fromkeys(out))


def evaluate(expr: str, value: Callable[[str], object]):
    """``expr`` at the parameters' values ``value(name)`` (floats or CasADi symbols)."""

    def ev(node: ast.AST):
        name = _dotted(node)
        if isinstance(node, ast.Constant):
            return float(node.value)
        if isinstance(node, ast.Call):
            arg = ev(node.args[0])
            symbolic = isinstance(arg, ca.SX | ca.MX | ca.DM)
            return (_SYMBOLIC if symbolic else FUNCTIONS)[node.func.id](arg)
        if name is not None:
            return value(name)
        if isinstance(node, ast.UnaryOp):
            return -ev(node.operand) if isinstance(node.op, ast.USub) else ev(node.operand)
        return _BINARY[type(node.op)](ev(node.left), ev(node.right))

    return ev(parse(expr))


def ordered(ties: Mapping[str, str], known: Iterable[str], *, source: str | None = None) -> list[str]:
    """The tied names in an order in which each tie's tied inputs come first; an unknown name, a
    tie of itself or a cycle is a one-line error naming the tie."""
    known = set(known)
    needs = {}
    for name, expr in ties.items():
        field = f"parameters.{name}.expr"
        if name not in known:
            raise unknown_name("parameter", name, known, source=source, field=field)
        used = names_in(expr, field)
        for other in used:
            if other not in known:
                raise unknown_name("parameter in a tie", other, known, source=source, field=field)
        needs[name] = [u for u in used if u in ties]
    out: list[str] = []
    state: dict[str, int] = {}

    def visit(name: str, path: list[str]) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            loop = " -> ".join([*path[path.index(name):], name])
            raise InputError(f"ties form a cycle: {loop}", source=source, field=f"parameters.{name}.expr")
        state[name] = 1
        for other in needs[name]:
            visit(other, [*path, name])
        state[name] = 2
        out.append(name)

    for name in ties:
        visit(name, [])
    return out


def tied(values: Mapping[str, float], ties: Mapping[str, str], order: Iterable[str] | None = None) -> dict[str, float]:
    """``values`` (SI, by name) with every tied parameter set by its tie (numeric); a tie that is
    not finite (e.g. the log of a negative value) is an error naming it."""
    out = dict(values)
    for name in order if order is not None else ordered(ties, values):
        v = float(evaluate(ties[name], out.__getitem__))
        if not math.isfinite(v):
            raise InputError(f"the tie {ties[name]!r} is {v} at these values", field=f"parameters.{name}.expr")
        out[name] = v
    return out
