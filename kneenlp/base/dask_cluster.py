"""Where work runs on Dask: a scheduler's address or a local cluster (``--scheduler`` / ``--dask``).

Imported where a command runs on Dask only (an optional dependency, ``pip install 'kneenlp[dask]'``).
"""

from __future__ import annotations

from dataclasses import dataclass

from kneenlp.base.errors import InputError


@dataclass(frozen=True)
class DaskWorkers:
    """Dask as the workers of independent solves: ``scheduler`` (``tcp://HOST:PORT``) or, without
    one, a local cluster of ``processes`` single-threaded worker processes."""

    scheduler: str | None = None
    processes: int = 2

    def connect(self):
        """(client, cluster or None): connected to the scheduler or to a new local cluster; a missing
        package or an unreachable scheduler is one :class:`~kneenlp.base.errors.InputError`."""
        field = "--scheduler" if self.scheduler else "--dask"
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:
            raise InputError("Dask is not installed: pip install 'kneenlp[dask]'", field=field) from None
        if self.scheduler:
            try:
                return Client(self.scheduler, timeout="20s"), None
            except (OSError, TimeoutError, ValueError, TypeError) as exc:
                raise InputError(f"cannot connect to the Dask scheduler {self.scheduler!r} ({type(exc).__name__}: "
                                 f"{exc})", field=field) from None
        cluster = LocalCluster(n_workers=self.processes, threads_per_worker=1, processes=True, dashboard_address=None)
        return Client(cluster), cluster
