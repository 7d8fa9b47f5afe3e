"""How a command's options become a calibration's: its priors, its starts (the global search or the
local chain) and where they run (forked processes or Dask)."""

from __future__ import annotations

from pathlib import Path

from kneenlp.base.errors import InputError


def prior_options(args) -> dict:
    """``calibrate``'s prior options from ``--priors`` and ``--prior-weight`` (unset: its defaults)."""
    return {k: v for k, v in (("priors", args.priors), ("prior_weight", args.prior_weight)) if v is not None}


def worker_count(args) -> int:
    """``--workers``, by default every core: the processes independent calibrations share (the
    hold-outs', a calibration's further starts)."""
    import os

    return args.workers or os.cpu_count() or 1


def search_workers(args):
    """Where a global search's solves run: Dask (``--dask``, ``--scheduler``), else
    :func:`worker_count` forked processes."""
    if args.dask or args.scheduler:
        from kneenlp.base.dask_cluster import DaskWorkers

        return DaskWorkers(args.scheduler, worker_count(args))
    return worker_count(args)


def search_starts(args, calibration: bool) -> int:
    """The starts of a command's calibrations: ``--starts`` (or the problem's); by default the global
    search's :data:`~kneenlp.estimation.search.DEFAULT_STARTS` for a real experiment's calibration,
    unless ``--multistart`` asks for the local chain's further starts; 1 for a scatter fit (and then
    ``--dask`` is refused: it runs a global search's solves)."""
    from kneenlp.estimation.search import DEFAULT_STARTS

    starts = args.starts if args.starts is not None else (
        DEFAULT_STARTS if calibration and getattr(args, "multistart", 1) == 1 else 1)
    if (args.dask or args.scheduler) and starts == 1:
        raise InputError("runs the global search's solves on Dask: give --starts N (N > 1) too",
                         field="--scheduler" if args.scheduler else "--dask")
    return starts


def start_workers(args) -> dict:
    """``identify``'s calibration options of its starts: a calibration's further starts (``--multistart``)
    or its global search's (:func:`search_starts`, its finished solves kept in ``--out``/search) share
    :func:`worker_count` processes (a scatter fit's global search too)."""
    from kneenlp.estimation.identify import resolve_strategy

    calibration = resolve_strategy(args.strategy, args.measured, args.method) == "calibration"
    starts = search_starts(args, calibration)
    if starts > 1:
        return {"starts": starts, "workers": search_workers(args)} | (
            {"store": str(Path(args.out) / "search")} if args.out else {})
    if not calibration:
        return {}
    return {"starts": 1} | ({"workers": worker_count(args)} if args.multistart > 1 else {})
