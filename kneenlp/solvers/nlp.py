"""The simultaneous identification NLP: ONE program for all trials and the ligament parameters.

Unknowns ``x = [p_free / scale, q_1 ... q_T in user units]``: the free parameters, scaled to order
one (k / 1e4 N, strains / 1e-2, modulus / 1e10 N/m^3), and the five free coordinates of every
trial in mm and deg (the units of the objective).  Equality constraints: every trial's
equilibrium residual (the model's one residual function, N m and N) is zero.  Objective: the
(optionally weighted) sum of squared differences between model and measured coordinates in mm and
deg, the paper's ``Psi^T Psi``.

The NLP is built once per (model, number of trials, free parameters, solver): all data enter as
the NLP parameter vector ``p = [theta (all parameters, SI), measured poses, weights, loads,
flexions]``, so refitting other data or other fixed values never rebuilds or recompiles it.
Contact working sets are taken at every pose IPOPT evaluates (:mod:`kneenlp.model.workingsets`),
so the constraints and their Jacobian are the contact model itself.

Speed choices: the residual is an MX graph around the vectorised contact (see
:mod:`kneenlp.model.contact`), mapped over trials with ``map(T, "thread", 2)`` so both cores evaluate
trials (``threads``; study workers use 1); it is *not* expanded to SX (that
would inline every contact point of every trial, the prototype's 75k-instruction-per-trial
mistake).  IPOPT gets exact first and second derivatives
from CasADi's AD (Lagrangian Hessian through the map) and uses MUMPS; the KKT system is tiny and
block-sparse, so linear algebra is negligible next to function evaluations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from kneenlp.base import interrupts
from kneenlp.base.conventions import LOAD_SIZE, coords_from_user, coords_to_user
from kneenlp.base.errors import InputError
from kneenlp.base.modes import Layout, WorkingSetSource
from kneenlp.experiment.problem import prior_rows
from kneenlp.model.solvercache import frozen
from kneenlp.solvers.equilibria import equilibrium_start
from kneenlp.solvers.result import SolverResult

if TYPE_CHECKING:
    from kneenlp.experiment.problem import IdentificationProblem

#: From :data:`OBJECTIVE_SCALE_FROM` trials on, IPOPT's filter line search refuses a trial point
#: whose equilibrium residual (1-norm of the scaled constraints, N and N m) exceeds
#: ``THETA_MAX_FACT * max(1, residual at the start)`` (IPOPT's ``theta_max_fact``, its own 1e4).
#: The start is at equilibrium (residual ~1e-6), so IPOPT's own ceiling let a first full step break
#: equilibrium by ~20 N (1-norm 126) and the next ones by ~200 N (1-norm 1.5e3), where the
#: contact's linearisation no longer holds: the steps grew (||d|| 25-100), the Hessian needed
#: inertia corrections, and the restoration phase failed (Set 4, default knee, seed 186: 150
#: iterations, then the rescue, 12 s).  Under the ceiling the trial points of 1.3e3-4.2e3 are
#: refused and IPOPT backtracks to a short step (3 % of it), staying near equilibrium: 17
#: iterations, the same optimum.
#: Set 4, default knee, seeds 0-199, the solve alone: 199/200 converged, worst 150 and 43
#: iterations, median 14 -> 200/200, worst 23, median 13 (100: worst 27; 1000: worst 25, median
#: 13.5); synthetic knee, 12 seeds: median 11.5 -> 11, worst 22 -> 17.  Sets 1 and 2 (7, 13
#: trials) gained nothing (medians 21.5 -> 25 and 19 -> 21 at 300; at 1000 one Set 1 seed of 16
#: failed), so smaller protocols keep IPOPT's own ceiling (docs/solvers.md).
THETA_MAX_FACT = 300.0
#: IPOPT options of the identification (tol 1e-10: same estimates as 1e-12, ~30 % fewer iterations).
IPOPT_OPTIONS = {"tol": 1e-10, "acceptable_tol": 1e-9, "constr_viol_tol": 1e-9, "max_iter": 150,
                 "print_level": 0, "linear_solver": "mumps", "mu_strategy": "monotone",
                 "nlp_scaling_method": "gradient-based", "sb": "yes"}
#: From :data:`OBJECTIVE_SCALE_FROM` trials on, IPOPT's objective is scaled by
#: ``OBJECTIVE_SCALE_TRIALS / trials``: the objective's gradient grows with the number of trials,
#: each equilibrium constraint's does not.  Set 4 (60 trials, factor 0.1), 12 noise seeds: default
#: knee 9-85 -> 10-20 iterations (median 1.56 -> 1.10 s), synthetic knee 10-158 -> 9-21 (3.02 ->
#: 1.57 s), same optima.  Sets 2 and 3 (13, 26 trials) gained nothing beyond the seed-to-seed
#: spread at 6/trials, so smaller protocols keep IPOPT's own scaling (docs/solvers.md).  A user's
#: ``obj_scaling_factor`` wins.
OBJECTIVE_SCALE_TRIALS = 6
OBJECTIVE_SCALE_FROM = 40


@dataclass
class NLPExpressions:
    """The symbolic identification NLP (MX): decision vector, data vector, objective, constraints."""

    x: ca.MX
    p: ca.MX
    f: ca.MX
    g: ca.MX
    lbx: np.ndarray
    ubx: np.ndarray
    #: what the working sets are taken from: poses (SI, 5 x T), all parameters, flexions (1 x T)
    q_si: ca.MX | None = None
    theta: ca.MX | None = None
    flexion: ca.MX | None = None


def nlp_expressions(problem: IdentificationProblem, parallel: str = "serial", threads: int = 1,
                    working_sets: WorkingSetSource = "data", layout: Layout = "vector") -> NLPExpressions:
    """The NLP's expressions (see module docstring); ``parallel``/``threads`` set the trial map.

    ``working_sets``: ``"data"`` makes the contact working sets the last part of the data vector
    (T x ws_size: a self-contained program, exact where they were taken); ``"graph"`` computes
    the contact inside the graph from the pose (:attr:`KneeModel.exact_residual`: self-contained
    and exact everywhere, for export; ``layout`` the graph's shape,
    :data:`kneenlp.geometry.graph_field.LAYOUTS`); ``"pose"`` takes them at every pose evaluated
    (:class:`~kneenlp.model.workingsets.WorkingSets`; derivatives then pass through a callback,
    which is slow: :func:`build_nlp` instead supplies the derivative functions of the data form)."""
    model, T = problem.model, problem.n_trials
    xp = ca.MX.sym("p_free", problem.n_free)
    xq = ca.MX.sym("q_user", 5, T)
    data_layout = problem.layout(working_sets=working_sets == "data")
    par = ca.MX.sym("data", data_layout.size)
    data = data_layout.split(par)
    loads, flex = data["loads"], data["flexions"]
    theta = problem.theta_of_scaled(xp, data["theta"])
    q_si = coords_from_user(xq)
    if parallel == "thread" and threads > 1:
        mapped = model.residual.map(T, "thread", threads)
    else:
        mapped = model.residual.map(T, "serial" if parallel == "thread" else parallel)
    if working_sets == "graph":
        exact = model.exact_residual_loop if layout == "loop" else model.exact_residual
        mapped = exact.map(T, "thread", threads) if parallel == "thread" and threads > 1 else exact.map(T)
        g = ca.vec(mapped(q_si, theta, loads, flex))
    else:
        ws = (model.working_sets_function(T)(q_si, theta, flex) if working_sets == "pose" and model.ws_size
              else data["working_sets"])
        g = ca.vec(mapped(q_si, theta, loads, flex, ws))
    diff = model.observation.map(T)(q_si, theta, loads, flex) - data["measured"]
    f = ca.sum1(ca.sum2(data["weights"] * diff * diff)) + _prior_term(problem, xp, data)
    lbx, ubx = problem.x_bounds()
    return NLPExpressions(ca.vertcat(xp, ca.vec(xq)), par, f, g, lbx, ubx, q_si, theta, flex)


def _prior_term(problem: IdentificationProblem, xp: ca.MX | ca.SX, data: dict) -> ca.MX | ca.SX:
    """The priors' share of the MAP objective (:func:`~kneenlp.experiment.problem.prior_rows`
    squared) of the scaled free parameters ``xp``; centres and widths come from the data vector,
    so changing a prior never rebuilds the NLP (only which priors are log-normal is its structure)."""
    if not problem.priors:
        return 0
    rows = prior_rows(xp * problem.scales, data["prior_centre"], data["prior_inv_sd"], problem.prior_logs)
    return ca.sumsqr(rows)


@dataclass
class IdentificationNLP:
    """A built NLP solver for problems of one layout (model, number of trials, free parameters)."""

    free: list[str]
    n_trials: int
    solver_name: str
    solver: ca.Function
    build_seconds: float


def build_nlp(problem: IdentificationProblem, solver: str = "ipopt", options: dict | None = None,
              threads: int = 2) -> IdentificationNLP:
    """Build the identification NLP solver of ``problem``'s layout (see module docstring)."""
    t0 = time.perf_counter()
    e = nlp_expressions(problem, "thread", threads, working_sets="data")
    nlp, derivatives = _with_working_sets_of_the_pose(problem, e)
    opts = {**derivatives, **dict(options or {})}
    if solver == "ipopt":
        opts = {"ipopt": {**IPOPT_OPTIONS, **ipopt_trial_options(problem.n_trials), **opts.pop("ipopt", {})},
                "print_time": False, "error_on_fail": False,
                **opts}
    else:
        opts = {"print_time": False, "error_on_fail": False, **opts}
    try:
        fn = ca.nlpsol(f"identify_{solver}", solver, nlp, opts)
    except RuntimeError as exc:
        raise InputError(f"cannot create NLP solver {solver!r}: {str(exc).splitlines()[-1]}",
                         field="solver") from None
    return IdentificationNLP(list(problem.free), problem.n_trials, solver, fn, time.perf_counter() - t0)


def ipopt_trial_options(n_trials: int) -> dict[str, float]:
    """IPOPT's options that depend on the number of trials: the objective's scaling
    (:data:`OBJECTIVE_SCALE_TRIALS`) and, for large protocols, the ceiling of the equilibrium
    residual along the iterates (:data:`THETA_MAX_FACT`); a user's options win over both."""
    if n_trials < OBJECTIVE_SCALE_FROM:
        return {"obj_scaling_factor": 1.0}
    return {"obj_scaling_factor": OBJECTIVE_SCALE_TRIALS / n_trials, "theta_max_fact": THETA_MAX_FACT}


def get_nlp(problem: IdentificationProblem, solver: str, options: dict | None, threads: int) -> IdentificationNLP:
    """The NLP solver of ``problem``'s layout (number of trials, free parameters), ``solver`` (a CasADi
    nlpsol plugin), its ``options`` and ``threads``, built once per model (``model.solvers``)."""
    key = ("nlp", problem.n_trials, tuple(problem.free), bool(problem.priors), problem.prior_logs, solver,
           frozen(options), threads)
    return problem.model.solvers.get(key, lambda: build_nlp(problem, solver, options, threads))


@dataclass(frozen=True)
class NlpSolver:
    """How the simultaneous NLP is solved: the CasADi ``nlpsol`` plugin ``name`` (``ipopt``,
    ``sqpmethod``, ...), its ``options`` (by plugin, e.g. ``{"ipopt": {"max_iter": 150}}``) and the
    ``threads`` of its trial map."""

    name: str = "ipopt"
    options: dict | None = None
    threads: int = 2


def solve_nlp(problem: IdentificationProblem, start: dict[str, float], how: NlpSolver = NlpSolver(),
              q0: np.ndarray | None = None) -> SolverResult:
    """One solve of the simultaneous NLP from ``start`` (SI values of every free parameter) as ``how``
    says, poses started at equilibrium (:func:`~kneenlp.solvers.equilibria.equilibrium_start`) or at ``q0``
    (T x 5, SI: e.g. a reduced-space fit's, the equilibria its continuation followed, which a solve from
    the unloaded state need not reach)."""
    t0 = time.perf_counter()
    threads = how.threads
    nlp = get_nlp(problem, how.name, how.options, threads)
    if q0 is None:
        eq = equilibrium_start(problem, problem.theta(start), threads)
        q_user, started_at_data = eq.q_user, int(np.sum(~eq.ok))
    else:
        q_user, started_at_data = coords_to_user(np.asarray(q0, float).reshape(-1, 5)), 0
    x0 = problem.to_x(start, q_user)
    lbx, ubx = problem.x_bounds()
    t1 = time.perf_counter()
    # contact working sets are taken at every pose IPOPT evaluates; after the solve no sample point left
    # out of them may penetrate (too few working-set slots, or contact outside the represented surface)
    with interrupts.deferred():  # Ctrl-C/SIGTERM: raised when the solve ends (CasADi would drop it)
        sol = nlp.solver(x0=x0, p=problem.data_vector(), lbx=lbx, ubx=ubx, lbg=0, ubg=0)
    st = nlp.solver.stats()
    values, q_user = problem.from_x(sol["x"])
    # IPOPT relaxes bounds by 1e-8 (scaled): a stiffness at its bound 0 ends at -1e-7 N/mm, which the
    # written calibration would then carry and every reader of it refuse; the bounds are the values' own
    values = np.clip(values, problem.lower, problem.upper)
    seconds = time.perf_counter() - t1
    g = np.asarray(sol["g"]).ravel()
    q, theta = coords_from_user(q_user), problem.theta(values)
    model = problem.model
    left_out, rim = -np.inf, 0.0
    if model.ws_size:
        left_out = float(np.max(model.left_out_batch(q, theta, problem.flexions, threads)))
        rim = float(np.max(model.rim_batch(q, theta, problem.flexions)))
    iterations = int(st.get("iter_count", 0))
    return SolverResult(solver=nlp.solver_name, values=dict(zip(problem.free, values, strict=True)), q=q,
                        objective=float(sol["f"]), success=bool(st.get("success", False)),
                        status=str(st.get("return_status", "unknown")), iterations=iterations,
                        evaluations=int(st.get("n_call_nlp_f", iterations)), seconds=seconds,
                        max_residual=float(np.max(np.abs(g))) if g.size else 0.0, start_seconds=t1 - t0,
                        build_seconds=nlp.build_seconds, left_out=left_out, rim=rim, started_at_data=started_at_data)


def _with_working_sets_of_the_pose(problem: IdentificationProblem, e: NLPExpressions) -> tuple[dict, dict]:
    """The NLP ``(x, p) -> (f, g)`` whose contact working sets are taken at every pose evaluated,
    and its derivative functions (``nlpsol`` options ``grad_f``, ``jac_g``, ``hess_lag``): those of
    the data form ``e`` evaluated with the working sets of the pose.  The working sets' own
    derivative is zero by construction (:mod:`kneenlp.model.workingsets`), so these are the exact
    derivatives, and no derivative has to pass through the Python callback."""
    model, T = problem.model, problem.n_trials
    if not model.ws_size:
        return {"x": e.x, "p": e.p, "f": e.f, "g": e.g}, {}
    n_base = e.p.numel() - T * model.ws_size
    x, p = ca.MX.sym("x", e.x.numel()), ca.MX.sym("p", n_base)
    no_ws = ca.DM.zeros(T * model.ws_size)
    where = ca.Function("poses", [e.x, e.p], [e.q_si, e.theta, e.flexion])(x, ca.vertcat(p, no_ws))
    p_full = ca.vertcat(p, ca.vec(model.working_sets_function(T)(*where)))
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", e.g.numel())
    f_of, g_of = ca.Function("f", [e.x, e.p], [e.f]), ca.Function("g", [e.x, e.p], [e.g])
    grad_f, jac_g, hess = _trial_block_derivatives(problem, e)
    derivatives = {
        "grad_f": ca.Function("nlp_grad_f", [x, p], grad_f.call([x, p_full]), ["x", "p"], ["f", "grad_f_x"]),
        "jac_g": ca.Function("nlp_jac_g", [x, p], jac_g.call([x, p_full]), ["x", "p"], ["g", "jac_g_x"]),
        "hess_lag": ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], hess.call([x, p_full, lam_f, lam_g]),
                                ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"]),
    }
    return {"x": x, "p": p, "f": f_of(x, p_full), "g": g_of(x, p_full)}, derivatives


def _trial_block_derivatives(problem: IdentificationProblem, e: NLPExpressions) -> tuple[ca.Function, ...]:
    """``grad_f``, ``jac_g`` and the upper triangle of the Lagrangian's Hessian of the data form ``e``
    (inputs ``(x, p)``, the Hessian's also ``(lam_f, lam_g)``), assembled from per-trial blocks.

    Trial ``t`` touches only its own pose and the free parameters, so every derivative is a sum or a
    stack of dense blocks over ``z_t = (q_t, p_free)``: the objective's gradient, the residual's 5 x
    (5 + n_free) Jacobian and the (5 + n_free)^2 Hessian of ``lam_f f_t + lam_t' r_t``.  The blocks
    come from one SX function (the residual expanded: its staged contact is a few operations on the
    working-set data), mapped over the trials on two threads; IPOPT's sparse matrices are assembled
    from them.  Differentiating the whole MX graph instead cost ~3x more per Hessian (its colouring
    seeds every trial with every parameter direction)."""
    model, T, nf = problem.model, problem.n_trials, problem.n_free
    residual = model.residual.expand()
    q_user, xp = ca.SX.sym("q_user", 5), ca.SX.sym("p_free", nf)
    theta_in, load = ca.SX.sym("theta", len(model.parameter_names)), ca.SX.sym("load", LOAD_SIZE)
    flexion = ca.SX.sym("flexion")
    ws, meas, w = ca.SX.sym("ws", model.ws_size), ca.SX.sym("measured", 5), ca.SX.sym("weights", 5)
    lam_f, lam = ca.SX.sym("lam_f"), ca.SX.sym("lam", 5)
    theta = problem.theta_of_scaled(xp, theta_in)
    q_si = coords_from_user(q_user)
    r = residual(q_si, theta, load, flexion, ws)
    diff = model.observation(q_si, theta, load, flexion) - meas
    f_t = ca.sum1(w * diff * diff)
    z = ca.vertcat(q_user, xp)
    ins = [q_user, xp, theta_in, load, flexion, ws, meas, w]
    # the objective's and the residual's first derivatives apart: grad_f and jac_g each evaluate their own
    objective = ca.Function("trial_objective", ins, [f_t, ca.gradient(f_t, z)])
    constraint = ca.Function("trial_constraint", ins, [r, ca.jacobian(r, z)])
    second = ca.Function("trial_hessian", [*ins, lam_f, lam], [ca.hessian(lam_f * f_t + ca.dot(lam, r), z)[0]])
    objective_map, constraint_map = objective.map(T, "thread", 2), constraint.map(T, "thread", 2)
    second_map = second.map(T, "thread", 2)

    x, p = ca.MX.sym("x", e.x.numel()), ca.MX.sym("p", e.p.numel())
    lam_fm, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 5 * T)
    xp_m, xq = x[:nf], ca.reshape(x[nf:], 5, T)
    d = problem.layout(working_sets=True).split(p)
    args = [xq, ca.repmat(xp_m, 1, T), ca.repmat(d["theta"], 1, T), d["loads"], d["flexions"], d["working_sets"],
            d["measured"], d["weights"]]
    f_all, g_all = objective_map(*args)
    r_all, j_all = constraint_map(*args)
    n = 5 + nf

    def block(m: ca.MX, t: int, rows: slice, cols: slice) -> ca.MX:
        return m[rows, t * n:(t + 1) * n][:, cols]

    qs, ps = slice(0, 5), slice(5, n)
    grad = ca.vertcat(ca.sum2(g_all[5:, :]), ca.vec(g_all[:5, :]))
    jac = ca.horzcat(ca.vertcat(*[block(j_all, t, slice(0, 5), ps) for t in range(T)]),
                     ca.diagcat(*[block(j_all, t, slice(0, 5), qs) for t in range(T)]))
    h_all = second_map(*args, ca.repmat(lam_fm, 1, T), ca.reshape(lam_g, 5, T))
    h_pp = sum((block(h_all, t, ps, ps) for t in range(T)), ca.MX.zeros(nf, nf))
    h_pq = ca.horzcat(*[block(h_all, t, ps, qs) for t in range(T)])
    f_sum = ca.sum2(f_all)
    if problem.priors:  # the priors touch the parameters alone: one small block
        centre, inv_sd = ca.SX.sym("prior_centre", nf), ca.SX.sym("prior_inv_sd", nf)
        pf = _prior_term(problem, xp, {"prior_centre": centre, "prior_inv_sd": inv_sd})
        prior = ca.Function("prior", [xp, centre, inv_sd], [pf, ca.gradient(pf, xp), ca.hessian(pf, xp)[0]])
        pv, pg, ph = prior(xp_m, d["prior_centre"], d["prior_inv_sd"])
        f_sum, grad, h_pp = f_sum + pv, grad + ca.vertcat(pg, ca.MX.zeros(5 * T)), h_pp + lam_fm * ph
    h_qq = ca.diagcat(*[block(h_all, t, qs, qs) for t in range(T)])
    hess = ca.vertcat(ca.horzcat(h_pp, h_pq), ca.horzcat(h_pq.T, h_qq))
    return (ca.Function("grad_f", [x, p], [f_sum, grad]),
            ca.Function("jac_g", [x, p], [ca.vec(r_all), jac]),
            ca.Function("hess_lagrangian", [x, p, lam_fm, lam_g], [ca.triu(hess)]))
