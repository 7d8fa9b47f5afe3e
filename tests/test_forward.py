"""Forward laxity simulation on the default knee: convergence, plausibility, signs."""

from pathlib import Path

import numpy as np
import pytest

import kneenlp
import kneenlp.base.resources
from kneenlp.base.conventions import LOAD_SIZE, coords_to_user
from kneenlp.experiment.protocol import Loading, Protocol, Trial
from kneenlp.solvers.forward import BatchStart, ForwardSolver, forward_solver
from kneenlp.solvers.workspace import ForwardMemory

PRIMARY = {"anterior": (3, 1), "posterior": (3, -1), "varus": (0, 1), "valgus": (0, -1),
           "internal": (1, 1), "external": (1, -1)}


def changes(result):
    """Change of every trial's coordinates (mm, deg) from the no-load pose at its flexion."""
    base = {s.trial.flexion_deg: coords_to_user(s.q) for s in result.solutions if s.trial.direction == "none"}
    return {s.trial.id: (s.trial, coords_to_user(s.q) - base[s.trial.flexion_deg]) for s in result.solutions}


@pytest.mark.parametrize("name,n", [("set1", 7), ("set2", 13), ("set3", 26), ("set4", 60)])
def test_protocols_have_table2_sizes_and_converge(knee, name, n):
    res = kneenlp.simulate(knee, name)
    assert len(res.solutions) == n
    assert res.converged == n, [s.trial.id for s in res.failed]
    assert res.max_residual <= 1e-6


def test_every_load_moves_the_tibia_in_its_own_direction(set3):
    for trial, d in changes(set3).values():
        if trial.direction == "none":
            continue
        j, sign = PRIMARY[trial.direction]
        assert sign * d[j] > 0, (trial.id, d)


def test_laxities_are_plausible(set3):
    d = {k: v[1] for k, v in changes(set3).items()}
    assert 0.5 <= d["anterior_134N_flex30"][3] <= 10.0
    assert 0.3 <= -d["posterior_67N_flex30"][3] <= 8.0
    assert 0.3 <= d["varus_10Nm_flex0"][0] <= 6.0
    assert 0.3 <= -d["valgus_10Nm_flex0"][0] <= 6.0
    assert 1.0 <= d["internal_2Nm_flex30"][1] <= 20.0
    assert 1.0 <= -d["external_2Nm_flex30"][1] <= 20.0


def test_every_ligament_carries_load_in_set3(set3):
    forces = np.array([[s.outputs[f"{n}_force_N"] for n in set3.knee.ligaments] for s in set3.solutions])
    assert np.all(forces.max(axis=0) > 20.0)


def test_acl_pretension_near_700N_at_reference_pose(model):
    ws = model.working_set(np.zeros(5), model.theta(), 0.0)[1]
    out = np.asarray(model.details(np.zeros(5), model.theta(), np.zeros(LOAD_SIZE), 0.0, ws)[1]).ravel()
    columns = [o.column for _, o in model.outputs]
    assert out[columns.index("ACL_force_N")] == pytest.approx(700.0, rel=1e-9)


@pytest.mark.parametrize("axes", ["joint", "femoral"])
def test_paper_fig2_isolating_load_cases(knee, axes):
    """The paper's Fig. 2: anterior load at 0 deg isolates the ACL, valgus at 0 deg the MCL, varus
    at 30 deg the LCL (the named ligament's force rises more than any other's).

    With the loads along the joint axes all three hold.  With the paper's femoral-frame loads a
    varus moment at 30 deg flexion carries sin(30 deg) = 1/2 of itself as internal moment about the
    tibial axis, which the cruciates resist: then the ACL dominates that case (docs/model.md,
    ``docs/scripts/fig2_axes_scan.py``: 1 of 36 synthetic knees with attachments moved by +-5 mm)."""
    import tomllib

    doc = tomllib.loads((kneenlp.base.resources.resource("protocols", "set3.toml")).read_text())
    doc["load_axes"] = axes
    rec = kneenlp.simulate(knee, Protocol.from_dict(doc)).recruitment().set_index("trial")
    dominant = rec["dominant"]
    for trial in ("anterior_134N_flex0", "anterior_80.4N_flex0"):
        assert dominant[trial] == "ACL", rec.loc[trial]
    for trial in ("valgus_10Nm_flex0", "valgus_6Nm_flex0"):
        assert dominant[trial] == "MCL", rec.loc[trial]
    varus30 = dominant[["varus_10Nm_flex30", "varus_6Nm_flex30"]]
    assert (varus30 == ("LCL" if axes == "joint" else "ACL")).all(), rec.loc[varus30.index]
    assert np.all(rec.loc[["none_flex0", "none_flex30"]].filter(like="change").to_numpy() == 0.0)


def test_nonconvergent_trial_is_reported_not_kept(model):
    fine = Trial("none_flex30", 30.0, {}, "none", 0.0)
    absurd = Trial("anterior_100kN_flex30", 30.0, {"anterior_force": 1e5}, "anterior", 1e5)
    sols = ForwardSolver(model).solve([fine, absurd], model.theta())
    assert sols[0].converged
    # no equilibrium within the envelope: Newton stops with the residual (or, had it found a dislocated
    # pose, the envelope check would reject it)
    assert not sols[1].converged and sols[1].strategy == "failed"
    assert "implausible" in sols[1].reason or sols[1].max_residual > 1.0, sols[1].reason
    # too few Newton iterations: reported with its residual
    sol = ForwardSolver(model, max_iter=2).solve_trial(
        Trial("anterior_134N_flex30", 30.0, {"anterior_force": 134.0}, "anterior", 134.0), model.theta())
    assert not sol.converged and sol.max_residual > 1e-6 and "residual" in sol.reason


def test_warm_start_reproduces_cold_solution(model, set3):
    solver = ForwardSolver(model)
    trials = [s.trial for s in set3.solutions]
    again = solver.solve(trials, model.theta(), {s.trial.id: s.q for s in set3.solutions})
    assert np.allclose([s.q for s in again], set3.q, atol=1e-10)


def test_parameter_continuation_reaches_the_cold_solution(model):
    """A trial's equilibrium at new parameters followed from its equilibrium at old ones (the retry
    of an outer fit's batch solve) is the forward solver's own solution at the new parameters."""
    solver = ForwardSolver(model)
    trial = Trial("anterior_134N_flex30", 30.0, {"anterior_force": 134.0}, "anterior", 134.0)
    theta0 = model.theta()
    theta = theta0.copy()
    for name, factor in (("ACL.k", 0.4), ("MCL.ref_strain", 3.0), ("PCL.k", 2.0)):
        theta[model.index(name)] *= factor
    q0 = solver.solve_trial(trial, theta0).q
    q, res = solver.continue_parameters(trial, theta0, theta, q0)
    cold = solver.solve_trial(trial, theta)
    assert res <= solver.tol and cold.converged
    assert np.allclose(q, cold.q, atol=1e-9)
    # a batch solve's retry takes that path: 4 Newton iterations do not reach the new equilibrium
    # from the old one, but do from the continuation's halfway pose
    short = ForwardSolver(model, max_iter=4)
    direct = short.newton.solve(q0[None, :], theta, Loading.of([trial]), 4)
    assert not direct.residual[0] <= short.tol
    q_batch, res_batch = short.solve_batch([trial], theta, BatchStart(q0[None, :], theta0=theta0), threads=1)
    assert res_batch[0] <= short.tol and np.allclose(q_batch[0], cold.q, atol=1e-8)


def test_a_workspace_is_the_callers_and_changes_no_result(model, set3):
    """Solvers share what they remember only through a workspace their caller passes; a solver with
    another (or a new one) computes the same poses, bit for bit."""
    trials, theta = [s.trial for s in set3.solutions], model.theta()
    memory = ForwardMemory()
    first = forward_solver(model, memory=memory).solve(trials, theta)
    assert memory.solved and forward_solver(model).memory is not memory and not forward_solver(model).memory.solved
    again = forward_solver(model, memory=memory).solve(trials, theta)
    fresh = forward_solver(model).solve(trials, theta)
    for a, b, c in zip(first, again, fresh, strict=True):
        assert np.array_equal(a.q, b.q) and np.array_equal(a.q, c.q)


def test_cold_start_remembers_the_passive_path():
    """A knee imaged at another pose walks from its reference flexion to each trial's; the walk of
    the last parameters is remembered, and what a flexion gets does not depend on the flexions
    asked for before it (the same numbers, bit for bit, in either order)."""
    model = kneenlp.experiment.kneemodel.KneeModel.of(kneenlp.Knee.named("s192803"))
    theta = model.theta()
    flexions = np.radians([60.0, 30.0, 47.5, 87.0])
    fresh = [ForwardSolver(model).cold_start(f, theta) for f in flexions]
    solver = ForwardSolver(model)
    in_order = [solver.cold_start(f, theta) for f in flexions]
    backwards = ForwardSolver(model)
    reverse = [backwards.cold_start(f, theta) for f in flexions[::-1]][::-1]
    for a, b, c in zip(fresh, in_order, reverse, strict=True):
        assert np.array_equal(a, b) and np.array_equal(a, c)
    assert np.radians(30.0) in solver.memory.passive[1] and np.radians(60.0) in solver.memory.passive[1]
    reference = model.knee.reference_pose[0]
    assert not np.allclose(fresh[0], ForwardSolver(model).reference)  # it did walk
    theta[model.index("ACLam.k_scale")] *= 2  # other parameters: a new path
    solver.cold_start(np.radians(60.0), theta)
    assert max(abs(f - reference) for f in solver.memory.passive[1]) == pytest.approx(abs(np.radians(60.0) - reference))


def test_fig2_axes_scan_script_runs(capsys):
    """docs/scripts/fig2_axes_scan.py (the evidence in docs/model.md) stays runnable."""
    import runpy

    scan = runpy.run_path(str((Path(__file__).resolve().parents[1] / "docs") / "scripts" / "fig2_axes_scan.py"))
    scan["main"](2, 2.0, 1)
    out = capsys.readouterr().out
    assert "2 knees, attachments moved by up to +-2 mm (seed 1)" in out
    assert out.count("\nfemoral ") == 1 and out.count("\njoint ") == 1


def test_load_point_shift_adds_the_virtual_work_of_the_moved_force(model):
    """LoadPoint (a candidate of real experiments): a robot's joint loads whose force acts at the
    tibial origin shifted by d (tibial frame) add F . d(R d)/dq to the residual, F the force whose
    components along e1, e2, e3 are the joint forces; oracle: central differences of the tibial pose."""
    from kneenlp.base.conventions import load_vector
    from kneenlp.model.kinematics import tibial_pose

    q = np.array([0.03, -0.1, 0.001, 0.002, -0.001])
    flexion = 0.6
    load = load_vector({"anterior_force": 150.0, "lateral_force": -40.0, "proximal_force": -60.0,
                        "internal_moment": 1.0}, axes="jcs")
    d = np.array([0.004, -0.003, 0.008])  # m
    theta0 = model.theta()
    theta1 = model.theta({"load_point.anterior": d[0], "load_point.proximal": d[1], "load_point.lateral": d[2]})
    ws = model.working_data(q, theta0, flexion)
    extra = (np.asarray(model.residual(q, theta1, load, flexion, ws)).ravel()
             - np.asarray(model.residual(q, theta0, load, flexion, ws)).ravel())

    def point(qq):
        R, _, axes = tibial_pose(flexion, qq)
        return np.asarray(R) @ d, np.column_stack([np.asarray(a).ravel() for a in axes])

    _, E = point(q)
    force = np.linalg.solve(E.T, load[8:11])
    h = 1e-7
    oracle = np.array([force @ (point(q + h * np.eye(5)[i])[0] - point(q - h * np.eye(5)[i])[0]) / (2 * h)
                       for i in range(5)])
    assert np.allclose(extra, oracle, atol=1e-6 * np.abs(oracle).max())
    assert np.abs(oracle[:2]).max() > 0.1  # the shift matters (N m)
    # the experiment's tibial origin moved by d (TibialOrigin) moves the joint loads' point the same
    # way, and adds to a LoadPoint shift
    axes = ("anterior", "proximal", "lateral")
    moved = model.theta({f"tibial_origin.{a}": v for a, v in zip(axes, d, strict=True)})
    both = model.theta({f"{e}.{a}": v / 2 for e in ("tibial_origin", "load_point")
                        for a, v in zip(axes, d, strict=True)})
    plain = np.asarray(model.residual(q, theta0, load, flexion, ws)).ravel()
    for theta in (moved, both):
        assert np.allclose(np.asarray(model.residual(q, theta, load, flexion, ws)).ravel() - plain, extra, atol=1e-12)
    femoral = load_vector({"anterior_force": 150.0, "internal_moment": 1.0}, axes="femoral")
    assert np.allclose(np.asarray(model.residual(q, moved, femoral, flexion, ws)).ravel(),
                       np.asarray(model.residual(q, theta0, femoral, flexion, ws)).ravel(), atol=1e-12)


def test_a_repeated_newton_solve_is_answered_from_memory(model, monkeypatch):
    """The single-trial Newton solve is a function of its inputs: asked again (a retry repeating a
    ramp), the solver answers from memory, bit for bit, without solving; other inputs solve."""
    solver = ForwardSolver(model)
    trial = Trial("anterior_134N_flex30", 30.0, {"anterior_force": 134.0}, "anterior", 134.0)
    theta, start = model.theta(), solver.cold_start(trial.flexion, model.theta())
    calls = []
    solve = solver.newton.solve
    monkeypatch.setattr(solver.newton, "solve", lambda *a, **k: calls.append(1) or solve(*a, **k))
    q1, res1 = solver._newton(start, theta, trial)
    q1[:] = np.nan  # a caller's changes do not reach the memory
    q2, res2 = solver._newton(start.copy(), theta.copy(), trial)
    assert len(calls) == 1 and res2 == res1 and res1 <= solver.tol
    assert np.array_equal(q2, ForwardSolver(model)._newton(start, theta, trial)[0])
    solver._newton(start, theta, trial, 0.5)  # another load: solved
    assert len(calls) == 2


@pytest.mark.parametrize("knee_name,protocol", [("default", "set3"), ("s192803", None)])
def test_a_trial_solves_the_same_alone_in_a_batch_or_in_any_order(knee_name, protocol):
    """The loading path starts every trial from its flexion's unloaded state, never from another
    trial: the batched solve of a protocol, its trials solved one by one by fresh solvers and the
    protocol in reverse order give the same poses and strategies, bit for bit (set 3: several
    trials per flexion; S192803: one flexion each)."""
    model = kneenlp.experiment.kneemodel.KneeModel.of(kneenlp.Knee.named(knee_name))
    if protocol:
        trials = list(Protocol.load(protocol).trials)
    else:
        from kneenlp.experiment.measured import read_measured
        trials = list(read_measured(kneenlp.base.resources.resource("datasets", "s192803_laxity.csv")).trials)
    theta = model.theta()
    batched = ForwardSolver(model).solve(trials, theta)
    single = [ForwardSolver(model).solve_trial(t, theta) for t in trials]
    reverse = ForwardSolver(model).solve(trials[::-1], theta)[::-1]
    assert all(s.converged for s in batched)
    for other in (single, reverse):
        assert all(np.array_equal(a.q, b.q) and a.strategy == b.strategy for a, b in zip(batched, other, strict=True))


class _SingularAtStart:
    """r = 1000 (q - 1e-3) in four coordinates and 1e6 (q4^2 - 1e-6) in the fifth (SI; steps of a
    millimetre or a milliradian): the Jacobian is singular at q4 = 0."""

    def trial_derivatives(self, q, theta, loading, threads):
        r = np.column_stack([1e3 * (q[:, :4] - 1e-3), 1e6 * (q[:, 4] ** 2 - 1e-6)])
        jac = np.zeros((len(q), 5, 5))
        jac[:, range(4), range(4)] = 1e3
        jac[:, 4, 4] = 2e6 * q[:, 4]
        return r, jac


def test_a_singular_jacobian_stops_its_trial_only():
    from kneenlp.solvers.newton import EquilibriumNewton

    q0 = np.array([[0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 5e-4]])
    out = EquilibriumNewton(_SingularAtStart()).solve(q0, None, Loading(np.zeros((2, LOAD_SIZE)), np.zeros(2)),
                                                      max_iter=30)
    assert out.residual[1] <= 1e-6 and np.allclose(out.q[1], 1e-3)  # its neighbour converges
    assert out.residual[0] >= 0.99 and np.allclose(out.q[0, :4], 1e-3)  # the singular one moves where it can


class _Bistable:
    """r = 1000 (1e-3 - q) in four coordinates (N, m) and a double well in the fifth,
    r5 = 1e6 (q5 - q5^3 / (1 mm)^2) + f (f the load's first component): at f = 0 a stable
    equilibrium at +-1 mm and an unstable one at 0; the left well's fold at f = 1e6 * 2 / 3^1.5 mm."""

    def trial_derivatives(self, q, theta, loading, threads):
        c2 = 1e-6
        r = np.column_stack([1e3 * (1e-3 - q[:, :4]), 1e6 * (q[:, 4] - q[:, 4] ** 3 / c2) + loading.loads[:, 0]])
        jac = np.zeros((len(q), 5, 5))
        jac[:, range(4), range(4)] = -1e3
        jac[:, 4, 4] = 1e6 * (1 - 3 * q[:, 4] ** 2 / c2)
        return r, jac


def test_settling_finds_the_stable_equilibrium_newton_misses():
    """Newton converges to any root: from next to the double well's hump it stops on the unstable
    equilibrium (q5 = 0).  Settling follows the flow downhill into the well the start leans to
    (+1 mm); past the left well's fold (f = 390 N) it ends in the right well, the only one left."""
    from kneenlp.solvers.newton import EquilibriumNewton

    newton = EquilibriumNewton(_Bistable())
    q0 = np.array([[0.0, 0.0, 0.0, 0.0, 1e-5]])
    loads = np.zeros((1, LOAD_SIZE))
    root = newton.solve(q0, None, Loading(loads, np.zeros(1)))
    assert root.residual[0] <= 1e-6 and abs(root.q[0, 4]) < 1e-12  # the hump
    rest = newton.settle(q0, None, Loading(loads, np.zeros(1)))
    assert rest.residual[0] <= 1e-6 and rest.q[0, 4] == pytest.approx(1e-3, rel=1e-9)
    assert np.allclose(rest.q[0, :4], 1e-3)
    left = np.array([[1e-3, 1e-3, 1e-3, 1e-3, -1e-3]])
    pushed = loads.copy()
    pushed[0, 0] = 400.0  # beyond the left well's fold: no equilibrium near -1 mm
    snap = newton.settle(left, None, Loading(pushed, np.zeros(1)))
    assert snap.residual[0] <= 1e-6 and snap.q[0, 4] > 1e-3


def test_newton_steps_beside_a_singular_jacobian_are_the_batch_without_it():
    from kneenlp.solvers.newton import newton_steps

    rng = np.random.default_rng(0)
    jac, r = rng.standard_normal((16, 5, 5)), rng.standard_normal((16, 5))
    singular = jac.copy()
    singular[7] = 0.0
    assert np.array_equal(np.delete(newton_steps(singular, r), 7, 0), np.delete(newton_steps(jac, r), 7, 0))
    assert np.array_equal(newton_steps(singular, r)[7], np.zeros(5))  # least squares: no step where nothing acts


def test_a_knee_written_another_way_has_the_same_forces_and_solves_the_same():
    """S192803 with every group's stiffness scale moved into its bundles' stiffnesses
    (:func:`~kneenlp.testing.reference.rescaled_knee`): the residual is the same function of the pose
    (1e-9 of its scale at random poses), and Set 1 solves to the same poses (1e-6 mm and deg) by the
    same strategies.  (Sets 1-4 of the default knee: the next test; a calibration's FE copy:
    tests/test_real_experiment.py; all of them: benchmarks/bench_reparametrised.py.)"""
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.testing.reference import rescaled_knee

    knee = kneenlp.Knee.named("s192803")
    other = rescaled_knee(knee, np.random.default_rng(4))
    a, b = KneeModel.of(knee), KneeModel.of(other)
    assert not np.allclose(a.theta(), b.theta())  # the values differ ...
    rng = np.random.default_rng(5)
    q = np.asarray(knee.reference_pose[1], float) + rng.normal(0, 1, (20, 5)) * [0.02, 0.05, 1e-3, 1e-3, 3e-4]
    loads, flexions = np.zeros((20, LOAD_SIZE)), np.radians(rng.uniform(0, 90, 20))
    ra = ForwardSolver(a).newton.evaluate(q, a.theta(), Loading(loads, flexions))[0]
    rb = ForwardSolver(b).newton.evaluate(q, b.theta(), Loading(loads, flexions))[0]
    assert np.max(np.abs(ra - rb)) <= 1e-9 * np.max(np.abs(ra))  # ... the forces do not
    for s, t in zip(kneenlp.simulate(knee, "set1").solutions, kneenlp.simulate(other, "set1").solutions, strict=True):
        assert s.converged and t.converged and s.strategy == t.strategy
        assert np.max(np.abs(coords_to_user(s.q) - coords_to_user(t.q))) <= 1e-6


@pytest.mark.parametrize("seed", [1, 2])
def test_the_default_knee_written_another_way_solves_sets_1_to_4_the_same(seed):
    """Random re-parametrisations of the default knee (scales moved into stiffnesses): every trial of
    Sets 1-4 converges to the same pose (1e-6 mm and deg) by the same strategy."""
    from kneenlp.testing.reference import rescaled_knee

    knee = kneenlp.Knee.default()
    other = rescaled_knee(knee, np.random.default_rng(seed))
    for protocol in ("set1", "set2", "set3", "set4"):
        a, b = kneenlp.simulate(knee, protocol).solutions, kneenlp.simulate(other, protocol).solutions
        for s, t in zip(a, b, strict=True):
            assert s.converged and t.converged and s.strategy == t.strategy, (protocol, s.trial.id)
            assert np.max(np.abs(coords_to_user(s.q) - coords_to_user(t.q))) <= 1e-6, (protocol, s.trial.id)


def test_an_unstable_equilibrium_is_named_by_the_sign_of_its_stiffness_whatever_the_units():
    """``unstable_equilibria``: det(-dr/dq) <= 0 (an odd number of directions that run away).  The
    verdict does not change when the coordinates' units change (columns and rows scaled by positive
    factors); every trial a forward solve of Set 3 reaches on the default knee is stable."""
    from types import SimpleNamespace

    from kneenlp.solvers.forward import unstable_equilibria

    rng = np.random.default_rng(0)
    basis = np.linalg.qr(rng.normal(size=(5, 5)))[0]
    stable = -basis @ np.diag([1e5, 3e4, 2e3, 40.0, 20.0]) @ basis.T
    saddle = -basis @ np.diag([1e5, 3e4, 2e3, 40.0, -5.0]) @ basis.T
    units = np.diag([1.0, 1.0, 1e3, 1e3, 1e3])  # rad and mm for rad and m
    jacobians = np.stack([stable, saddle, units @ stable @ units, units @ saddle @ units])
    model = SimpleNamespace(trial_derivatives=lambda q, theta, loading, threads: (None, jacobians))
    flags = unstable_equilibria(model, np.zeros((4, 5)), np.zeros(1), Loading(np.zeros((4, LOAD_SIZE)), np.zeros(4)))
    assert flags.tolist() == [False, True, False, True]
    solutions = kneenlp.simulate(kneenlp.Knee.default(), "set3").solutions
    assert all(s.converged and s.stable for s in solutions)
