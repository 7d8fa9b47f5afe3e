"""A command's inputs, read and checked before any work: input files and ``--out`` (one-line
errors naming the option), the knee with its user elements and parameter set, the names of
sets, effects and free parameters, and ``--with-effect`` values (display units -> SI)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.cli import options as opt


# ------------------------------------------------------------------ input files and --out (before the work)
@contextlib.contextmanager
def naming(field: str):
    """Name ``field`` (the option) in an input error that names no field."""
    try:
        yield
    except InputError as exc:
        raise exc.with_context(field=field) from None


def check_out(value: str, kind: str) -> None:
    """``--out`` must be creatable and writable: a directory (``kind="dir"``) or a file
    (``"file"``); checked by creating and removing a temporary directory in the nearest existing
    ancestor, which also catches read-only file systems."""
    import tempfile

    from kneenlp.base.atomic import TMP_PREFIX

    if not value.strip():
        raise InputError("empty path", field="--out")
    path = Path(value)
    if kind == "dir" and path.exists() and not path.is_dir():
        raise InputError("exists and is not a directory", source=value, field="--out")
    if kind == "file" and path.is_dir():
        raise InputError("is a directory; give the file to write, e.g. DIR/protocol.toml", source=value,
                         field="--out")
    start = path if kind == "dir" else path.parent
    base = next((p for p in (start, *start.parents) if p.exists()), Path("."))
    if not base.is_dir():
        raise InputError(f"{base} is not a directory", source=value, field="--out")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=TMP_PREFIX, dir=base))
    except OSError as exc:
        raise InputError(f"cannot write in {base} ({exc.strerror or exc})", source=value, field="--out") from None


def check_inputs(args) -> None:
    """Every file and option of a command that sets ``validate``, checked before any work starts:
    ``--out`` (kind ``out_kind``), ``--knee``, ``--parameters``, ``--protocol``, ``--sets`` and
    the measured data (read once into ``args.measured``)."""
    if not getattr(args, "validate", False):
        return
    apply_problem(args)
    if getattr(args, "out_kind", None) and getattr(args, "out", None) is not None:
        check_out(args.out, args.out_kind)
    knee = getattr(args, "knee", None)
    if knee is not None:
        from kneenlp.model.knee_file import available_knees, resolve_knee

        with naming("--knee"):
            resolved = resolve_knee(knee)
        if not resolved.is_file():
            raise InputError(f"file not found, and not a shipped knee ({', '.join(available_knees())})",
                             source=knee, field="--knee")
    if getattr(args, "parameters", None):
        from kneenlp.model.parameters import ParameterSet

        with naming("--parameters"):
            ParameterSet.load(args.parameters)
    from kneenlp.experiment.protocol import Protocol

    if isinstance(getattr(args, "protocol", None), str):
        with naming("--protocol"):
            Protocol.load(args.protocol)
    for name in getattr(args, "sets", None) or []:
        with naming("--sets"):
            Protocol.load(name)
    if isinstance(getattr(args, "reference", None), str):
        with naming("--reference"):
            Protocol.load(args.reference)
    if getattr(args, "data", None) is not None:
        from kneenlp.experiment.measured import read_measured

        args.measured = read_measured(args.data, protocol=getattr(args, "protocol", None))


#: What a command takes from a problem file when its option is not given (option attribute: the
#: problem's field), and the defaults without either.
FROM_PROBLEM = {"noise": "noise", "strategy": "strategy", "priors": "priors", "prior_weight": "prior_weight",
                "hold_out": "hold_outs", "also_free": "also_free", "multistart": "multistart",
                "starts": "starts"}
DEFAULTS = {"strategy": "auto", "multistart": 1}  # --starts: starts.search_starts
DIAGNOSE_NOISE = "uniform:0.5"


def apply_problem(args) -> None:
    """``--problem DIR``: the problem file's knee, data and options fill those not given (its
    parameter table joins the knee in :func:`knee_from_args`); the data given twice, or neither,
    is refused."""
    from kneenlp.experiment.problem_file import ProblemFile

    if not hasattr(args, "problem"):
        return
    args.problem_file = None
    if args.problem is None:
        if args.data is None:
            raise InputError("give the measured data (DATA.csv) or --problem DIR", field="data")
    else:
        if args.data is not None or getattr(args, "knee", None) is not None:
            raise InputError("names the knee and the data: give DATA.csv and --knee, or --problem, not both",
                             field="--problem")
        with naming("--problem"):
            problem = ProblemFile.load(args.problem)
        args.problem_file, args.data, args.knee = problem, str(problem.data), problem.knee
        for option, key in FROM_PROBLEM.items():
            value = getattr(problem, key)
            if hasattr(args, option) and getattr(args, option) in (None, []) and value not in (None, ()):
                setattr(args, option, list(value) if isinstance(value, tuple) else value)
    for option, value in DEFAULTS.items():
        if hasattr(args, option) and getattr(args, option) is None:
            setattr(args, option, value)
    if args.command == "diagnose" and args.noise is None:
        args.noise = DIAGNOSE_NOISE


def check_names(knee, args) -> None:
    """``--free`` and ``--with-effect`` must name parameters and effects of the model (checked
    after the knee is read, before the work)."""
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.experiment.problem import check_free

    model = KneeModel.of(knee)
    for spec in getattr(args, "with_effect", None) or []:
        with naming("--with-effect"):
            model.effect(spec.partition(":")[0])
    if getattr(args, "free", None):
        try:
            check_free(model, args.free)
        except InputError as exc:
            raise InputError(exc.message, source=exc.source, field="--free") from None
    for name in getattr(args, "profile", None) or []:
        if name not in model.parameter_names:
            raise InputError(unknown_name("parameter", name, model.parameter_names).message, field="--profile")
    problem = getattr(args, "problem_file", None)
    if problem is not None:
        check_problem_names(model, getattr(args, "measured", None), problem)


def check_problem_names(model, data, problem) -> None:
    """A problem file's ``also_free`` must name the model's effects and its ``hold_outs`` the data's
    hold-outs, whichever command reads it (an error names the file's own field, not an option)."""
    from kneenlp.estimation.choice import also_free_names
    from kneenlp.validation.crossval import chosen_hold_outs

    checks = {"also_free": lambda names: also_free_names(model, names)}
    if data is not None:
        checks["hold_outs"] = lambda names: chosen_hold_outs(data, names)
    for key, check in checks.items():
        names = list(getattr(problem, key))
        if names:
            try:
                check(names)
            except InputError as exc:
                raise InputError(exc.message, source=str(problem.path), field=key) from None


def set_names(text: str) -> list[str]:
    """``--sets``: ``1,2`` -> ``set1, set2``; names and protocol files as they are."""
    return [f"set{s}" if s.isdigit() else s for s in opt.names(text)]


def knee_from_args(args):
    """The knee model of the --knee, --parameters and --element options."""
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.model.knee import Knee
    from kneenlp.model.plugins import load_elements

    knee = Knee.load(args.knee) if args.knee else Knee.default()
    if getattr(args, "parameters", None):
        knee = knee.with_parameters(args.parameters)
    if getattr(args, "problem_file", None) is not None:
        knee = args.problem_file.knee_with_parameters(knee)
    elements = getattr(args, "element", None)
    return KneeModel(knee, load_elements(elements)) if elements else knee


def knee_reference(value: str | None) -> str | None:
    """A --knee value as study workers get it: a shipped knee's name, or an absolute path."""
    from kneenlp.model.knee_file import available_knees, knee_file, resolve_knee

    if value is None:
        return value
    path = resolve_knee(value)
    return value if value in available_knees() and path == knee_file(value) else str(path.resolve())


def effect_values(knee, specs: list[str]) -> dict[str, float]:
    """``NAME[:param=value,...]`` (display units, e.g. ``posterior_capsule:k=8000``,
    ``registration:anterior_translation=1.5``) -> parameter values in SI."""
    import numpy as np

    from kneenlp.experiment.kneemodel import KneeModel

    model = KneeModel.of(knee)
    values: dict[str, float] = {}
    for spec in specs or []:
        name, _, rest = spec.partition(":")
        with naming("--with-effect"):
            effect = model.effect(name)
        for item in filter(None, rest.split(",")):
            key, eq, val = item.partition("=")
            key = key.strip()
            full = effect.parameter_named(key)
            if full is None:
                raise InputError(f"unknown parameter {key!r} of effect {name}; known: "
                                 + ", ".join(effect.parameters), field="--with-effect")
            if not eq:
                raise InputError(f"expected PARAM=VALUE in {spec!r}", field="--with-effect")
            par = model.parameter(full)
            try:
                values[full] = par.from_user(val)
            except ValueError:
                raise InputError(f"value of {full} is not a number: {val!r}", field="--with-effect") from None
            if not np.isfinite(values[full]):
                raise InputError(f"value of {full} must be finite: {val!r}", field="--with-effect")
            if values[full] == model.theta()[model.index(full)]:
                raise InputError(f"{full} = {val} {par.unit} is the knee's own value: the data would not change",
                                 field="--with-effect")
        if not rest and effect.parameters:
            first = effect.parameters[0]
            raise InputError(f"give the strength, e.g. {name}:{first}=VALUE ({model.parameter(first).unit})",
                             field="--with-effect")
    return values


#: Fits (sets x samples) a study runs without --yes; the paper's study has 4 x 1000.
MAX_STUDY_FITS = 10_000
#: Seconds a study fit takes on one core, as estimated before a study (measured: 1.7-5.4 s on the
#: synthetic knee; a mesh knee's fit solves its trials with mesh contact: about a minute).
SECONDS_PER_FIT = {"spheres": 3.0, "mesh": 60.0}
#: Disk a sample file takes (a 0.6 kB JSON file in a 4 kB block).
BYTES_PER_SAMPLE = 4096


def study_size(args) -> str:
    """The study's size in fits, time and disk (estimated from :data:`SECONDS_PER_FIT` and
    :data:`BYTES_PER_SAMPLE`); an input error naming ``--samples`` beyond :data:`MAX_STUDY_FITS`
    fits without ``--yes``, before any work (``--samples 1000000`` is refused at once)."""
    from kneenlp.base.tomlfile import read_toml
    from kneenlp.model.knee_file import resolve_knee

    fits = len(args.sets) * args.samples
    workers = args.workers or (1 if args.scheduler or args.dask else os.cpu_count() or 1)
    contact = read_toml(resolve_knee(args.knee or "default")).get("contact", {})
    mesh = isinstance(contact, dict) and ("femur" in contact or any(isinstance(t, dict) and "femur" in t
                                                                    for t in contact.values()))
    seconds = fits * SECONDS_PER_FIT["mesh" if mesh else "spheres"] / workers
    span = f"{seconds / 3600:,.3g} h" if seconds < 36000 else f"{seconds / 3600:,.0f} h"
    if seconds < 3600:
        span = f"{seconds / 60:.2g} min"
    text = (f"{len(args.sets)} sets x {args.samples:,} samples = {fits:,} fits: about {span} on {workers} "
            f"worker{'s' if workers > 1 else ''} (~{SECONDS_PER_FIT['mesh' if mesh else 'spheres']:g} s a fit on "
            f"{'a mesh' if mesh else 'this'} knee) and {fits:,} sample files ({fits * BYTES_PER_SAMPLE / 1e9:.3g} GB)")
    if fits > MAX_STUDY_FITS and not args.yes:
        raise InputError(f"{text}; more than {MAX_STUDY_FITS:,} fits needs --yes (a Monte Carlo's standard error falls "
                         "as 1/sqrt(samples): 100-1000 samples a set are usually enough)", field="--samples")
    return text
