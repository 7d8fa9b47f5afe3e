"""Export the identification NLP for other solvers: AMPL .nl, CasADi serialised functions, C code.

The exported problem is :mod:`kneenlp.solvers.nlp`'s NLP for one knee, one data set and one set of
free parameters, with the data substituted (``.nl``) or supplied as the parameter vector ``p``
(CasADi and C).  Contact:

* CasADi files and C code hold it exactly (``contact="exact"``): the femoral distance field is
  inside the graph (:mod:`kneenlp.geometry.graph_field`, its coefficients one constant array), so
  every constraint equals kneenlp's own at every point, and the optimum is ``identify``'s
  (tests/test_export.py, CasADi files and compiled C on the default knee).  The C of a mesh knee
  lays the field out as one point's function in a loop (``layout="loop"``,
  :data:`kneenlp.geometry.graph_field.LAYOUTS`: the default knee's compiles in ~10 s at ``-O0``);
  docs/solvers.md;
* ``.nl`` holds only expressions AMPL knows, so for a mesh knee its contact is the second-order
  expansion of the contact wrench at the start poses (``contact="expansion"``): an approximation,
  exact at the start poses.  The file's header and ``problem.json`` say so and give its error,
  measured at export time on poses around the start (:func:`expansion_error`).  Knees without
  working sets (sphere contact) are exact in every format.
  Decision variables: the free parameters scaled to order one (value / scale, the
scale and unit are in ``problem.json``) and every trial's five coordinates in mm and deg.
Constraints: every trial's five equilibrium residuals (N m, N m, N, N, N), all ``= 0``.
Objective: the sum of squared model-minus-measured coordinates (mm^2 + deg^2).

* ``nl``: ``kneenlp.nl`` (+ ``.row``/``.col`` names) written by :mod:`kneenlp.io.nlwriter`; variables
  in .nl order (coordinates first, they appear nonlinearly in the objective too);
* ``casadi``: ``nlp_f``, ``nlp_g``, ``nlp_grad_f``, ``nlp_jac_g``, ``nlp_hess_l`` as
  ``*.casadi`` files for ``casadi.Function.load`` (no kneenlp needed), inputs ``(x, p)``
  (``nlp_hess_l``: ``(x, p, lam_f, lam_g)``, the full symmetric Hessian of
  ``lam_f f + lam_g' g``);
* ``c``: the same functions as C code (``kneenlp_nlp.c`` and ``kneenlp_nlp.h``, CasADi's
  calling convention), compile with ``gcc -shared -fPIC -O1`` (a mesh knee: ``-O0`` compiles 3-6x
  faster, its functions run ~3x slower);
* always ``problem.json``: names, units, scaling, bounds, start, ``p`` and the data's origin.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from kneenlp.base.atomic import atomic_target, write_text_atomic
from kneenlp.base.conventions import (
    COORDINATE_UNITS,
    COORDINATES,
    RESIDUAL_NAMES,
    RESIDUAL_UNITS,
    coords_from_user,
)
from kneenlp.base.errors import InputError
from kneenlp.base.keywords import keyword_options
from kneenlp.base.modes import ContactForm, ExportFormat, Layout, NlCommon, checked, names
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData, read_measured
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.geometry.graph_field import LAYOUTS
from kneenlp.model.knee import Knee
from kneenlp.solvers.equilibria import equilibrium_start
from kneenlp.solvers.nlp import nlp_expressions

#: How the exported NLP holds mesh contact (module docstring).
CONTACT_FORMS = names(ContactForm)
#: Half-width (mm or deg) of the box around the start poses where an expansion's error is measured.
ERROR_PROBE = 1.0
#: Poses drawn per trial for that measurement.
ERROR_SAMPLES = 4


@dataclass
class ExportProblem:
    """The NLP of one identification, ready to be written in any format."""

    f: ca.MX
    g: ca.MX
    x: ca.MX
    p: ca.MX
    p_value: np.ndarray
    x0: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray
    var_names: list[str]
    var_units: list[str]
    con_names: list[str]
    con_units: list[str]
    scales: dict[str, float]
    n_free: int
    meta: dict
    #: how the contact is held: "exact" (in the graph) or "expansion" (at the start poses, in ``p``)
    contact: ContactForm = "exact"
    #: for "expansion" on a knee with working sets: its measured error (see :func:`expansion_error`)
    contact_error: dict | None = None
    #: the data vector ``p``'s layout in words (:class:`~kneenlp.experiment.problem.DataLayout`)
    p_layout: str = ""
    #: the graph's shape for "exact" mesh contact (:data:`kneenlp.geometry.graph_field.LAYOUTS`):
    #: "vector" for CasADi files, "loop" for C
    layout: str = "vector"

    def function(self) -> ca.Function:
        return ca.Function("nlp", [self.x, self.p], [self.f, self.g], ["x", "p"], ["f", "g"])


@dataclass(frozen=True)
class ExportOptions:
    """The keyword options of :func:`export_problem` (its docstring), checked in one place (:meth:`of`)."""

    free: list[str] | None = None
    start: dict[str, float] | None = None
    seed: int = 0
    with_effects: list[str] | None = None
    fixed: dict[str, float] | None = None
    contact: ContactForm = "exact"
    layout: Layout = "vector"

    def __post_init__(self) -> None:
        if self.contact not in CONTACT_FORMS:
            raise ValueError(f"contact must be one of {CONTACT_FORMS}, not {self.contact!r}")
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, not {self.layout!r}")



def export_problem(knee: Knee | KneeModel | None, data: MeasuredData | str | Path, **options) -> ExportProblem:
    """Build the identification NLP of ``data`` with a start like
    :func:`kneenlp.estimation.identify.identify`'s (``knee`` may be a model with user elements).
    Keyword options (:class:`ExportOptions`): ``free``, ``start``, ``seed`` (0), ``with_effects``
    and ``fixed`` as :func:`~kneenlp.estimation.identify.identify`'s; ``contact``: ``"exact"``
    (CasADi, C) or ``"expansion"`` (what ``.nl`` can hold; module docstring); ``layout``: the exact
    contact's graph shape (``"vector"`` for CasADi files, ``"loop"`` for C)."""
    opts = keyword_options(ExportOptions, "export_problem", options)
    free, start, seed, layout = opts.free, opts.start, opts.seed, opts.layout
    model = KneeModel.of(knee or Knee.default())
    if not isinstance(data, MeasuredData):
        data = read_measured(data)
    problem = IdentificationProblem.from_data(model, data, free, fixed=opts.fixed, with_effects=opts.with_effects or ())
    free = problem.free
    T = problem.n_trials
    contact = opts.contact if model.ws_size else "exact"  # no working sets: the one form is exact
    e = nlp_expressions(problem, parallel="serial", working_sets="graph" if contact == "exact" else "data",
                        layout=layout)
    values = problem.scatter(np.random.default_rng(seed))
    values.update(problem.check_start(start))
    theta0 = problem.theta(values)
    q0 = equilibrium_start(problem, theta0)
    x0 = problem.to_x(values, q0.q_user)
    var_names = list(free) + [f"{t.id}.{c}" for t in data.trials for c in COORDINATES]
    var_units = [f"{p.unit} x {p.scale * p.to_user:g}" for p in problem.parameters]
    var_units += list(COORDINATE_UNITS) * T
    con_names = [f"{t.id}.eq_{r}" for t in data.trials for r in RESIDUAL_NAMES]
    meta = {"knee": model.knee.source, "data": data.source, "protocol": data.protocol,
            "trials": [t.id for t in data.trials],
            "parameters": dict(zip(model.parameter_names, problem.theta().tolist(), strict=True)),
            "elements": [f"{type(el).__module__}.{type(el).__name__}:{el.name}" for el in model.elements],
            "start_seed": seed, "working_sets": bool(model.ws_size)}
    ws = model.working_data_batch(q0.q, theta0, problem.flexions) if contact == "expansion" else None
    error = expansion_error(problem, q0.q, theta0, ws, seed) if contact == "expansion" else None
    return ExportProblem(e.f, e.g, e.x, e.p, problem.data_vector(ws), x0, e.lbx, e.ubx, var_names, var_units,
                         con_names, list(RESIDUAL_UNITS) * T,
                         {n: float(s) for n, s in zip(free, problem.scales, strict=True)}, len(free), meta,
                         contact, error, problem.layout().describe(), layout)


def expansion_error(problem: IdentificationProblem, q0: np.ndarray, theta: np.ndarray, ws: np.ndarray,
                    seed: int = 0) -> dict:
    """How far the contact's expansion at the start poses ``q0`` (T x 5, SI; working sets ``ws``)
    is from the contact itself: the equilibrium residuals of both at poses drawn around the start
    (each coordinate uniform within :data:`ERROR_PROBE` mm or deg), the largest difference (N, N m)
    and its ratio to the largest residual there."""
    model = problem.model
    rng = np.random.default_rng(seed)
    exact = model.exact_residual
    worst, scale = 0.0, 0.0
    for i, t in enumerate(problem.trials):
        for _ in range(ERROR_SAMPLES):
            q = q0[i] + coords_from_user(rng.uniform(-ERROR_PROBE, ERROR_PROBE, 5))
            a = np.asarray(model.residual(q, theta, t.load, t.flexion, ws[i])).ravel()
            b = np.asarray(exact(q, theta, t.load, t.flexion)).ravel()
            worst, scale = max(worst, float(np.abs(a - b).max())), max(scale, float(np.abs(b).max()))
    return {"probe_mm_deg": ERROR_PROBE, "samples_per_trial": ERROR_SAMPLES, "max_residual_difference": worst,
            "relative": worst / scale if scale else 0.0,
            "meaning": "largest |expansion - contact| of any equilibrium residual (N, N m) at poses within "
                       f"+-{ERROR_PROBE:g} mm or deg of the start poses, and its ratio to the largest residual there"}


def _derivative_functions(prob: ExportProblem) -> list[ca.Function]:
    x, p = prob.x, prob.p
    lam_f = ca.MX.sym("lam_f")
    lam_g = ca.MX.sym("lam_g", prob.g.numel())
    lag = lam_f * prob.f + ca.dot(lam_g, prob.g)
    return [
        ca.Function("nlp_f", [x, p], [prob.f], ["x", "p"], ["f"]),
        ca.Function("nlp_g", [x, p], [prob.g], ["x", "p"], ["g"]),
        ca.Function("nlp_grad_f", [x, p], [ca.gradient(prob.f, x)], ["x", "p"], ["grad_f"]),
        ca.Function("nlp_jac_g", [x, p], [ca.jacobian(prob.g, x)], ["x", "p"], ["jac_g"]),
        ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [ca.hessian(lag, x)[0]],
                    ["x", "p", "lam_f", "lam_g"], ["hess_l"]),
    ]


def nl_function(prob: ExportProblem) -> tuple[ca.Function, np.ndarray]:
    """The NLP with the data substituted as an SX function of the .nl-ordered variables
    (coordinates first), and ``order`` such that ``x_nl = x[order]``."""
    nq = len(prob.var_names) - prob.n_free
    order = np.concatenate([np.arange(prob.n_free, prob.n_free + nq), np.arange(prob.n_free)])
    xnl = ca.MX.sym("x_nl", len(order))
    x_ours = ca.vertcat(xnl[nq:], xnl[:nq])
    return ca.Function("nlp_nl", [xnl], list(prob.function()(x_ours, prob.p_value))).expand(), order


def write_export(prob: ExportProblem, fmt: ExportFormat, out: str | Path, *,
                 nl_common: NlCommon = "defined") -> list[Path]:
    """Write ``prob`` in format ``fmt`` (nl, casadi, c) into directory ``out``; returns the files.

    ``nl_common``: see :func:`kneenlp.io.nlwriter.write_nl` (``"lifted"`` for SCIP)."""
    checked("export format", fmt, ExportFormat, field="--format")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    extra: dict = {}
    if fmt == "nl":
        from kneenlp.io.nlwriter import Bounds, NlInput, write_nl

        if prob.contact == "exact" and prob.meta.get("working_sets"):
            raise InputError("the .nl format cannot hold mesh contact exactly: build the problem with "
                             "contact='expansion' (what `kneenlp export --format nl` does)", field="--format")
        fn, order = nl_function(prob)
        nq = len(order) - prob.n_free
        bounds = Bounds(prob.lbx[order], prob.ubx[order], np.zeros(len(prob.con_names)), np.zeros(len(prob.con_names)))
        nl_input = NlInput(nq, prob.x0[order], bounds, [prob.var_names[i] for i in order], prob.con_names,
                           "sum_squared_residuals")
        extra = write_nl(out / "kneenlp.nl", fn, nl_input, title=_nl_title(prob), common=nl_common)
        extra["variable_order"] = "nl: coordinates first, then free parameters (see kneenlp.col)"
        files += [out / "kneenlp.nl", out / "kneenlp.row", out / "kneenlp.col"]
    elif fmt == "casadi":
        for fn in _derivative_functions(prob):
            with atomic_target(out / f"{fn.name()}.casadi") as tmp:
                fn.save(str(tmp))
            files.append(out / f"{fn.name()}.casadi")
    else:
        if prob.meta.get("working_sets") and prob.contact == "exact" and prob.layout != "loop":
            raise InputError("C code of a mesh knee's exact contact needs the loop layout (the vector one does not "
                             "compile in practice): build the problem with layout='loop' (what `kneenlp export "
                             "--format c` does)", field="--format")
        cg = ca.CodeGenerator("kneenlp_nlp.c", {"with_header": True})
        for fn in _derivative_functions(prob):
            cg.add(fn)
        cg.generate(str(out) + "/")
        files += [out / "kneenlp_nlp.c", out / "kneenlp_nlp.h"]
        extra = {"compile": "gcc -shared -fPIC -O1 kneenlp_nlp.c -o libkneenlp_nlp.so -lm",
                 "load": "casadi.external('nlp_hess_l', './libkneenlp_nlp.so') (or dlopen; CasADi's calling "
                         "convention, see kneenlp_nlp.h)"}
    sidecar = {
        "format": fmt,
        "description": "kneenlp identification NLP: min sum of squared coordinate residuals s.t. equilibrium",
        "objective": {"name": "sum_squared_residuals", "unit": "mm^2 + deg^2"},
        "variables": [{"name": n, "unit": u, "lb": float(lo), "ub": float(hi), "x0": float(v)}
                      for n, u, lo, hi, v in zip(prob.var_names, prob.var_units, prob.lbx, prob.ubx, prob.x0,
                                                 strict=True)],
        "constraints": [{"name": n, "unit": u, "lb": 0.0, "ub": 0.0}
                        for n, u in zip(prob.con_names, prob.con_units, strict=True)],
        "scaling": {n: {"scale": s, "meaning": f"variable = {n} [SI] / {s:g}"} for n, s in prob.scales.items()},
        "contact": _contact_words(prob),
        **({"contact_error": prob.contact_error} if prob.contact_error else {}),
        "p": prob.p_value.tolist(),
        "p_layout": prob.p_layout,
        "source": prob.meta,
        "files": [f.name for f in files],
        **({fmt: extra} if extra else {}),
    }
    write_text_atomic(out / "problem.json", json.dumps(sidecar, indent=1))
    files.append(out / "problem.json")
    return files



def _contact_words(prob: ExportProblem) -> str:
    if prob.contact == "exact":
        return ("exact: the contact is computed in the graph from the pose (the femoral distance field's B-spline "
                "inside it); every constraint is kneenlp's own at every point")
    err = prob.contact_error or {}
    return ("APPROXIMATION: mesh contact as the second-order expansion of its wrench at the start poses, exact there "
            f"only; measured within +-{err.get('probe_mm_deg', ERROR_PROBE):g} mm/deg of them: largest residual "
            f"error {err.get('max_residual_difference', float('nan')):.3g} N or N m "
            f"({100 * err.get('relative', float('nan')):.2g} % of the largest residual); the CasADi and C exports "
            "are exact")


def _nl_title(prob: ExportProblem) -> str:
    return "kneenlp identification" + ("" if prob.contact == "exact" else f" ({_contact_words(prob)})")
