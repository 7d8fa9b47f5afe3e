"""CasADi functions compiled to C once per machine, with the same numbers as CasADi's own.

A knee's per-trial functions that Newton's iteration and the implicit-function sensitivities
evaluate thousands of times (:meth:`~kneenlp.experiment.kneemodel.KneeModel.trial_derivatives`) are
SX functions.  CasADi evaluates them in its virtual machine; the same operations as C, compiled by
the system's C compiler, take a fraction of the time (S192803's calibration, one start: 8.8 -> 5.1
s; benchmarks/bench_compiled.py).  The NLP's per-trial blocks stay in CasADi: they change with the
free parameters, and IPOPT's share of a calibration is small.

:func:`compiled` returns the function's library from the cache (:func:`~kneenlp.base.cache.cache_dir`,
``compiled/``), keyed by the SHA-256 of its serialized form, the compiler's flags and CasADi's version.  The flags
(``-O1 -ffp-contract=off``, no fast-math) keep every operation as the virtual machine does it, in
the same order: a library is used only if it gives the function's own values bit for bit at a seeded
probe input, so a result does not depend on whether the cache holds the library.

``$KNEENLP_COMPILE`` chooses when to compile:

* ``auto`` (the default): the cached library if there is one; otherwise the function itself, and
  the library is compiled in a detached, lowest-priority process for the next run (a first run
  never waits on a compiler, and one compile of a knee's functions takes 10-30 s);
* ``wait``: compile now if the cache lacks it (benchmarks, long studies);
* ``off``: never (the test suite, which builds many small models once each).

Without a C compiler (``$CC``, else ``cc``), a writable cache or a POSIX system, the function is
used as it is.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shlex
import shutil
import subprocess
import tempfile
import threading
import time
import warnings
from pathlib import Path

import casadi as ca
import numpy as np

from kneenlp.base.cache import cache_dir

#: The compiler's flags: optimised, but no contraction into fused multiply-adds and no fast-math, so
#: the library computes what CasADi's virtual machine computes, to the bit.
FLAGS = ("-shared", "-fPIC", "-O1", "-ffp-contract=off")
MODES = ("auto", "wait", "off")
#: A library not loaded for this many days is removed when another is compiled (an upgrade of the
#: package or of CasADi changes the code, and so the key: the old libraries would stay forever).
KEEP_DAYS = 30


def mode() -> str:
    """``$KNEENLP_COMPILE`` (module docstring), ``auto`` if unset or unknown."""
    value = os.environ.get("KNEENLP_COMPILE", "auto").strip().lower()
    return value if value in MODES else "auto"


def compiler() -> str | None:
    """The C compiler's path (``$CC``, else ``cc``), ``None`` without one."""
    return shutil.which(os.environ.get("CC", "cc")) if os.name == "posix" else None


def compiled(function: ca.Function) -> ca.Function:
    """``function`` as a compiled library where that is possible and gives its values bit for bit,
    otherwise ``function`` itself (module docstring).  Only SX functions are compiled."""
    how, cc = mode(), compiler()
    if how == "off" or cc is None or not function.is_a("SXFunction"):
        return function
    where = cache_dir("compiled")
    if where is None:
        return function
    name = function.name()
    # the key: the function's serialized form (a third of the time of generating its C code, which
    # only a missing library needs), the flags and CasADi's version
    key = hashlib.sha256(function.serialize().encode() + " ".join(FLAGS).encode()
                         + ca.__version__.encode()).hexdigest()[:24]
    library = where / f"{name}_{key}.so"
    if not library.exists():
        generator = ca.CodeGenerator(f"{name}.c")
        generator.add(function)
        source = generator.dump().encode()
        _prune(where)
        src = where / f"{name}_{key}.{os.getpid()}.c"  # this process's copy: removed by its own command
        _write(src, source)
        if how == "auto":
            _compile_detached(cc, src, library)
            return function
        _compile(cc, src, library)
    return _loaded(function, library)


def _prune(where: Path) -> None:
    """Remove the libraries in ``where`` not loaded for :data:`KEEP_DAYS` days (:func:`_loaded`
    touches a library it loads)."""
    cutoff = time.time() - KEEP_DAYS * 86400
    for old in [*where.glob("*.so"), *where.glob("*.lock")]:
        with contextlib.suppress(OSError):
            if old.stat().st_mtime < cutoff:
                old.unlink()


def _write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (another process may write the same)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "wb") as out:
        out.write(data)
    os.replace(tmp, path)


def _command(cc: str, src: Path, library: Path, wait: bool) -> str:
    """The shell command compiling ``src`` into ``library`` atomically (a temporary, then renamed),
    once per library however many processes ask at once: under an exclusive lock on the library's
    lock file (``flock``; waited for if ``wait``, else given up: another process compiles it), and
    only if the library is still missing when the lock is taken.  ``src`` is removed in every case."""
    tmp, src_q, lib_q = shlex.quote(f"{library}.{os.getpid()}.tmp"), shlex.quote(str(src)), shlex.quote(str(library))
    build = f"test -e {lib_q} || {{ {shlex.quote(cc)} {' '.join(FLAGS)} {src_q} -o {tmp} -lm && mv -f {tmp} {lib_q}; }}"
    flock = shutil.which("flock")
    if flock is not None:
        lock = shlex.quote(str(library.with_suffix(".lock")))
        build = f"{shlex.quote(flock)} {'' if wait else '-n '}{lock} sh -c {shlex.quote(build)}"
    return f"{build}; rm -f {tmp} {src_q}"


def _compile(cc: str, src: Path, library: Path) -> None:
    """Compile now (or wait for the process that does); a failure leaves no library (the function
    is then used as it is)."""
    subprocess.run(["sh", "-c", _command(cc, src, library, wait=True)], stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, check=False)


def _compile_detached(cc: str, src: Path, library: Path) -> None:
    """Compile in a process of its own session at the lowest priority, not waited for (it outlives
    the caller, and takes almost no CPU from a solve that runs meanwhile); nothing if another
    process is compiling the same library."""
    nice = shutil.which("nice")
    command = ([nice, "-n", "19"] if nice else []) + ["sh", "-c", _command(cc, src, library, wait=False)]
    subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                     close_fds=True)


def _loaded(function: ca.Function, library: Path) -> ca.Function:
    """The library's function if it loads and gives ``function``'s values bit for bit at a seeded
    probe input, else ``function``."""
    if not library.exists():
        return function
    try:
        external = ca.external(function.name(), str(library))
    except RuntimeError:
        return function
    rng = np.random.default_rng(0)
    args = [rng.uniform(-1.0, 1.0, function.sparsity_in(i).shape) for i in range(function.n_in())]
    ours, theirs = function(*args), external(*args)
    ours, theirs = (ours, theirs) if isinstance(ours, (list, tuple)) else ([ours], [theirs])
    same = all(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True) for a, b in zip(ours, theirs, strict=True))
    if not same:
        warnings.warn(f"the compiled {function.name()} differs from CasADi's own; it is not used ({library})",
                      stacklevel=3)
        return function
    with contextlib.suppress(OSError):
        os.utime(library)  # in use: kept by _prune
    return external


class BufferedCall:
    """Numeric calls of a CasADi function through its :meth:`casadi.Function.buffer`: the inputs are
    copied into preallocated arrays and the outputs read from others, without CasADi's conversions
    of every argument (a small function's call: ~80 -> ~5 us).  The same evaluation as calling the
    function, so the same numbers.  Arguments and results are flat arrays in CasADi's (column-major)
    order of each input and output; calls are serialised (one buffer)."""

    def __init__(self, function: ca.Function):
        dense = [function.sparsity_in(i).is_dense() for i in range(function.n_in())]
        dense += [function.sparsity_out(i).is_dense() for i in range(function.n_out())]
        if not all(dense):
            raise ValueError(f"{function.name()}: a buffered call needs dense inputs and outputs")
        self.function = function
        self._buffer, self._evaluate = function.buffer()
        self._args = [np.zeros(function.nnz_in(i)) for i in range(function.n_in())]
        self._results = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
        for i, a in enumerate(self._args):
            self._buffer.set_arg(i, memoryview(a))
        for i, r in enumerate(self._results):
            self._buffer.set_res(i, memoryview(r))
        self._lock = threading.Lock()

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        """The outputs (flat copies) at the inputs ``args`` (each flat in CasADi's order, or broadcast)."""
        with self._lock:
            for mine, a in zip(self._args, args, strict=True):
                mine[:] = np.ravel(a)
            self._evaluate()
            return [r.copy() for r in self._results]
