"""A calibration problem as a file: ``problems/<name>/problem.toml`` (``kneenlp identify --problem DIR``).

In the spirit of PEtab's problem files: one file names the knee, the measured data, the
parameter table (value, unit, bounds, free or fixed, prior), the declared noise and the hold-outs,
so that identify, cross-validate, diagnose and predict run the same problem::

    name = "s192803"
    description = "..."
    knee = "s192803"              # a shipped knee's name, or a knee file relative to this one
    data = "laxity.csv"           # measured data, relative to this file
    noise = "uniform:0.2"         # optional: the declared noise (mm, deg)
    strategy = "calibration"      # optional: auto | calibration | scatter (kneenlp.identify)
    priors = "default"            # optional: default | none
    prior_weight = 1.0            # optional: mm^2, deg^2
    hold_outs = ["anterior"]      # optional: cross-validate's hold-outs (default: all)
    also_free = ["tibial_origin"] # optional: effects a calibration fits beside its table (--also-free)
    multistart = 4                # optional: a calibration's starts, the lowest kept (--multistart)
    starts = 32                   # optional: a calibration's global search, its starts (--starts)

    [parameters]                  # the parameter table, as a parameter file's [values]
    "PFL.k_scale" = {value = 1.0, unit = "1", free = true, bounds = [0.1, 10],
                     prior = {distribution = "lognormal", median = 1.0, sd_log = 0.3}}

Unknown keys, missing files and bad entries are one-line errors naming the file and the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from kneenlp.base.errors import InputError
from kneenlp.base.modes import PriorChoice, Strategy, checked
from kneenlp.base.tomlfile import read_toml
from kneenlp.experiment.noise import NoiseModel
from kneenlp.model.knee import Knee
from kneenlp.model.parameters import Entries, read_entries

#: The fit strategies a problem may name (:func:`kneenlp.estimation.identify.identify`'s).
#: The file a problem folder holds.
FILE = "problem.toml"
#: The keys of a problem file: required, then optional.
REQUIRED = ("name", "knee", "data")
OPTIONAL = ("description", "noise", "strategy", "priors", "prior_weight", "hold_outs", "also_free", "multistart",
            "starts", "parameters")
#: The most starts a problem may ask for (as the command line's --multistart, docs/inputs.md).
MAX_STARTS = 1000


@dataclass(frozen=True)
class ProblemFile:
    """A problem file, read and checked (paths resolved against its folder)."""

    path: Path
    name: str
    knee: str  # a shipped knee's name or the path of a knee file
    data: Path
    description: str = ""
    noise: str | None = None
    strategy: str | None = None
    priors: str | None = None
    prior_weight: float | None = None
    hold_outs: tuple[str, ...] = ()
    entries: Entries | None = None
    also_free: tuple[str, ...] = ()
    multistart: int | None = None
    starts: int | None = None

    @classmethod
    def load(cls, path: str | Path) -> ProblemFile:
        """Read ``path`` (a problem folder, or its ``problem.toml``)."""
        from kneenlp.model.knee_file import available_knees

        path = Path(path)
        if path.is_dir():
            path = path / FILE
        if not path.is_file():
            raise InputError(f"no {FILE} here", source=str(path))
        src = str(path)
        doc = read_toml(path)
        for key in doc:
            if key not in (*REQUIRED, *OPTIONAL):
                raise InputError(f"unknown key {key!r}; known: {', '.join((*REQUIRED, *OPTIONAL))}", source=src,
                                 field=key)
        for key in REQUIRED:
            if key not in doc:
                raise InputError("missing", source=src, field=key)
        text = {k: _string(doc, k, src) for k in ("name", "knee", "data", "description", "noise", "strategy", "priors")
                if k in doc}
        knee = text["knee"] if text["knee"] in available_knees() else str(path.parent / text["knee"])
        if knee != text["knee"] and not Path(knee).is_file():
            raise InputError(f"neither a shipped knee ({', '.join(available_knees())}) nor a file next to "
                             f"{FILE}", source=src, field="knee")
        data = path.parent / text["data"]
        if not data.is_file():
            raise InputError(f"file not found: {data}", source=src, field="data")
        if "noise" in text:
            try:
                level = NoiseModel.parse(text["noise"]).std
            except InputError as exc:
                raise InputError(exc.message, source=src, field="noise") from None
            if not level > 0:
                raise InputError(f"needs a level above zero, got {text['noise']!r}; e.g. uniform:0.2", source=src,
                                 field="noise")
        checked("strategy", text.get("strategy", "auto"), Strategy, source=src, field="strategy")
        checked("priors", text.get("priors", "default"), PriorChoice, source=src, field="priors")
        weight = doc.get("prior_weight")
        if weight is not None and (isinstance(weight, bool) or not isinstance(weight, int | float) or not weight > 0):
            raise InputError(f"expected a variance > 0 (mm^2, deg^2), got {weight!r}", source=src,
                             field="prior_weight")
        holds, extra = (doc.get(k, []) for k in ("hold_outs", "also_free"))
        for key, names in (("hold_outs", holds), ("also_free", extra)):
            if not isinstance(names, list) or not all(isinstance(h, str) and h for h in names):
                raise InputError(f"expected a list of names, got {names!r}", source=src, field=key)
        starts = {key: _starts(doc, key, src) for key in ("multistart", "starts")}
        entries = read_entries(doc["parameters"], src, "parameters") if "parameters" in doc else None
        return cls(path, text["name"], knee, data, text.get("description", ""), text.get("noise"),
                   text.get("strategy"), text.get("priors"), None if weight is None else float(weight), tuple(holds),
                   entries, tuple(extra), starts["multistart"], starts["starts"])

    def calibrate_options(self) -> dict:
        """The options of :func:`~kneenlp.estimation.calibrate.calibrate` the problem names (its
        effects, starts, priors and their weight; those it leaves out are not given)."""
        options = {"also_free": list(self.also_free) or None, "multistart": self.multistart, "starts": self.starts,
                   "priors": self.priors,
                   "prior_weight": self.prior_weight}
        return {k: v for k, v in options.items() if v is not None}

    def knee_with_parameters(self, knee: Knee | None = None) -> Knee:
        """The problem's knee (or ``knee``) with the parameter table over its own parameter set."""
        knee = knee or Knee.load(self.knee)
        if self.entries is None:
            return knee
        return knee.with_parameters(knee.parameters.with_entries(self.entries, source=str(self.path)))


def _starts(doc: dict, key: str, src: str) -> int | None:
    """A number of starts (``multistart``, ``starts``), None if not given."""
    starts = doc.get(key)
    if starts is not None and (isinstance(starts, bool) or not isinstance(starts, int)
                               or not 1 <= starts <= MAX_STARTS):
        raise InputError(f"expected a whole number of starts from 1 to {MAX_STARTS}, got {starts!r}", source=src,
                         field=key)
    return starts


def _string(doc: dict, key: str, src: str) -> str:
    value = doc[key]
    if not isinstance(value, str) or (key != "description" and not value.strip()):
        raise InputError(f"expected a non-empty string, got {value!r}", source=src, field=key)
    return value
