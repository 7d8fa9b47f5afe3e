"""Noise studies: the paper's Monte Carlo (Table 3, Fig. 3) at any scale, locally or on Dask.

For each protocol ("set") and sample index, the truth is simulated once, seeded noise is added
(:func:`sample_seed`: derived from the study seed, the protocol's name and the index only, so
results are bit-identical whatever the executor and worker count) and the parameters are identified.
Every finished sample is written atomically to ``DIR/samples/<set>_<index>.json`` (temporary
file + ``os.replace``): a study killed mid-run and started again with the same arguments skips
what is done, and the estimates table has exactly one row per (set, sample).  ``DIR/study.json``
records the arguments; resuming with different ones is refused.

A sample file that is not a complete result of its own (set, sample) (truncated or edited by
hand, or left by a copy interrupted half-way) is reported on the ``kneenlp`` logger, removed and
computed again; stale temporary files of a killed run are removed.  A study interrupted by
Ctrl-C or SIGTERM stops its worker processes and keeps every finished sample.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import re
import sys
import time
import zlib
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from tqdm import tqdm

from kneenlp.base import interrupts
from kneenlp.base.atomic import write_text_atomic
from kneenlp.base.dask_cluster import DaskWorkers
from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.modes import Method

if TYPE_CHECKING:
    from kneenlp.studies.truth import StudyTruths

STARTS = ("scatter", "truth")
#: Keys every sample file holds (written by :meth:`Study.record`).
SAMPLE_KEYS = ("set", "sample", "seed", "status", "success")

log = logging.getLogger("kneenlp")


@dataclass(frozen=True)
class StudySpec:
    """What a study computes (all that determines its numbers)."""

    sets: tuple[str, ...] = ("set1", "set2", "set3", "set4")
    samples: int = 20
    noise: str = "uniform:0.5"
    seed: int = 0
    method: Method = "simultaneous"
    knee: str | None = None  # knee TOML path; None = embedded default knee
    #: user force elements by import path ("module:factory", see kneenlp.model.plugins)
    elements: tuple[str, ...] = ()
    #: candidate effects freed in every fit (e.g. ("posterior_capsule",))
    with_effects: tuple[str, ...] = ()
    free: tuple[str, ...] | None = None
    nested_max_evals: int = 6000
    #: where each fit starts: "scatter" (the paper: +-500 N and +-0.02 around the reference values,
    #: drawn from the sample's seed) or "truth" (the true values: the spread then shows the noise's
    #: effect on the least-squares estimate alone, and Set 4 fits take ~7 instead of 10-60 iterations)
    start: str = "scatter"

    def tasks(self) -> list[tuple[str, int]]:
        return [(s, i) for s in self.sets for i in range(self.samples)]

    def identity(self) -> dict:
        """The arguments that must match for a resume (the sample count may grow)."""
        d = asdict(self)
        d.pop("samples")
        return d


def sample_seed(study_seed: int, set_name: str, index: int) -> int:
    """Seed of one sample's noise, independent of execution order and workers."""
    ss = np.random.SeedSequence([study_seed, zlib.crc32(set_name.encode()), index])
    return int(ss.generate_state(1, dtype=np.uint32)[0])


def run_sample(spec: StudySpec, set_name: str, index: int, threads: int = 2, truths: StudyTruths | None = None) -> dict:
    """Simulate, add noise and identify one sample; returns one result row (never raises).

    ``threads`` of the NLP's trial map: 1 in worker processes (one process per core already);
    ``truths``: the study's model and true simulations (built here when not given)."""
    from kneenlp.base.conventions import coordinate_columns
    from kneenlp.estimation.identify import identify
    from kneenlp.experiment.measured import MeasuredData
    from kneenlp.model.params import default_free
    row: dict = {"set": set_name, "sample": index, "seed": -1}
    t0 = time.perf_counter()
    try:
        if truths is None:
            from kneenlp.studies.truth import StudyTruths

            truths = StudyTruths.of(spec)
        model, truth = truths.model, truths.truth(set_name)
        # the protocol's name, not the path it was given by: moving the file keeps the draws
        seed = row["seed"] = sample_seed(spec.seed, truth.protocol.name, index)
        df = truth.measured(spec.noise, seed)
        data = MeasuredData.from_user([s.trial for s in truth.solutions], df[coordinate_columns()].to_numpy(),
                                      set_name, f"{set_name} sample {index}")
        free = list(spec.free) if spec.free else None
        start = None
        if spec.start == "truth":
            start = {n: truth.parameters[n] for n in (free or default_free(model))}
        fit = identify(model, data, method=spec.method, free=free, seed=seed, start=start, noise=spec.noise,
                       nested_options={"max_evals": spec.nested_max_evals}, with_effects=list(spec.with_effects),
                       threads=threads)
        row.update(status=fit.status, success=fit.success, objective=fit.objective, iterations=fit.iterations,
                   evaluations=fit.evaluations, max_residual=fit.max_residual, seconds=fit.seconds,
                   message=fit.message)
        row.update({f"{n}": v for n, v in fit.params.items()})
    except Exception as exc:  # a failed sample is recorded, never dropped
        row.update(status=f"error: {type(exc).__name__}: {exc}", success=False, objective=np.nan,
                   iterations=-1, evaluations=-1, max_residual=np.nan, seconds=np.nan, message=str(exc))
    row["wall_seconds"] = time.perf_counter() - t0
    return row


def _serve(truths: StudyTruths, tasks, results) -> None:
    """A local worker process: Ctrl-C and SIGTERM left to the parent; solves the samples of
    ``tasks`` (until ``None``) with the study's ``truths`` (forked: the parent's as built so far,
    kept for every sample) and puts their rows on ``results``; it stops when its parent is gone
    (killed).  The NLP's trial map runs serially: one process per core (two threads per process
    would oversubscribe the cores)."""
    interrupts.as_worker()
    parent = os.getppid()
    while True:
        try:
            task = tasks.get(timeout=1.0)
        except queue.Empty:
            if os.getppid() != parent:
                return
            continue
        if task is None:
            return
        spec, set_name, index = task
        results.put(run_sample(spec, set_name, index, threads=1, truths=truths))


def _dask_sample(spec: StudySpec, set_name: str, index: int) -> dict:
    """:func:`run_sample` on a Dask worker (one thread each), with the truths of its worker plugin."""
    from kneenlp.studies.dask_truths import worker_truths

    return run_sample(spec, set_name, index, threads=1, truths=worker_truths())


@dataclass
class Study:
    """A study directory: spec, finished samples, and the analysis outputs."""

    spec: StudySpec
    out: Path
    rows: list[dict] = field(default_factory=list)

    @property
    def sample_dir(self) -> Path:
        return self.out / "samples"

    def sample_path(self, set_name: str, index: int) -> Path:
        """File of one sample; a protocol given as a path gets a safe, unique file key."""
        key = set_name
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", set_name):
            key = f"{re.sub(r'[^A-Za-z0-9_.-]', '_', Path(set_name).stem)}-{zlib.crc32(set_name.encode()):08x}"
        return self.sample_dir / f"{key}_{index:06d}.json"

    def prepare(self) -> None:
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            self.sample_dir.mkdir(exist_ok=True)
        except OSError as exc:
            raise InputError(f"cannot create the study directory ({exc.strerror or exc})", source=str(self.out),
                             field="--out") from None
        for stale in [*self.out.glob(".*.tmp"), *self.sample_dir.glob(".*.tmp")]:  # of a killed run
            stale.unlink(missing_ok=True)
        spec_file = self.out / "study.json"
        if spec_file.exists():
            try:
                recorded = json.loads(spec_file.read_text())
                if not isinstance(recorded, dict):
                    raise ValueError("not a JSON object")
            except (ValueError, OSError) as exc:
                raise InputError(f"not a study record ({exc}); use another --out or remove the file",
                                 source=str(spec_file)) from None
            old = json.loads(json.dumps(asdict(StudySpec()))) | recorded  # newer fields
            mine = json.loads(json.dumps(self.spec.identity()))
            if {k: old.get(k) for k in mine} != mine:
                diff = ", ".join(f"{k}: {old.get(k)!r} -> {v!r}" for k, v in mine.items() if old.get(k) != v)
                raise InputError(f"holds a study with other arguments ({diff}); use another --out",
                                 source=str(spec_file))
        write_text_atomic(spec_file, json.dumps(asdict(self.spec), indent=2))

    def read_sample(self, set_name: str, index: int) -> dict | None:
        """The finished row of one sample, or None if its file is absent or not a complete row of
        this (set, sample) (e.g. truncated)."""
        path = self.sample_path(set_name, index)
        try:
            row = json.loads(path.read_text())
        except (ValueError, OSError):  # absent, unreadable or not JSON
            return None
        if not isinstance(row, dict) or any(k not in row for k in SAMPLE_KEYS) or \
                (row["set"], row["sample"]) != (set_name, index):
            return None
        return row

    def pending(self) -> list[tuple[str, int]]:
        """Samples still to compute; a sample file that is there but broken is reported, removed
        and pending again."""
        todo = []
        for s, i in self.spec.tasks():
            path = self.sample_path(s, i)
            if not path.exists():
                todo.append((s, i))
            elif self.read_sample(s, i) is None:
                log.warning(f"{path}: truncated or corrupt sample file; computing sample {i} of {s} again")
                path.unlink(missing_ok=True)
                todo.append((s, i))
        return todo

    def record(self, row: dict) -> None:
        clean = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in row.items()}
        write_text_atomic(self.sample_path(row["set"], row["sample"]), json.dumps(clean))

    def load_rows(self) -> pd.DataFrame:
        rows = [r for s, i in self.spec.tasks() if (r := self.read_sample(s, i)) is not None]
        df = pd.DataFrame(rows)
        if not df.empty:
            df = df.sort_values(["set", "sample"], key=lambda c: c.map(self._order) if c.name == "set" else c)
        return df.reset_index(drop=True)

    def _order(self, s: str) -> int:
        return list(self.spec.sets).index(s) if s in self.spec.sets else 99


@dataclass(frozen=True)
class StudyRunOptions:
    """:func:`run_study`'s keyword options (its docstring), checked in one place."""

    workers: int | None = None
    scheduler: str | None = None
    dask_local: bool = False
    progress: bool | None = None
    analyse: bool = True
    truths: StudyTruths | None = None


def run_study(spec: StudySpec, out: str | Path, **options) -> Study:
    """Run (or resume) a study into ``out``; see module docstring.

    ``workers`` local processes (default: all cores; 1 = in this process), or Dask: ``scheduler``
    (address ``tcp://HOST:PORT``) or ``dask_local`` (a LocalCluster with ``workers`` processes).
    ``progress``: a progress bar (default: on a terminal); ``analyse`` (default True): the study's
    analysis when done.  ``truths``: the model and true simulations of ``spec``'s knee
    (:meth:`~kneenlp.studies.truth.StudyTruths.of`), e.g. the caller's, already built; made here when
    not given.
    """
    from kneenlp.base.keywords import keyword_options
    from kneenlp.experiment.protocol import Protocol

    opts = keyword_options(StudyRunOptions, "run_study", options)
    workers, scheduler, truths = opts.workers, opts.scheduler, opts.truths

    for s in spec.sets:
        Protocol.load(s)  # validates names early
    if spec.start not in STARTS:
        raise unknown_name("start", spec.start, STARTS)
    workers = workers or os.cpu_count() or 1
    if truths is None:
        from kneenlp.studies.truth import StudyTruths

        truths = StudyTruths.of(spec)
    # Dask first: a missing package or an unreachable scheduler writes nothing into ``out``
    dask = DaskWorkers(scheduler, workers).connect() if scheduler or opts.dask_local else None
    study = Study(spec, Path(out))
    study.prepare()
    todo = study.pending()
    bar = _progress(len(spec.tasks()), len(spec.tasks()) - len(todo), opts.progress)
    if todo:
        for row in _execute(spec, todo, workers, dask, truths):
            interrupts.check()  # a sample whose solve was interrupted is not recorded
            study.record(row)
            bar.update(1)
    elif dask is not None:  # nothing left to run (a finished study resumed)
        for part in dask:
            if part is not None:
                part.close()
    bar.close()
    if opts.analyse:
        from kneenlp.studies.report import analyse_study

        analyse_study(study, truths)
    return study


def _execute(spec: StudySpec, todo: list[tuple[str, int]], workers: int, dask,
             truths: StudyTruths) -> Iterable[dict]:
    """The rows of the samples ``todo`` as they finish: on Dask, in this process (``workers`` 1) or
    in a local pool of ``workers`` processes, each keeping its own ``truths``."""
    if dask is not None:
        yield from _execute_dask(spec, todo, dask, truths)
        return
    if workers == 1:
        for s, i in todo:
            yield run_sample(spec, s, i, truths=truths)
        return
    # fork: works from scripts and notebooks without a __main__ guard, and the workers start with the
    # truths built so far; the parent holds no CasADi threads at this point (thread maps join their
    # threads after every evaluation).  Plain processes, not a pool: each keeps its truths in its own
    # loop (no per-process global), a worker that dies is noticed, and stopping them is terminate()
    ctx = get_context("fork") if sys.platform.startswith("linux") else get_context("spawn")
    tasks, results = ctx.Queue(), ctx.Queue()
    procs = [ctx.Process(target=_serve, args=(truths, tasks, results), daemon=True)
             for _ in range(min(workers, len(todo)))]
    try:
        for p in procs:
            p.start()
        for s, i in todo:
            tasks.put((spec, s, i))
        for _ in procs:
            tasks.put(None)
        for _ in todo:
            yield _next_row(results, procs)
    finally:  # finished, Ctrl-C, SIGTERM, or the consumer gone: stop the workers now, not after the queue
        for p in procs:
            if p.is_alive():
                p.terminate()
            p.join()


def _next_row(results, procs: list) -> dict:
    """The next finished row; a worker that died (killed, or a crash in compiled code) is an error,
    not a wait without end."""
    while True:
        try:
            return results.get(timeout=1.0)
        except queue.Empty:
            dead = [p.exitcode for p in procs if p.exitcode not in (None, 0)]
            if dead or all(p.exitcode is not None for p in procs):
                code = dead[0] if dead else 0
                raise RuntimeError(f"a study worker process died (exit code {code}); finished samples "
                                   "are kept, run the study again to resume") from None


def _execute_dask(spec: StudySpec, todo: list[tuple[str, int]], dask, truths: StudyTruths) -> Iterable[dict]:
    from dask.distributed import as_completed as dask_completed

    from kneenlp.studies.dask_truths import TruthsPlugin

    client, cluster = dask
    try:
        client.register_plugin(TruthsPlugin(truths))
        futures = [client.submit(_dask_sample, spec, s, i, pure=False) for s, i in todo]
        for fut in dask_completed(futures):
            yield fut.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _progress(total: int, done: int, progress: bool | None) -> tqdm:
    """The study's progress bar on stderr (``progress`` None: when stderr is a terminal)."""
    show = sys.stderr.isatty() if progress is None else progress
    return tqdm(total=total, initial=done, unit="fit", desc="study", disable=not show)
