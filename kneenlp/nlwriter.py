"""A writer of AMPL ``.nl`` files (text format) from a CasADi SX function.

The input is an SX function ``F(x) -> (f, g)`` with a scalar objective and a constraint vector.
Its instruction list (``Function.instruction_id/input/output/constant``) is turned into
expression trees in the .nl prefix notation; every node used more than once becomes a *defined
variable* (a ``V`` segment, declared as a common expression), so the file grows linearly with
the graph.  ``fmin``/``fmax`` are written with ``abs`` (``(a + b -+ |a - b|) / 2``), which every
.nl reader supports (CasADi's own importer has no min/max or if-then-else).  Operations that have
no .nl counterpart (comparisons, conditionals) raise a clear error.

Variables must be ordered as .nl requires: those nonlinear in both constraints and objective
first (``n_both``), then those nonlinear in constraints only.  All terms are written in the
nonlinear part (linear coefficients 0 in the ``J``/``G`` segments), which is valid .nl.

References: D. M. Gay, "Writing .nl Files" (2005) and "Hooking Your Solver to AMPL" (1997).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import casadi as ca
import numpy as np

_BINARY = {ca.OP_ADD: "o0", ca.OP_SUB: "o1", ca.OP_MUL: "o2", ca.OP_DIV: "o3", ca.OP_POW: "o5",
           ca.OP_CONSTPOW: "o5", ca.OP_ATAN2: "o48"}
_UNARY = {ca.OP_NEG: "o16", ca.OP_SQRT: "o39", ca.OP_EXP: "o44", ca.OP_LOG: "o43", ca.OP_SIN: "o41",
          ca.OP_COS: "o46", ca.OP_TAN: "o38", ca.OP_ATAN: "o49", ca.OP_ASIN: "o51", ca.OP_ACOS: "o53",
          ca.OP_TANH: "o37", ca.OP_SINH: "o40", ca.OP_COSH: "o45", ca.OP_FABS: "o15"}
_OP_NAMES = {v: k for k, v in vars(ca).items() if k.startswith("OP_") and isinstance(v, int)}


def _num(v: float) -> str:
    return f"n{float(v)!r}"


class _Graph:
    """Expression DAG of an SX function, with use counts."""

    def __init__(self, fn: ca.Function):
        self.kind: list[str] = []  # 'v' variable, 'n' number, 'o' operation
        self.data: list = []
        self.uses: list[int] = []
        self.f_node: int | None = None
        self.g_nodes: list[int | None] = [None] * fn.nnz_out(1)
        reg: dict[int, int] = {}
        for k in range(fn.n_instructions()):
            op = fn.instruction_id(k)
            ins, outs = fn.instruction_input(k), fn.instruction_output(k)
            if op == ca.OP_INPUT:
                reg[outs[0]] = self._add("v", ins[1])
            elif op == ca.OP_CONST:
                reg[outs[0]] = self._add("n", fn.instruction_constant(k))
            elif op == ca.OP_OUTPUT:
                node = reg[ins[0]]
                self.uses[node] += 1
                if outs[0] == 0:
                    self.f_node = node
                else:
                    self.g_nodes[outs[1]] = node
            elif op == ca.OP_ASSIGN:
                reg[outs[0]] = reg[ins[0]]
            else:
                if op not in _BINARY and op not in _UNARY and op not in (
                        ca.OP_SQ, ca.OP_TWICE, ca.OP_INV, ca.OP_FMIN, ca.OP_FMAX, ca.OP_LOG1P, ca.OP_EXPM1):
                    raise ValueError(f"operation {_OP_NAMES.get(op, op)} has no .nl equivalent")
                children = [reg[w] for w in ins[: (2 if op in _BINARY or op in (ca.OP_FMIN, ca.OP_FMAX) else 1)]]
                for c in children:
                    # min/max use each operand twice: make them defined variables
                    self.uses[c] += 2 if op in (ca.OP_FMIN, ca.OP_FMAX) else 1
                reg[outs[0]] = self._add("o", (op, children))

    def _add(self, kind: str, data) -> int:
        self.kind.append(kind)
        self.data.append(data)
        self.uses.append(0)
        return len(self.kind) - 1


class _Emitter:
    def __init__(self, graph: _Graph, var_map: np.ndarray, n_var: int):
        self.g = graph
        self.var_map = var_map  # SX input index -> .nl variable index
        self.defined: dict[int, int] = {}  # node -> defined-variable index (global .nl index)
        self.n_var = n_var

    def tokens(self, node: int, top: bool = False) -> list[str]:
        """Prefix tokens of ``node`` (iterative, so deep chains do not hit the recursion limit)."""
        out: list[str] = []
        stack: list = [(node, top)]
        while stack:
            item = stack.pop()
            if isinstance(item, str):
                out.append(item)
                continue
            n, is_top = item
            if not is_top and n in self.defined:
                out.append(f"v{self.defined[n]}")
                continue
            kind, data = self.g.kind[n], self.g.data[n]
            if kind == "v":
                out.append(f"v{self.var_map[data]}")
            elif kind == "n":
                out.append(_num(data))
            else:
                op, ch = data
                seq: list = []
                if op in _BINARY:
                    seq = [_BINARY[op], (ch[0], False), (ch[1], False)]
                elif op in _UNARY:
                    seq = [_UNARY[op], (ch[0], False)]
                elif op == ca.OP_SQ:
                    seq = ["o5", (ch[0], False), "n2"]
                elif op == ca.OP_TWICE:
                    seq = ["o2", "n2", (ch[0], False)]
                elif op == ca.OP_INV:
                    seq = ["o3", "n1", (ch[0], False)]
                elif op == ca.OP_LOG1P:
                    seq = ["o43", "o0", "n1", (ch[0], False)]
                elif op == ca.OP_EXPM1:
                    seq = ["o1", "o44", (ch[0], False), "n1"]
                elif op in (ca.OP_FMIN, ca.OP_FMAX):
                    a, b = (ch[0], False), (ch[1], False)
                    inner = ["o1" if op == ca.OP_FMIN else "o0", "o0", a, b, "o15", "o1", a, b]
                    seq = ["o3", *inner, "n2"]
                stack.extend(reversed(seq))
        return out


def write_nl(path: str | Path, fn: ca.Function, *, n_both: int, x0: Sequence[float], lbx: Sequence[float],
             ubx: Sequence[float], lbg: Sequence[float], ubg: Sequence[float], var_names: Sequence[str],
             con_names: Sequence[str], objective_name: str = "objective", title: str = "kneenlp") -> dict:
    """Write ``fn`` (SX, ``x -> (f, g)``, variables already in .nl order) to ``path`` (.nl) with
    ``.row``/``.col`` name files beside it.  Returns counts for the caller's metadata."""
    if not fn.is_a("SXFunction"):
        fn = fn.expand()
    n, m = fn.nnz_in(0), fn.nnz_out(1)
    graph = _Graph(fn)
    em = _Emitter(graph, np.arange(n), n)
    shared = [i for i in range(len(graph.kind)) if graph.kind[i] == "o" and graph.uses[i] > 1]
    for j, node in enumerate(shared):
        em.defined[node] = n + j
    x = ca.SX.sym("x", n)
    f_expr, g_expr = fn(x)
    jac = ca.jacobian_sparsity(g_expr, x) if m else ca.Sparsity(0, n)
    grad = ca.jacobian_sparsity(f_expr, x)
    rows_j = [[] for _ in range(m)]
    for r, c in zip(*jac.get_triplet(), strict=True):
        rows_j[r].append(c)
    col_counts = np.bincount(np.array(jac.get_triplet()[1], dtype=int), minlength=n)
    path = Path(path)
    with path.open("w") as fh:
        w = fh.write
        w(f"g3 1 1 0\t# problem {title}\n")
        w(f" {n} {m} 1 0 {m} 0\t# vars, constraints, objectives, ranges, eqns, lcons\n")
        w(f" {m} 1\t# nonlinear constraints, objectives\n")
        w(" 0 0\t# network constraints: nonlinear, linear\n")
        w(f" {n} {n_both} {n_both}\t# nonlinear vars in constraints, objectives, both\n")
        w(" 0 0 0 1\t# linear network variables; functions; arith, flags\n")
        w(" 0 0 0 0 0\t# discrete variables: binary, integer, nonlinear (b,c,o)\n")
        w(f" {jac.nnz()} {grad.nnz()}\t# nonzeros in Jacobian, gradients\n")
        w(f" {max(map(len, con_names), default=0)} {max(map(len, var_names), default=0)}"
          "\t# max name lengths: constraints, variables\n")
        w(f" {len(shared)} 0 0 0 0\t# common exprs: b,c,o,c1,o1\n")
        for node in shared:
            w(f"V{em.defined[node]} 0 0\n")
            w("\n".join(em.tokens(node, top=True)) + "\n")
        for i, node in enumerate(graph.g_nodes):
            w(f"C{i}\n")
            w(("\n".join(em.tokens(node)) if node is not None else "n0") + "\n")
        w("O0 0\n")
        w(("\n".join(em.tokens(graph.f_node)) if graph.f_node is not None else "n0") + "\n")
        w(f"x{n}\n" + "".join(f"{i} {float(v)!r}\n" for i, v in enumerate(x0)))
        w("r\n")
        for lo, hi in zip(lbg, ubg, strict=True):
            w(_bound_line(lo, hi))
        w("b\n")
        for lo, hi in zip(lbx, ubx, strict=True):
            w(_bound_line(lo, hi))
        w(f"k{n - 1}\n" + "".join(f"{c}\n" for c in np.cumsum(col_counts)[: n - 1]))
        for i, cols in enumerate(rows_j):
            w(f"J{i} {len(cols)}\n" + "".join(f"{c} 0\n" for c in sorted(cols)))
        gcols = sorted(grad.get_triplet()[1])
        w(f"G0 {len(gcols)}\n" + "".join(f"{c} 0\n" for c in gcols))
    path.with_suffix(".row").write_text("".join(f"{c}\n" for c in con_names) + f"{objective_name}\n")
    path.with_suffix(".col").write_text("".join(f"{v}\n" for v in var_names))
    return {"variables": n, "constraints": m, "defined_variables": len(shared),
            "instructions": fn.n_instructions(), "jacobian_nonzeros": jac.nnz()}


def _bound_line(lo: float, hi: float) -> str:
    lo_inf, hi_inf = not np.isfinite(lo), not np.isfinite(hi)
    if lo_inf and hi_inf:
        return "3\n"
    if lo == hi:
        return f"4 {float(lo)!r}\n"
    if lo_inf:
        return f"1 {float(hi)!r}\n"
    if hi_inf:
        return f"2 {float(lo)!r}\n"
    return f"0 {float(lo)!r} {float(hi)!r}\n"
