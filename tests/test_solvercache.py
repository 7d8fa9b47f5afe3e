"""Built solvers live in one place (KneeModel.solvers), keyed by what changes them."""

from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.protocol import Protocol
from kneenlp.model.solvercache import SolverCache, frozen
from kneenlp.solvers.forward import forward_solver
from kneenlp.solvers.nlp import get_nlp


def test_frozen_options_ignore_order_and_see_values():
    a = {"ipopt": {"max_iter": 60, "tol": 1e-8}, "print_time": False}
    b = {"print_time": False, "ipopt": {"tol": 1e-8, "max_iter": 60}}
    assert frozen(a) == frozen(b) and hash(frozen(a)) == hash(frozen(b))
    assert frozen(a) != frozen({"ipopt": {"max_iter": 61, "tol": 1e-8}, "print_time": False})
    assert frozen(None) == frozen({}) == ()


def test_cache_builds_once():
    cache, built = SolverCache(), []
    for _ in range(3):
        cache.get(("x", 1), lambda: built.append(1) or len(built))
    assert built == [1] and ("x", 1) in cache and len(cache) == 1
    cache.clear()
    assert len(cache) == 0


def test_model_keeps_each_solver_once(model):
    model.solvers.clear()
    assert forward_solver(model) is not forward_solver(model)  # a solver with memory is its caller's
    assert not len(model.solvers)
    problem = IdentificationProblem(model, Protocol.load("set1").trials, ["ACL.k"])
    one = get_nlp(problem, "ipopt", {"ipopt": {"max_iter": 60, "tol": 1e-8}}, 1)
    n = len(model.solvers)
    assert get_nlp(problem, "ipopt", {"ipopt": {"tol": 1e-8, "max_iter": 60}}, 1) is one
    assert len(model.solvers) == n
    assert get_nlp(problem, "ipopt", {"ipopt": {"max_iter": 61, "tol": 1e-8}}, 1) is not one
    assert len(model.solvers) == n + 1
