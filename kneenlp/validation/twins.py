"""The experiment's twin: the data the calibrated knee itself would have produced.

:func:`twin` predicts every trial at its measured load and flexion with a calibration's values and
adds normal noise at its misfit; the same hold-outs on the twin give the errors of a model that is
exactly right (:mod:`kneenlp.validation.crossval`).  :class:`TwinStore` keeps finished draws so a
long run of many twins resumes."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.base.conventions import coordinate_columns
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.noise import NoiseModel
from kneenlp.prediction.predict import predict


def twin(model: KneeModel, data: MeasuredData, parameters: dict[str, float], sd: np.ndarray,
         rng: np.random.Generator) -> MeasuredData:
    """The experiment as the knee with ``parameters`` would have produced it: every trial of
    ``data`` at its measured load and flexion predicted (registration included), plus normal noise
    of standard deviation ``sd`` per coordinate (5, mm and deg) drawn from ``rng`` (a (T, 5) draw
    of standard normals, scaled).  A trial without equilibrium is left out."""
    truth = predict(model, data, parameters)
    ok = truth.converged
    q = truth.predicted_user[ok] + NoiseModel("gaussian", 1.0).sample(rng, (int(ok.sum()), 5)) * sd
    trials = [t for t, k in zip(data.trials, ok, strict=True) if k]
    return MeasuredData.from_user(trials, q, data.protocol, f"twin of {data.source}", side=data.side,
                                  experiment=data.experiment)


@dataclass(frozen=True)
class TwinStore:
    """Finished twin draws in a directory: ``draw_<n>.csv`` (hold-out, row within it and errors,
    mm and deg), and ``run.json`` naming the run (knee, its structure and parameters, data, hold-outs,
    options) so that a store of another run is refused, never mixed in.  Nothing is written before
    the first draw finishes (an interrupted run with none leaves no file)."""

    path: Path
    #: what ``run.json`` holds
    identity: dict

    @classmethod
    def open(cls, path: Path, model: KneeModel, data: MeasuredData, names: list[str], options: dict) -> TwinStore:
        """The store at ``path`` for this run (written with its first draw); another run's is an
        :class:`~kneenlp.base.errors.InputError`."""
        from kneenlp.base.errors import InputError

        path = Path(path)
        from kneenlp.estimation.search import model_structure

        identity = {"knee": model.knee.name, "structure": model_structure(model),
                    "parameters": np.round(model.theta(), 12).tolist(),
                    "trials": [t.id for t in data.trials], "measured": np.round(data.q_user, 9).tolist(),
                    "hold_outs": names, "options": {k: v for k, v in sorted(options.items()) if v is not None}}
        identity = json.loads(json.dumps(identity))
        stamp = path / "run.json"
        if stamp.is_file() and json.loads(stamp.read_text()) != identity:
            raise InputError("holds the twins of another run (knee, data, hold-outs or options differ); remove "
                             "it or write elsewhere", source=str(path), field="--out")
        return cls(path, identity)

    def load(self, draw: int) -> dict[str, np.ndarray] | None:
        """The held-out errors of finished draw ``draw`` by hold-out name (None: not finished)."""
        path = self.path / f"draw_{draw}.csv"
        if not path.is_file():
            return None
        table, columns = pd.read_csv(path), coordinate_columns()
        return {n: g.sort_values("row")[columns].to_numpy(float) for n, g in table.groupby("held_out", sort=False)}

    def save(self, draw: int, errors: dict[str, np.ndarray]) -> None:
        """Write draw ``draw``'s held-out errors, atomically (``run.json`` first, with the first draw)."""
        from kneenlp.base.atomic import write_csv_atomic, write_text_atomic

        if not (self.path / "run.json").is_file():
            self.path.mkdir(parents=True, exist_ok=True)
            write_text_atomic(self.path / "run.json", json.dumps(self.identity))

        columns = coordinate_columns()
        rows = [{"held_out": n, "row": i, **dict(zip(columns, e, strict=True))}
                for n, table in errors.items() for i, e in enumerate(table)]
        write_csv_atomic(pd.DataFrame(rows, columns=["held_out", "row", *columns]), self.path / f"draw_{draw}.csv",
                         index=False, float_format="%.17g")
