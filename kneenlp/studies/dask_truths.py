"""The study's truths on Dask workers: a worker plugin (Dask's own mechanism for per-worker
state) holding one :class:`~kneenlp.studies.truth.StudyTruths` per worker, built by the first
sample that worker solves.  Imported only when a study runs on Dask (an optional dependency)."""

from __future__ import annotations

from distributed import WorkerPlugin, get_worker

from kneenlp.studies.truth import StudyTruths

PLUGIN_NAME = "kneenlp-study-truths"


class TruthsPlugin(WorkerPlugin):
    """Holds ``truths`` on each worker (pickled to it as their arguments alone)."""

    name = PLUGIN_NAME

    def __init__(self, truths: StudyTruths):
        self.truths = truths


def worker_truths() -> StudyTruths | None:
    """The truths of the plugin on the Dask worker running this task; None without the plugin."""
    plugin = get_worker().plugins.get(PLUGIN_NAME)
    return plugin.truths if isinstance(plugin, TruthsPlugin) else None
