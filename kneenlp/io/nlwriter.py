"""A writer of AMPL ``.nl`` files (text format) from a CasADi SX function.

The input is an SX function ``F(x) -> (f, g)`` with a scalar objective and a constraint vector.
Its instruction list (``Function.instruction_id/input/output/constant``) is turned into
expression trees in the .nl prefix notation; every node used more than once becomes a *defined
variable* (a ``V`` segment, declared as a common expression), so the file grows linearly with
the graph.  ``fmin``/``fmax`` are written with ``abs`` (``(a + b -+ |a - b|) / 2``), which every
.nl reader supports (CasADi's own importer has no min/max or if-then-else).  Operations that have
no .nl counterpart (comparisons, conditionals) raise a one-line InputError.

Variables must be ordered as .nl requires: those nonlinear in both constraints and objective
first (``n_both``), then those nonlinear in constraints only.  All terms are written in the
nonlinear part (linear coefficients 0 in the ``J``/``G`` segments), which is valid .nl.

References: D. M. Gay, "Writing .nl Files" (2005) and "Hooking Your Solver to AMPL" (1997).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from kneenlp.base.atomic import atomic_target, write_text_atomic
from kneenlp.base.errors import InputError

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
        self.n_vars = fn.nnz_in(0)
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
                    raise InputError(f"the .nl format has no {_OP_NAMES.get(op, op)} (a comparison or conditional; a "
                                     "ligament path that wraps an obstacle needs one): export --format casadi or c",
                                     field="--format")
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
    """Writes nodes as prefix tokens; sums are flattened into n-ary ``o54`` so that trees stay
    shallow (a left-deep chain of thousands of additions overflowed SCIP's recursive reader)."""

    def __init__(self, graph: _Graph, var_map: np.ndarray, n_var: int):
        self.g = graph
        self.var_map = var_map  # SX input index -> .nl variable index
        self.defined: dict[int, int] = {}  # node -> defined-variable index (global .nl index)
        self.n_var = n_var

    def _sum_terms(self, node: int) -> list[int]:
        """Operands of the maximal tree of single-use, non-defined additions rooted at ``node``."""
        terms: list[int] = []
        stack = [node]
        while stack:
            n = stack.pop()
            kind, data = self.g.kind[n], self.g.data[n]
            if n != node and (n in self.defined or kind != "o" or data[0] != ca.OP_ADD):
                terms.append(n)
                continue
            stack.extend(reversed(data[1]))
        return terms

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
                if op == ca.OP_ADD:
                    terms = self._sum_terms(n)
                    seq = ["o54", str(len(terms)), *[(t, False) for t in terms]] if len(terms) > 2 else \
                        ["o0", (terms[0], False), (terms[1], False)]
                elif op in _BINARY:
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


_NUMPY = {ca.OP_ADD: np.add, ca.OP_SUB: np.subtract, ca.OP_MUL: np.multiply, ca.OP_DIV: np.divide,
          ca.OP_POW: np.power, ca.OP_CONSTPOW: np.power, ca.OP_ATAN2: np.arctan2, ca.OP_NEG: np.negative,
          ca.OP_SQRT: np.sqrt, ca.OP_EXP: np.exp, ca.OP_LOG: np.log, ca.OP_SIN: np.sin, ca.OP_COS: np.cos,
          ca.OP_TAN: np.tan, ca.OP_ATAN: np.arctan, ca.OP_ASIN: np.arcsin, ca.OP_ACOS: np.arccos,
          ca.OP_TANH: np.tanh, ca.OP_SINH: np.sinh, ca.OP_COSH: np.cosh, ca.OP_FABS: np.abs,
          ca.OP_SQ: np.square, ca.OP_TWICE: lambda a: 2 * a, ca.OP_INV: lambda a: 1 / a, ca.OP_FMIN: np.minimum,
          ca.OP_FMAX: np.maximum, ca.OP_LOG1P: np.log1p, ca.OP_EXPM1: np.expm1}


def _node_values(graph: _Graph, x: np.ndarray) -> np.ndarray:
    vals = np.zeros(len(graph.kind))
    with np.errstate(all="ignore"):
        for i, (kind, data) in enumerate(zip(graph.kind, graph.data, strict=True)):
            if kind == "v":
                vals[i] = x[data]
            elif kind == "n":
                vals[i] = data
            else:
                vals[i] = _NUMPY[data[0]](*(vals[c] for c in data[1]))
    return vals


def _leaves(graph: _Graph, node: int | None, cut: dict[int, int], n: int) -> set[int]:
    """Variable indices an expression depends on, shared nodes counting as variable ``cut[node]``."""
    out: set[int] = set()
    if node is None:
        return out
    stack, seen = [node], set()
    while stack:
        k = stack.pop()
        if k in seen:
            continue
        seen.add(k)
        if k != node and k in cut:
            out.add(cut[k])
        elif graph.kind[k] == "v":
            out.add(graph.data[k])
        elif graph.kind[k] == "o":
            stack.extend(graph.data[k][1])
    return out


@dataclass(frozen=True)
class Bounds:
    """Bounds of the variables (``lbx``, ``ubx``) and of the constraints (``lbg``, ``ubg``)."""

    lbx: Sequence[float]
    ubx: Sequence[float]
    lbg: Sequence[float]
    ubg: Sequence[float]


@dataclass(frozen=True)
class NlInput:
    """What a .nl file states beside the expressions: ``n_both`` (the variables nonlinear in both
    the objective and the constraints, first), the start ``x0``, the :class:`Bounds` and the names
    of the variables, the constraints and the objective."""

    n_both: int
    x0: Sequence[float]
    bounds: Bounds
    var_names: Sequence[str]
    con_names: Sequence[str]
    objective_name: str = "objective"


def write_nl(path: str | Path, fn: ca.Function, nl_input: NlInput, *, title: str = "kneenlp",
             common: str = "defined") -> dict:
    """Write ``fn`` (SX, ``x -> (f, g)``, variables already in .nl order) with ``nl_input`` to
    ``path`` (.nl) with ``.row``/``.col`` name files beside it.  Returns counts for the caller's
    metadata.

    ``common`` says how subexpressions used more than once are written: ``"defined"`` as .nl
    defined variables (compact, the same NLP), or ``"lifted"`` as auxiliary variables ``aux_j``
    with constraints ``aux_j - expr_j = 0`` (an equivalent lifted NLP, for readers that copy
    defined variables at every use: SCIP's reader is exponential in their nesting depth).
    """
    if common not in ("defined", "lifted"):
        raise ValueError(f"common must be 'defined' or 'lifted', got {common!r}")
    if not fn.is_a("SXFunction"):
        fn = fn.expand()
    nl = _NlProblem.build(fn, nl_input, common == "lifted")
    path = Path(path)
    with atomic_target(path) as tmp, tmp.open("w") as fh:
        nl.write(fh.write, title)
    names = [*nl.con_names, nl_input.objective_name]
    write_text_atomic(path.with_suffix(".row"), "".join(f"{c}\n" for c in names))
    write_text_atomic(path.with_suffix(".col"), "".join(f"{v}\n" for v in nl.var_names))
    return {"variables": nl.n, "constraints": nl.m, "common": common, "shared_subexpressions": len(nl.shared),
            "instructions": fn.n_instructions(), "jacobian_nonzeros": int(nl.col_counts.sum())}


@dataclass(frozen=True)
class _NlProblem:
    """The NLP as the .nl file states it: the expression graph, its shared nodes (``cut``: node ->
    .nl index of the defined or auxiliary variable standing for it), the Jacobian and gradient
    sparsity, the start point, the bounds and the names (with the auxiliary variables and their
    definitions when ``lifted``)."""

    graph: _Graph
    emitter: _Emitter
    shared: list[int]
    cut: dict[int, int]
    lifted: bool
    n: int
    m: int
    nlv: tuple[int, int, int]
    rows: list[list[int]]
    gcols: list[int]
    col_counts: np.ndarray
    x: np.ndarray
    bounds: Bounds
    var_names: Sequence[str]
    con_names: Sequence[str]

    @classmethod
    def build(cls, fn: ca.Function, nl_input: NlInput, lifted: bool) -> _NlProblem:
        """The .nl statement of the SX function ``fn`` with ``nl_input`` (lifted or not)."""
        n0, m0 = fn.nnz_in(0), fn.nnz_out(1)
        x0, bounds, n_both = np.asarray(nl_input.x0, dtype=float), nl_input.bounds, nl_input.n_both
        var_names, con_names = nl_input.var_names, nl_input.con_names
        graph = _Graph(fn)
        shared = [i for i in range(len(graph.kind)) if graph.kind[i] == "o" and graph.uses[i] > 1]
        cut = {node: n0 + j for j, node in enumerate(shared)}
        n = n0 + (len(shared) if lifted else 0)
        m = m0 + (len(shared) if lifted else 0)
        em = _Emitter(graph, np.arange(n0), n0)
        em.defined = dict(cut)
        rows, gcols = _sparsity(graph, cut, lifted)
        col_counts = np.zeros(n, dtype=int)
        for r in rows:
            col_counts[r] += 1
        if not lifted:
            return cls(graph, em, shared, cut, lifted, n, m, (n, n_both, n_both), rows, gcols, col_counts, x0,
                       bounds, var_names, con_names)
        aux = len(shared)
        x_all = np.concatenate([x0, _node_values(graph, x0)[shared]])
        lifted_bounds = Bounds(np.concatenate([bounds.lbx, np.full(aux, -np.inf)]),
                                np.concatenate([bounds.ubx, np.full(aux, np.inf)]),
                                np.concatenate([bounds.lbg, np.zeros(aux)]),
                                np.concatenate([bounds.ubg, np.zeros(aux)]))
        return cls(graph, em, shared, cut, lifted, n, m, (n, n, n), rows, gcols, col_counts, x_all, lifted_bounds,
                   [*var_names, *[f"aux_{j}" for j in range(aux)]],
                   [*con_names, *[f"aux_{j}_definition" for j in range(aux)]])

    def write(self, w: Callable[[str], object], title: str) -> None:
        """Write the .nl text through ``w``: header, expression segments, then the numeric ones."""
        n, m, nlv, em, graph = self.n, self.m, self.nlv, self.emitter, self.graph
        w(f"g3 1 1 0\t# problem {title}\n")
        w(f" {n} {m} 1 0 {m} 0\t# vars, constraints, objectives, ranges, eqns, lcons\n")
        w(f" {m} 1\t# nonlinear constraints, objectives\n")
        w(" 0 0\t# network constraints: nonlinear, linear\n")
        w(f" {nlv[0]} {nlv[1]} {nlv[2]}\t# nonlinear vars in constraints, objectives, both\n")
        w(" 0 0 0 1\t# linear network variables; functions; arith, flags\n")
        w(" 0 0 0 0 0\t# discrete variables: binary, integer, nonlinear (b,c,o)\n")
        w(f" {int(self.col_counts.sum())} {len(self.gcols)}\t# nonzeros in Jacobian, gradients\n")
        w(f" {max(map(len, self.con_names), default=0)} {max(map(len, self.var_names), default=0)}"
          "\t# max name lengths: constraints, variables\n")
        w(f" {0 if self.lifted else len(self.shared)} 0 0 0 0\t# common exprs: b,c,o,c1,o1\n")
        if not self.lifted:
            for node in self.shared:
                w(f"V{self.cut[node]} 0 0\n")
                w("\n".join(em.tokens(node, top=True)) + "\n")
        for i, node in enumerate(graph.g_nodes):
            w(f"C{i}\n")
            w(("\n".join(em.tokens(node)) if node is not None else "n0") + "\n")
        if self.lifted:
            m0 = len(graph.g_nodes)
            for j, node in enumerate(self.shared):
                w(f"C{m0 + j}\no1\nv{self.cut[node]}\n" + "\n".join(em.tokens(node, top=True)) + "\n")
        w("O0 0\n")
        w(("\n".join(em.tokens(graph.f_node)) if graph.f_node is not None else "n0") + "\n")
        self._write_numbers(w)

    def _write_numbers(self, w: Callable[[str], object]) -> None:
        """Write the start point, the bounds and the Jacobian and gradient sparsity through ``w``."""
        n, b = self.n, self.bounds
        w(f"x{n}\n" + "".join(f"{i} {float(v)!r}\n" for i, v in enumerate(self.x)))
        w("r\n" + "".join(_bound_line(lo, hi) for lo, hi in zip(b.lbg, b.ubg, strict=True)))
        w("b\n" + "".join(_bound_line(lo, hi) for lo, hi in zip(b.lbx, b.ubx, strict=True)))
        w(f"k{n - 1}\n" + "".join(f"{c}\n" for c in np.cumsum(self.col_counts)[: n - 1]))
        for i, cols in enumerate(self.rows):
            w(f"J{i} {len(cols)}\n" + "".join(f"{c} 0\n" for c in cols))
        w(f"G0 {len(self.gcols)}\n" + "".join(f"{c} 0\n" for c in self.gcols))


def _sparsity(graph: _Graph, cut: dict[int, int], lifted: bool) -> tuple[list[list[int]], list[int]]:
    """The variables each constraint depends on (its Jacobian row) and those the objective depends
    on (its gradient), the shared nodes being the keys of ``cut`` (in their order).  Defined
    variables are not variables: without ``lifted`` a row lists the variables behind them instead."""
    shared, n0, m0 = list(cut), graph.n_vars, len(graph.g_nodes)
    con_nodes = list(graph.g_nodes) + (shared if lifted else [])
    rows = [sorted(_leaves(graph, node, cut, n0) | ({cut[node]} if lifted and i >= m0 else set()))
            for i, node in enumerate(con_nodes)]
    if lifted:
        return rows, sorted(_leaves(graph, graph.f_node, cut, n0))
    dep: dict[int, set[int]] = {}
    for node in shared:
        d = set()
        for v in _leaves(graph, node, cut, n0):
            d |= dep[v] if v >= n0 else {v}
        dep[cut[node]] = d

    def expand(vs: list[int]) -> list[int]:
        return sorted(set().union(*[dep[v] if v >= n0 else {v} for v in vs])) if vs else []

    return [expand(r) for r in rows], expand(sorted(_leaves(graph, graph.f_node, cut, n0)))


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
