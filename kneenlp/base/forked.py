"""Independent deterministic jobs shared out over forked processes, results in order.

What a calibration's starts and a cross-validation's hold-outs need: each job is a function of its
item alone, so sharing the items out changes nothing in the results, only the wall time.  Fork
(Linux), because the workers inherit the model: its compiled CasADi functions are not picklable.
A result is sent back through a pipe after ``pack`` strips what cannot be pickled (the model) and
``unpack`` puts it back in the parent.  Elsewhere, or with one worker, the jobs run here in turn.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import TypeVar

from kneenlp.base import interrupts

Item = TypeVar("Item")
Result = TypeVar("Result")


def one_blas_thread():
    """A context in which NumPy's and SciPy's BLAS run on one thread: in a worker of a pool that
    fills the cores, a BLAS on two threads per worker oversubscribes them (the global search of
    S192803 on 2 workers: 64 s with OpenBLAS's default of two threads each, 53 s with one)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def _same(result):
    return result


def forked_map(work: Callable[[Item], Result], items: list[Item], workers: int, *,
               pack: Callable[[Result], Result] = _same, unpack: Callable[[Result], Result] = _same) -> list[Result]:
    """``[work(item) for item in items]``; with ``workers`` > 1 on Linux the items are shared out
    round-robin over that many forked processes (module docstring).  An exception in a worker is
    raised here; the workers stop when this returns or raises (Ctrl-C included)."""
    if workers <= 1 or len(items) <= 1 or not sys.platform.startswith("linux"):
        return [work(item) for item in items]
    from multiprocessing import get_context

    ctx = get_context("fork")
    shares = [list(range(len(items)))[i::workers] for i in range(min(workers, len(items)))]
    running = []
    try:
        for share in shares:
            receive, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_worker, args=(work, [items[i] for i in share], pack, send), daemon=True)
            proc.start()
            send.close()
            running.append((proc, receive, share))
        out: dict[int, Result] = {}
        for proc, receive, share in running:
            status, payload = receive.recv()
            proc.join()
            if status == "error":
                raise payload
            out |= {i: unpack(r) for i, r in zip(share, payload, strict=True)}
    finally:
        for proc, _, _ in running:
            if proc.is_alive():
                proc.terminate()
    return [out[i] for i in range(len(items))]


def _worker(work: Callable, items: list, pack: Callable, send) -> None:
    """A forked process's jobs, sent back as ("ok", packed results) or ("error", exception); its
    BLAS on one thread (:func:`one_blas_thread`)."""
    interrupts.as_worker()
    try:
        with one_blas_thread():
            results = [work(item) for item in items]  # every job before any packing: a job may share what pack strips
        send.send(("ok", [pack(r) for r in results]))
    except Exception as exc:  # sent to the parent, which raises it
        send.send(("error", exc))
    finally:
        send.close()
