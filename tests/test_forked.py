"""forked_map: jobs shared out over forked processes give the sequential results, in order."""

import os

import pytest

from kneenlp.base.forked import forked_map


def test_results_come_back_in_order_from_other_processes():
    items = list(range(7))
    out = forked_map(lambda i: (i * i, os.getpid()), items, workers=3)
    assert [v for v, _ in out] == [i * i for i in items]
    assert os.getpid() not in {pid for _, pid in out}  # computed in the workers
    assert len({pid for _, pid in out}) == 3


def test_pack_strips_before_sending_and_unpack_restores():
    unpicklable = lambda: None  # noqa: E731 - a lambda cannot be pickled, as a CasADi model cannot
    out = forked_map(lambda i: {"i": i, "model": unpicklable}, [1, 2], workers=2,
                     pack=lambda r: r | {"model": None}, unpack=lambda r: r | {"model": unpicklable})
    assert out == [{"i": 1, "model": unpicklable}, {"i": 2, "model": unpicklable}]


def test_packing_waits_for_every_job_of_the_worker():
    """Jobs may share what ``pack`` strips (a calibration's starts share its problem and model): a
    worker packs its results only after its last job."""
    shared = {"model": "compiled"}

    def work(i):
        assert shared["model"] == "compiled", "a job ran after the packing stripped the shared model"
        return {"i": i, "problem": shared}

    def pack(r):
        r["problem"]["model"] = None
        return r

    out = forked_map(work, [1, 2, 3, 4], workers=2, pack=pack)
    assert [r["i"] for r in out] == [1, 2, 3, 4]


def test_a_workers_error_is_raised_here():
    def work(i):
        if i == 3:
            raise ValueError("no equilibrium for trial 3")
        return i

    with pytest.raises(ValueError, match="trial 3"):
        forked_map(work, [1, 2, 3, 4], workers=2)
    assert forked_map(work, [1, 2], workers=1) == [1, 2]
