"""Compiled CasADi functions (kneenlp.base.compiled): the same numbers as CasADi's own, or not used.

The oracle is CasADi's virtual machine evaluating the same function: a compiled library must agree
with it bit for bit, on a small function here and on a real knee's forward solve (slow).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np
import pytest

from kneenlp.base import compiled as cmod
from kneenlp.base.compiled import compiled

pytestmark = pytest.mark.skipif(cmod.compiler() is None, reason="no C compiler")


def small(name: str = "small", cos: bool = False) -> ca.Function:
    x, y = ca.SX.sym("x", 3), ca.SX.sym("y")
    f = ca.cos(x) if cos else ca.sin(x) * y + ca.sqrt(x * x + 1) / (y * y + 2) - ca.fmax(x, 0.3 * y)
    return ca.Function(name, [x, y], [f, ca.jacobian(f, x)])


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("KNEENLP_CACHE", str(tmp_path))
    return tmp_path / "compiled"


def test_a_compiled_function_gives_casadis_values_bit_for_bit(cache, monkeypatch):
    monkeypatch.setenv("KNEENLP_COMPILE", "wait")
    f = small()
    g = compiled(f)
    assert not g.is_a("SXFunction")  # the library, not the function
    assert len(list(cache.glob("small_*.so"))) == 1 and not list(cache.glob("*.c"))
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, y = rng.normal(size=3) * 10, rng.normal() * 10
        for a, b in zip(f(x, y), g(x, y), strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b))
    assert compiled(small()).is_a("SXFunction") is False  # from the cache


def test_auto_compiles_in_the_background_for_the_next_call(cache, monkeypatch):
    monkeypatch.setenv("KNEENLP_COMPILE", "auto")
    f = small("later")
    assert compiled(f) is f  # nobody waits on the compiler
    deadline = time.monotonic() + 120
    while not list(cache.glob("later_*.so")) and time.monotonic() < deadline:
        time.sleep(0.2)
    g = compiled(small("later"))
    assert not g.is_a("SXFunction")


def test_off_no_compiler_and_mx_functions_are_left_as_they_are(cache, monkeypatch):
    monkeypatch.setenv("KNEENLP_COMPILE", "off")
    f = small()
    assert compiled(f) is f
    monkeypatch.setenv("KNEENLP_COMPILE", "wait")
    monkeypatch.setenv("CC", "/nonexistent/cc")
    assert compiled(f) is f
    monkeypatch.delenv("CC")
    x = ca.MX.sym("x")
    h = ca.Function("h", [x], [2 * x])
    assert compiled(h) is h
    assert not cache.exists() or not list(cache.iterdir())


def test_a_library_that_differs_is_not_used(cache, monkeypatch):
    monkeypatch.setenv("KNEENLP_COMPILE", "wait")
    other = compiled(small("same_name", cos=True))  # a library of another function of the same name
    assert not other.is_a("SXFunction")
    library = next(cache.glob("same_name_*.so"))
    f = small("same_name")
    with pytest.warns(UserWarning, match="differs from CasADi's own"):
        assert cmod._loaded(f, library) is f


@pytest.mark.slow
def test_a_real_knee_solves_the_same_with_its_compiled_functions(cache, monkeypatch):
    """S192803's 25 trials: the forward solve with compiled residuals is CasADi's own, to the bit."""
    import kneenlp
    from kneenlp.base.resources import resource
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.experiment.measured import read_measured
    from kneenlp.solvers.forward import ForwardSolver

    trials = read_measured(resource("datasets", "s192803_laxity.csv")).trials
    knee = kneenlp.Knee.named("s192803")
    poses = {}
    for how in ("off", "wait"):
        monkeypatch.setenv("KNEENLP_COMPILE", how)
        model = KneeModel(knee)
        assert model._residual_and_jacobian.is_a("SXFunction") == (how == "off")
        poses[how] = np.array([s.q for s in ForwardSolver(model).solve(trials, model.theta())])
    assert np.array_equal(poses["off"], poses["wait"])


def test_a_buffered_call_is_the_functions_call():
    """BufferedCall: the same numbers as calling the function (flat, column-major), and a function
    with sparse outputs refused (its flat results would not be the dense matrices)."""
    from kneenlp.base.compiled import BufferedCall

    xs, ys = ca.SX.sym("x", 3), ca.SX.sym("y")
    f = ca.Function("dense", [xs, ys], [ca.densify(v) for v in small()(xs, ys)]).map(4)
    x, y = np.arange(12.0).reshape(3, 4) / 7, np.linspace(-1, 2, 4)
    value, jac = BufferedCall(f)(x.ravel(order="F"), y)
    assert np.array_equal(value, np.asarray(f(x, y)[0]).ravel(order="F"))
    assert np.array_equal(jac, np.asarray(f(x, y)[1]).ravel(order="F"))
    s = ca.SX.sym("s", 3)
    with pytest.raises(ValueError, match="dense"):
        BufferedCall(ca.Function("sparse", [s], [ca.jacobian(ca.sin(s), s)]))


def test_libraries_unused_for_a_month_are_removed_when_another_is_compiled(cache, monkeypatch):
    """An upgrade changes the code and so the key: the old library would stay forever.  A library
    loaded within KEEP_DAYS is kept (loading touches it); an older one goes when another compiles."""
    import os

    monkeypatch.setenv("KNEENLP_COMPILE", "wait")
    compiled(small("kept"))
    compiled(small("old"))
    kept, old = next(cache.glob("kept_*.so")), next(cache.glob("old_*.so"))
    month = time.time() - (cmod.KEEP_DAYS + 1) * 86400
    for path in (kept, old):
        os.utime(path, (month, month))
    assert not compiled(small("kept")).is_a("SXFunction")  # loaded: touched
    compiled(small("new"))
    assert kept.exists() and not old.exists() and list(cache.glob("new_*.so"))


def test_processes_asking_at_once_compile_a_library_once(cache, tmp_path, monkeypatch):
    """Three processes that need the same library at the same moment: one compiler runs (the others
    wait on its lock, then load its library), every one gets the library, and no source is left."""
    import os
    import shutil
    import subprocess
    import sys

    log = tmp_path / "compiler.log"
    wrapper = tmp_path / "cc"
    wrapper.write_text(f"#!/bin/sh\necho run >> {log}\nsleep 1\nexec {shutil.which('cc')} \"$@\"\n")
    wrapper.chmod(0o755)
    code = ("import casadi as ca; from kneenlp.base.compiled import compiled; x = ca.SX.sym('x', 3); "
            "f = ca.Function('shared', [x], [ca.sin(x) * x]); print(compiled(f).is_a('SXFunction'))")
    env = os.environ | {"KNEENLP_CACHE": str(tmp_path), "KNEENLP_COMPILE": "wait", "CC": str(wrapper)}
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True)
             for _ in range(3)]
    outs = [p.communicate(timeout=120)[0].strip() for p in procs]
    assert outs == ["False"] * 3  # every process loaded the library
    assert log.read_text().count("run") == 1
    assert len(list(cache.glob("shared_*.so"))) == 1 and not list(cache.glob("*.c"))
