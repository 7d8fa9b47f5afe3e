"""Command-line interface: ``kneenlp <command> ...``.

Bad input gives a one-line ``kneenlp: error: ...`` on stderr and exit status 2 (never a
traceback); with ``--json`` the error is also printed on stdout as ``{"error": ..., "file": ...,
"field": ...}``.  A run in which some trial or fit did not converge still writes its outputs and
exits with status 1.  Every option and input file is checked before any work starts (option
values by their argparse types, files by :func:`_check_inputs`); outputs are written through a
staging directory (:func:`kneenlp.io.atomic.staged_directory`), so a failed or interrupted
command leaves no half-written file.  Ctrl-C (SIGINT) and SIGTERM end a command with one line and
status 130 / 143, keeping finished work (a study's finished samples).  An unexpected exception
(a bug) is one line and status 3 (``KNEENLP_DEBUG=1`` shows the traceback).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import sys
from pathlib import Path

from kneenlp import options as opt
from kneenlp.errors import ConvergenceError, InputError
from kneenlp.io.atomic import staged_directory, write_error

#: Exit statuses: 0 done, 1 some trial or fit did not converge, 2 bad input, 3 internal error (a
#: bug), 130 interrupted (Ctrl-C), 143 terminated (SIGTERM).
EXIT_INPUT, EXIT_BUG, EXIT_INTERRUPTED, EXIT_TERMINATED = 2, 3, 130, 143



# ------------------------------------------------------------------ input files and --out (before the work)
@contextlib.contextmanager
def _naming(field: str):
    """Name ``field`` (the option) in an input error that names no field."""
    try:
        yield
    except InputError as exc:
        raise exc.with_context(field=field) from None


def _check_out(value: str, kind: str) -> None:
    """``--out`` must be creatable and writable: a directory (``kind="dir"``) or a file
    (``"file"``); checked by creating and removing a temporary directory in the nearest existing
    ancestor, which also catches read-only file systems."""
    import tempfile

    from kneenlp.io.atomic import TMP_PREFIX

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


def _check_inputs(args) -> None:
    """Every file and option of a command that sets ``validate``, checked before any work starts:
    ``--out`` (kind ``out_kind``), ``--knee``, ``--parameters``, ``--protocol``, ``--sets`` and
    the measured data (read once into ``args.measured``)."""
    if not getattr(args, "validate", False):
        return
    if getattr(args, "out_kind", None) and getattr(args, "out", None) is not None:
        _check_out(args.out, args.out_kind)
    knee = getattr(args, "knee", None)
    if knee is not None:
        from kneenlp.model.knee_file import available_knees, resolve_knee

        with _naming("--knee"):
            resolved = resolve_knee(knee)
        if not resolved.is_file():
            raise InputError(f"file not found, and not a shipped knee ({', '.join(available_knees())})",
                             source=knee, field="--knee")
    if getattr(args, "parameters", None):
        from kneenlp.model.parameters import ParameterSet

        with _naming("--parameters"):
            ParameterSet.load(args.parameters)
    from kneenlp.experiment.protocol import Protocol

    if isinstance(getattr(args, "protocol", None), str):
        with _naming("--protocol"):
            Protocol.load(args.protocol)
    for name in getattr(args, "sets", None) or []:
        with _naming("--sets"):
            Protocol.load(name)
    if isinstance(getattr(args, "reference", None), str):
        with _naming("--reference"):
            Protocol.load(args.reference)
    if getattr(args, "data", None) is not None:
        from kneenlp.experiment.measured import read_measured

        args.measured = read_measured(args.data, protocol=getattr(args, "protocol", None))


def _check_names(knee, args) -> None:
    """``--free`` and ``--with-effect`` must name parameters and effects of the model (checked
    after the knee is read, before the work)."""
    from kneenlp.experiment.problem import check_free
    from kneenlp.model.kneemodel import KneeModel

    model = KneeModel.of(knee)
    for spec in getattr(args, "with_effect", None) or []:
        with _naming("--with-effect"):
            model.effect(spec.partition(":")[0])
    if getattr(args, "free", None):
        try:
            check_free(model, args.free)
        except InputError as exc:
            raise InputError(exc.message, source=exc.source, field="--free") from None


def _set_names(text: str) -> list[str]:
    """``--sets``: ``1,2`` -> ``set1, set2``; names and protocol files as they are."""
    return [f"set{s}" if s.isdigit() else s for s in opt.names(text)]


def _knee(args):
    """The knee model of the --knee, --parameters and --element options."""
    from kneenlp.model.knee import Knee
    from kneenlp.model.kneemodel import KneeModel
    from kneenlp.model.plugins import load_elements

    knee = Knee.load(args.knee) if args.knee else Knee.default()
    if getattr(args, "parameters", None):
        knee = knee.with_parameters(args.parameters)
    elements = getattr(args, "element", None)
    return KneeModel(knee, load_elements(elements)) if elements else knee


def _knee_reference(value: str | None) -> str | None:
    """A --knee value as study workers get it: a shipped knee's name, or an absolute path."""
    from kneenlp.model.knee_file import available_knees, knee_file, resolve_knee

    if value is None:
        return value
    path = resolve_knee(value)
    return value if value in available_knees() and path == knee_file(value) else str(path.resolve())


def _effect_values(knee, specs: list[str]) -> dict[str, float]:
    """``NAME[:param=value,...]`` (display units, e.g. ``posterior_capsule:k=8000``,
    ``registration:anterior_translation=1.5``) -> parameter values in SI."""
    import numpy as np

    from kneenlp.model.kneemodel import KneeModel

    model = KneeModel.of(knee)
    values: dict[str, float] = {}
    for spec in specs or []:
        name, _, rest = spec.partition(":")
        with _naming("--with-effect"):
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
                values[full] = float(val) / par.to_user
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


def cmd_diagnose(args) -> int:
    from kneenlp.inference.adequacy import diagnose
    from kneenlp.inference.basefit import base_fit
    from kneenlp.inference.calibrate import calibrate, real_experiment
    from kneenlp.model.kneemodel import KneeModel

    knee = _knee(args)
    data = args.measured  # read and checked by the options layer
    if real_experiment(data):  # the base model of a real experiment is its calibration (registration included)
        fit = calibrate(KneeModel.of(knee), data, noise=args.noise, seed=args.seed).fit
    else:
        fit = base_fit(knee, data, args.noise, seed=args.seed)
    d = diagnose(fit, args.noise, refit=args.refit, limits="simulated" if args.simulated_limits else "linear")
    if args.out:
        with staged_directory(args.out) as stage:
            d.write(stage.path)
    print(d.to_json() if args.json else d.report())
    return 0


def cmd_simulate(args) -> int:
    import numpy as np

    from kneenlp.experiment.protocol import Protocol
    from kneenlp.io import plots
    from kneenlp.simulation import simulate

    protocol = Protocol.load(args.protocol)
    knee = _knee(args)
    result = simulate(knee, protocol, parameters=_effect_values(knee, args.with_effect))
    table = result.table()
    recruitment = result.recruitment() if any(t.direction == "none" for t in protocol.trials) else None
    with staged_directory(args.out) as stage:
        out = stage.path
        table.to_csv(out / "kinematics.csv", index=False, float_format="%.10g")
        (out / "knee_report.txt").write_text(result.knee.report() + "\n")  # how the files became the model
        written = [out / "kinematics.csv", out / "knee_report.txt"]
        if recruitment is not None:
            recruitment.to_csv(out / "ligament_recruitment.csv", index=False, float_format="%.6g")
            written.append(out / "ligament_recruitment.csv")
        biased = bool(np.any(result.model.bias_user(result.model.theta(result.parameters)) != 0))
        if (args.noise not in (None, "none") or biased) and not result.failed:  # a registration bias shows only there
            measured = result.measured(args.noise, args.seed)
            measured.to_csv(out / "measured.csv", index=False, float_format="%.10g")
            written.append(out / "measured.csv")
        if not args.no_plots:
            axes = "/".join(sorted({t.axes for t in protocol.trials}))
            title = f"{result.knee.name} knee, {protocol.title or protocol.name}, loads along {axes} axes"
            written.append(plots.laxity_curves(table, out / "laxity.png", title))
            written.append(plots.ligament_forces(table, list(result.knee.ligaments), out / "ligament_forces.png",
                                                 title, recruitment))
    written = [stage.final(p) for p in written]
    summary = result.summary() | {"outputs": [str(p) for p in written]}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"{protocol.name}: {result.converged}/{len(result.solutions)} trials converged, "
              f"max residual {result.max_residual:.2e} N or N m, {result.seconds:.2f} s")
        cols = ["trial", "varus_rotation_deg", "internal_rotation_deg", "lateral_translation_mm",
                "anterior_translation_mm", "proximal_translation_mm"]
        print(table[cols + [f"{n}_force_N" for n in result.knee.ligaments]].to_string(index=False,
                                                                                        float_format="%.2f"))
        for s in result.failed:
            print(f"NOT CONVERGED: {s.trial.id}: {s.reason}")
        print("wrote: " + ", ".join(str(p) for p in written))
    return 1 if result.failed else 0


def cmd_identify(args) -> int:
    from kneenlp.inference.calibrate import Calibration, calibrate, real_experiment
    from kneenlp.inference.identify import identify
    from kneenlp.model.kneemodel import KneeModel

    knee = _knee(args)
    _check_names(knee, args)
    options = {"weighted": args.weighted, "multistart": args.multistart, "solver": args.solver,
               "protocol": args.protocol, "with_effects": args.with_effect}
    calibration = None
    if real_experiment(args.measured) and args.method == "simultaneous":
        calibration = calibrate(KneeModel.of(knee), args.measured, args.free, seed=args.seed, noise=args.noise,
                                **options)
        fit = calibration.fit
    else:
        fit = identify(knee, args.measured, args.method, free=args.free, seed=args.seed, noise=args.noise, **options)
        calibration = Calibration(fit, None, [])
    if args.out:
        with staged_directory(args.out) as stage:
            fit.table().to_csv(stage.path / "fit_trials.csv", index=False, float_format="%.10g")
            (stage.path / "fit.json").write_text(fit.to_json())
            (stage.path / "calibrated.toml").write_text(calibration.to_toml())
    if args.json:
        print(json.dumps(json.loads(fit.to_json()) | calibration.summary(), indent=2))
    else:
        print(calibration.report())
    return 0 if fit.success else 1


def cmd_compare_methods(args) -> int:
    from kneenlp.inference.identify import identify

    knee = _knee(args)
    fits = [identify(knee, args.measured, seed=args.seed),
            identify(knee, args.measured, method="nested", seed=args.seed,
                     nested_options={"max_evals": args.max_evals, "max_seconds": args.max_seconds})]
    rows = []
    for f in fits:
        rows.append({"method": f.method, "objective": f.objective, "params": f.params_user(),
                     "evaluations": f.evaluations, "evaluation_kind": "IPOPT iterations" if f.method == "simultaneous"
                     else "rootfinder solves (trial equilibria)", "iterations": f.iterations,
                     "seconds": f.seconds, "max_residual": f.max_residual, "status": f.status, "success": f.success})
    ref = fits[0].params
    rows[1]["max_relative_difference"] = max(abs(fits[1].params[n] - ref[n]) / abs(ref[n]) for n in ref)
    if args.json:
        print(json.dumps({"units": {n: fits[0]._info(n).unit for n in fits[0].free}, "methods": rows}, indent=2))
    else:
        names = fits[0].free
        head = f"{'method':13s} {'objective':>12s} " + " ".join(f"{n:>14s}" for n in names)
        print(head + f" {'evaluations':>12s} {'seconds':>8s} {'max resid':>10s}")
        units = " ".join(f"{'[' + fits[0]._info(n).unit + ']':>14s}" for n in names)
        print(f"{'':13s} {'[mm2+deg2]':>12s} {units}")
        for r in rows:
            vals = " ".join(f"{r['params'][n]:14.6g}" for n in names)
            print(f"{r['method']:13s} {r['objective']:12.6g} {vals} {r['evaluations']:12d} {r['seconds']:8.2f}"
                  f" {r['max_residual']:10.2e}")
        print("evaluations: IPOPT iterations (simultaneous); trial equilibrium solves (nested)")
        print(f"largest relative parameter difference: {100 * rows[1]['max_relative_difference']:.3f} %")
    return 0 if all(f.success for f in fits) else 1


#: Fits (sets x samples) a study runs without --yes; the paper's study has 4 x 1000.
MAX_STUDY_FITS = 10_000
#: Seconds a study fit takes on one core, as estimated before a study (measured: 1.7-5.4 s on the
#: synthetic knee; a mesh knee's fit solves its trials with mesh contact: about a minute).
SECONDS_PER_FIT = {"spheres": 3.0, "mesh": 60.0}
#: Disk a sample file takes (a 0.6 kB JSON file in a 4 kB block).
BYTES_PER_SAMPLE = 4096


def _study_size(args) -> str:
    """The study's size in fits, time and disk (estimated from :data:`SECONDS_PER_FIT` and
    :data:`BYTES_PER_SAMPLE`); an input error naming ``--samples`` beyond :data:`MAX_STUDY_FITS`
    fits without ``--yes``, before any work (issue 24: ``--samples 1000000`` gave no early message)."""
    from kneenlp.model.knee_file import resolve_knee
    from kneenlp.model.parameters import read_toml

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


def cmd_study(args) -> int:
    from kneenlp.studies.study import StudySpec, run_study

    size = _study_size(args)
    if args.samples * len(args.sets) > MAX_STUDY_FITS:
        print(f"kneenlp: note: {size}", file=sys.stderr)
    spec = StudySpec(sets=tuple(args.sets), samples=args.samples, noise=args.noise, seed=args.seed,
                     method=args.method, knee=_knee_reference(args.knee),
                     free=tuple(args.free) if args.free else None,
                     start=args.start, elements=tuple(args.element), with_effects=tuple(args.with_effect))
    from kneenlp.studies.truth import study_model

    _check_names(study_model(spec.knee, spec.elements), args)  # built once here; forked workers share it
    study = run_study(spec, args.out, workers=args.workers, scheduler=args.scheduler, dask_local=args.dask,
                      progress=False if args.quiet else None)
    df = study.load_rows()
    failed = int((~df["success"].astype(bool)).sum()) if len(df) else 0
    summary = {"out": str(study.out), "fits": len(df), "failed": failed,
               "outputs": sorted(p.name for p in study.out.iterdir() if p.is_file())}
    if args.json:
        print(json.dumps(summary, indent=2))
    elif not args.quiet:
        print((study.out / "summary.md").read_text())
    return 1 if failed else 0


def cmd_export(args) -> int:
    from kneenlp.io.export import export_problem, write_export

    knee = _knee(args)
    _check_names(knee, args)
    prob = export_problem(knee, args.measured, free=args.free, seed=args.seed, with_effects=args.with_effect,
                          contact="expansion" if args.format == "nl" else "exact")
    with staged_directory(args.out) as stage:
        files = write_export(prob, args.format, stage.path, nl_common=args.nl_common)
    files = [stage.final(f) for f in files]
    if args.json:
        print(json.dumps({"format": args.format, "files": [str(f) for f in files], "contact": prob.contact,
                          **({"contact_error": prob.contact_error} if prob.contact_error else {}),
                          "variables": len(prob.var_names), "constraints": len(prob.con_names)}, indent=2))
    else:
        print(f"wrote {args.format} export of {len(prob.var_names)} variables, {len(prob.con_names)} constraints: "
              + ", ".join(str(f) for f in files))
        if prob.contact_error:
            print(f"contact: {json.loads((files[-1]).read_text())['contact']}")
    return 0


def cmd_design(args) -> int:
    from kneenlp.inference.design import candidate_pool, default_flexions, design, rse_text, write_protocol

    knee = _knee(args)
    _check_names(knee, args)
    flexions = args.flexions if args.flexions is not None else default_flexions(knee)
    result = design(knee, args.max_cases, args.criterion, pool=candidate_pool(flexions), free=args.free,
                    noise=args.noise, robust=args.robust, seed=args.seed, reference=args.reference)
    try:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        path = write_protocol(result, args.out)
    except OSError as exc:
        raise write_error(exc, args.out) from None
    # an unidentified parameter's relative standard error is infinite: null in JSON, never 0
    summary = {"protocol": str(path), "cases": len(result.protocol), "criterion": args.criterion,
               "value": result.value if math.isfinite(result.value) else None,
               "predicted_relative_stderr": {n: v if math.isfinite(v) else None
                                             for n, v in result.predicted_rse.items()},
               "trials": [t.id for t in result.protocol.trials], "infeasible": result.infeasible}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"wrote {path}: {len(result.protocol)} load cases, {args.criterion}-criterion {result.value:.4g}")
        for n, v in result.predicted_rse.items():
            print(f"  {n:18s} predicted relative standard error {rse_text(v)}")
        if result.infeasible:
            print(f"  left out, no equilibrium on this knee: {', '.join(result.infeasible)}")
    return 0


def cmd_view(args) -> int:
    from kneenlp.errors import unknown_name
    from kneenlp.experiment.protocol import Protocol
    from kneenlp.io import views
    from kneenlp.simulation import simulate

    views.require_plotly()
    protocol = Protocol.load(args.protocol)
    known = [t.id for t in protocol.trials]
    for tid in args.trial or []:
        if tid not in known:
            raise unknown_name("trial", tid, known).with_context(field="--trial")
    chosen = list(dict.fromkeys(args.trial)) if args.trial else views.default_view_trials(protocol)
    result = simulate(_knee(args), protocol)
    with staged_directory(args.out) as stage:
        written = views.write_views(result, chosen, stage.path)
    written = [stage.final(p) for p in written]
    failed = [s for s in result.failed if s.trial.id in chosen]
    for s in failed:
        print(f"NOT CONVERGED: {s.trial.id}: {s.reason}")
    print("\n".join(str(p) for p in written))
    return 1 if failed else 0


def _knee_args(p: argparse.ArgumentParser, parameters: bool = True) -> None:
    p.add_argument("--knee", help="knee description TOML, or the name of a shipped knee: default (Lenhart 2015, "
                                  "the default), synthetic")
    if parameters:
        p.add_argument("--parameters", help="parameter set TOML (reference values and fixed parameters)")
    p.add_argument("--element", action="append", default=[], metavar="MODULE:FACTORY",
                   help="add user force elements made by this importable factory (repeatable)")


def cmd_import_osim(args) -> int:
    from kneenlp.io.import_osim import import_osim

    with staged_directory(args.out) as stage:  # a refused import leaves nothing behind (no meshes/)
        report = import_osim(args.model, stage.path, geometry=args.geometry, groups=args.groups,
                             femur_mesh=args.femur_mesh, femur_offset=args.femur_offset * 1e-3,
                             tuberosity=None if args.tuberosity is None else tuple(v * 1e-3 for v in args.tuberosity))
    report.knee_file = Path(args.out) / report.knee_file.name
    print(report.text())
    return 0


def cmd_export_osim(args) -> int:
    from kneenlp.io.export_osim import export_osim

    changes = export_osim(args.fit, args.knee, args.model, args.out)
    print(f"wrote {args.out}: {len(changes)} values of {len({c[0] for c in changes})} bundles changed")
    return 0


def cmd_import_abaqus(args) -> int:
    from kneenlp.io.import_abaqus import import_abaqus

    with staged_directory(args.out) as stage:
        knee_file = import_abaqus(args.model, stage.path, side=args.side, name=args.name or Path(args.out).name)
    print(f"wrote {stage.final(knee_file)} (and parameters.toml, meshes/)")
    return 0


def cmd_import_laxity(args) -> int:
    from kneenlp.io.laxity_mat import import_laxity

    df = import_laxity(args.mat, args.out, args.side)
    if args.json:
        print(json.dumps({"trials": len(df), "out": args.out, "side": args.side}))
    else:
        print(f"wrote {args.out}: {len(df)} trials of a {args.side} knee (joint loads, measured flexion; mm, deg, N, "
              "N m)")
    return 0


def cmd_predict(args) -> int:
    from kneenlp.inference.predict import predict, write_prediction

    knee = _knee(args)
    prediction = predict(knee, args.measured)
    written = []
    if args.out:
        with staged_directory(args.out) as stage:
            written = write_prediction(prediction, stage.path)
        written = [stage.final(p) for p in written]
    if args.json:
        print(json.dumps(prediction.summary() | {"outputs": [str(p) for p in written]}, indent=2))
    else:
        print(prediction.report())
        if written:
            print("wrote: " + ", ".join(str(p) for p in written))
    return 0 if prediction.converged.all() else 1


def cmd_cross_validate(args) -> int:
    from kneenlp.inference import crossval
    from kneenlp.model.kneemodel import KneeModel

    model = KneeModel.of(_knee(args))
    results = crossval.cross_validate(model, args.measured, args.hold_out or None, seed=args.seed)
    table = crossval.table(results)
    written = []
    if args.out:
        with staged_directory(args.out) as stage:
            table.to_csv(stage.path / "cross_validation.csv", index=False, float_format="%.6g")
            for r in results:
                slug = r.name.replace(" ", "_")
                r.prediction.table().to_csv(stage.path / f"predicted_{slug}.csv", index=False, float_format="%.10g")
        written = [str(stage.final(stage.path / "cross_validation.csv"))]
    if args.json:
        print(json.dumps({"units": "mm, deg", "hold_outs": table.to_dict(orient="records"), "outputs": written},
                         indent=2))
    else:
        print(crossval.report(results))
        if written:
            print("wrote: " + ", ".join(written))
    return 0 if all(r.prediction.converged.all() for r in results) else 1


def cmd_identifiability(args) -> int:
    from kneenlp.inference.identifiability import identifiability

    knee = _knee(args)
    _check_names(knee, args)
    result = identifiability(knee, args.protocol, free=args.free, noise=args.noise)
    if args.json:
        print(json.dumps({"rank": result.rank, "identifiable": result.identifiable, "free": result.free,
                          "stderr": result.stderr, "unidentified_directions": result.directions(),
                          "singular_values": result.singular_values.tolist()}, indent=2))
    else:
        print(result.report())
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = opt.OneLineParser(prog="kneenlp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate a laxity protocol (forward problem)")
    p.add_argument("--protocol", default="set3", help="protocol name (set1..set4) or TOML file")
    _knee_args(p)
    p.add_argument("--out", default="kneenlp-out", help="output directory")
    p.add_argument("--noise", default=None, type=opt.noise,
                   help="also write measured.csv with noise: uniform:B | gaussian:S")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the noise (default 0)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.add_argument("--with-effect", action="append", default=[], metavar="NAME:PARAM=VALUE,...",
                   help="switch a candidate effect on (display units), e.g. posterior_capsule:k=8000")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func=cmd_simulate, validate=True, out_kind="dir")

    p = sub.add_parser("diagnose", help="model adequacy: where the fit fails and which effect is missing")
    p.add_argument("data", help="measured-data CSV")
    _knee_args(p)
    p.add_argument("--noise", default="uniform:0.5", type=opt.noise_level,
                   help="noise model of the data (default uniform:0.5)")
    p.add_argument("--refit", type=opt.integer(0, opt.MAX_CASES), default=4,
                   help="refit the best N candidates (default 4)")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the start scatter")
    p.add_argument("--simulated-limits", action="store_true",
                   help="detection limits from simulated noise-free data instead of the linearised test "
                        "(a few seconds per candidate parameter; exact for nonlinear effects)")
    p.add_argument("--out", help="write residual_map.png/.csv, laxity_fit.png and diagnosis.json here")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_diagnose, validate=True, out_kind="dir")

    p = sub.add_parser("identify", help="identify ligament parameters from measured data (simultaneous NLP)")
    p.add_argument("data", help="measured-data CSV (as written by 'kneenlp simulate --noise')")
    _knee_args(p)
    p.add_argument("--free", type=opt.names,
                   help="comma-separated parameters to identify (default: k and ref_strain of all)")
    p.add_argument("--noise", type=opt.noise_level, help="noise model of the data for the covariance, e.g. uniform:0.5")
    p.add_argument("--weighted", action="store_true", help="weight coordinates by inverse noise variance")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the paper's start scatter")
    p.add_argument("--multistart", type=opt.integer(1, opt.MAX_STARTS), default=1,
                   help="number of starts (best is kept)")
    p.add_argument("--method", default="simultaneous", choices=["simultaneous", "nested"],
                   help="simultaneous NLP (default) or the paper's nested Complex method")
    p.add_argument("--solver", default="ipopt", type=opt.solver, help="CasADi nlpsol plugin (default ipopt)")
    p.add_argument("--protocol", help="protocol the data must match (default: the one named in the data)")
    p.add_argument("--with-effect", action="append", default=[], metavar="NAME",
                   help="also identify this candidate effect's parameters (repeatable; see 'kneenlp diagnose')")
    p.add_argument("--out", help="also write fit.json and fit_trials.csv here")
    p.add_argument("--json", action="store_true", help="print JSON instead of the report")
    p.set_defaults(func=cmd_identify, validate=True, out_kind="dir")

    p = sub.add_parser("compare-methods", help="simultaneous NLP vs the paper's nested Complex method")
    p.add_argument("data", help="measured-data CSV")
    _knee_args(p)
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the start scatter / Complex")
    p.add_argument("--max-evals", type=opt.integer(1, opt.MAX_EVALS), default=5000,
                   help="Complex evaluation budget")
    p.add_argument("--max-seconds", type=opt.positive, default=None, help="Complex wall-time budget")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_compare_methods, validate=True)

    p = sub.add_parser("study", help="noise study: the paper's Monte Carlo (Table 3, Fig. 3) at any scale")
    p.add_argument("--sets", default="1,2,3,4", type=_set_names,
                   help="protocols: 1,2,3,4 or names/files (default 1,2,3,4)")
    p.add_argument("--samples", type=opt.integer(1, opt.MAX_SAMPLES), default=20,
                   help="noise samples per set (default 20)")
    p.add_argument("--noise", default="uniform:0.5", type=opt.noise, help="uniform:B or gaussian:SIGMA (mm, deg)")
    p.add_argument("--seed", type=opt.SEED, default=0, help="study seed; each sample's seed derives from it")
    p.add_argument("--method", default="simultaneous", choices=["simultaneous", "nested"])
    _knee_args(p, parameters=False)
    p.add_argument("--free", type=opt.names, help="comma-separated parameters to identify")
    p.add_argument("--with-effect", action="append", default=[], metavar="NAME",
                   help="also identify this candidate effect's parameters (repeatable)")
    p.add_argument("--start", default="scatter", choices=["scatter", "truth"],
                   help="fit starts: scattered like the paper (default) or at the true values")
    p.add_argument("--out", default="kneenlp-study", help="study directory (resumable)")
    p.add_argument("--workers", type=opt.integer(1, opt.MAX_WORKERS), default=None,
                   help="local processes (default: all cores)")
    p.add_argument("--scheduler", type=opt.scheduler, help="Dask scheduler address tcp://HOST:PORT")
    p.add_argument("--dask", action="store_true", help="run on a local Dask cluster")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.add_argument("--yes", action="store_true",
                   help=f"run a study of more than {MAX_STUDY_FITS:,} fits (sets x samples) after its estimate")
    p.set_defaults(func=cmd_study, validate=True, out_kind="dir")

    p = sub.add_parser("export", help="write the identification NLP for other solvers (.nl, CasADi, C)")
    p.add_argument("data", help="measured-data CSV")
    p.add_argument("--format", required=True, choices=["nl", "casadi", "c"], help="export format")
    p.add_argument("--out", default="kneenlp-export", help="output directory")
    _knee_args(p)
    p.add_argument("--free", type=opt.names, help="comma-separated parameters to identify")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the start scatter")
    p.add_argument("--with-effect", action="append", default=[], metavar="NAME",
                   help="also free this candidate effect's parameters (repeatable)")
    p.add_argument("--nl-common", default="defined", choices=["defined", "lifted"],
                   help="shared subexpressions as .nl defined variables (default) or lifted auxiliary variables")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_export, validate=True, out_kind="dir")

    p = sub.add_parser("import-osim", help="turn an OpenSim knee model into a kneenlp knee (multi-bundle)")
    p.add_argument("model", help="the .osim file")
    p.add_argument("--out", required=True, help="directory for knee.toml, parameters.toml and meshes/")
    p.add_argument("--geometry", help="folder of the model's meshes (default: beside the model)")
    p.add_argument("--groups", default="fine", choices=["fine", "coarse"],
                   help="bundle groups: fine (ACLam, ACLpl, ...) or coarse (ACL, PCL, MCL, ...)")
    p.add_argument("--femur-mesh", help="femoral surface to use instead of the model's femoral contact mesh")
    p.add_argument("--femur-offset", type=opt.finite, default=0.0,
                   help="mm the articular surface lies outside --femur-mesh (cartilage thickness on bone)")
    p.add_argument("--tuberosity", type=opt.point3, metavar="X,Y,Z",
                   help="tibial tuberosity, mm in the tibia body's frame (default: the patellar-tendon insertions, "
                        "else estimated from the tibial mesh)")
    p.set_defaults(func=cmd_import_osim, validate=True, out_kind="dir")

    p = sub.add_parser("import-abaqus", help="turn an Abaqus FE knee model (cartilage, fibres, frames) into a knee")
    p.add_argument("model", help="folder of the FE model: geometry/, ligaments/, frames/ (as the S192803 deposit)")
    p.add_argument("--out", required=True, help="directory for knee.toml, parameters.toml and meshes/")
    p.add_argument("--side", required=True, choices=["left", "right"], help="the knee's side")
    p.add_argument("--name", help="the knee's name (default: the --out folder's name)")
    p.set_defaults(func=cmd_import_abaqus, validate=True, out_kind="dir")

    p = sub.add_parser("import-laxity", help="robotic laxity measurements (MATLAB struct) -> measured-data CSV")
    p.add_argument("mat", help="MATLAB file with a processed_laxity_trial struct array")
    p.add_argument("--out", required=True, help="the measured-data CSV to write")
    p.add_argument("--side", required=True, choices=["left", "right"],
                   help="the knee's side (the file's signs are anatomical; the side is recorded and checked "
                        "against the knee a fit uses)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_import_laxity, validate=True, out_kind="file")

    p = sub.add_parser("predict", help="simulate every measured trial at its measured load and flexion; compare")
    p.add_argument("data", help="measured-data CSV (e.g. from import-laxity)")
    _knee_args(p)
    p.add_argument("--out", help="write predicted.csv and predicted_laxity.png here")
    p.add_argument("--json", action="store_true", help="print JSON: rms (mm, deg by column), trials, converged")
    p.set_defaults(func=cmd_predict, validate=True, out_kind="dir")

    p = sub.add_parser("cross-validate", help="calibrate without some trials and predict them (held-out errors)")
    p.add_argument("data", help="measured-data CSV of a real experiment (e.g. from import-laxity)")
    _knee_args(p)
    p.add_argument("--hold-out", action="append", default=[], metavar="NAME",
                   help="only this hold-out (repeatable): 'flexion <F> deg' (the highest flexion) or a load "
                        "direction such as anterior or valgus; default: all of them")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the calibrations (default 0)")
    p.add_argument("--out", help="write cross_validation.csv and each hold-out's predicted_<name>.csv here")
    p.add_argument("--json", action="store_true", help="print JSON: one row per hold-out (RMS in mm, deg)")
    p.set_defaults(func=cmd_cross_validate, validate=True, out_kind="dir")

    p = sub.add_parser("export-osim", help="write a fit of an imported knee into a copy of its OpenSim model")
    p.add_argument("fit", help="the fit's JSON (kneenlp identify --json)")
    p.add_argument("--knee", required=True, help="the imported knee's knee.toml")
    p.add_argument("--model", required=True, help="the OpenSim model the knee was imported from")
    p.add_argument("--out", required=True, help="the calibrated .osim to write")
    p.set_defaults(func=cmd_export_osim, validate=True, out_kind="file")

    p = sub.add_parser("identifiability", help="which parameters a protocol can identify, before fitting")
    p.add_argument("--protocol", default="set4", help="protocol name or TOML file")
    p.add_argument("--free", type=opt.names,
                   help="comma-separated parameters (default: stiffness and reference strain of each)")
    p.add_argument("--noise", default="uniform:0.5", type=opt.noise_level, help="noise model (mm, deg)")
    _knee_args(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_identifiability, validate=True)

    p = sub.add_parser("design", help="design a laxity protocol with few load cases and tight estimates")
    p.add_argument("--max-cases", type=opt.integer(1, opt.MAX_CASES), default=22,
                   help="largest number of load cases (default 22)")
    p.add_argument("--criterion", default="A", choices=["A", "D", "W", "R"],
                   help="A: sum of relative variances, D: log det, W: worst relative standard error, "
                        "R: worst standard-error ratio to a reference protocol (--reference)")
    p.add_argument("--reference", default="set4", help="reference protocol of criterion R (default set4)")
    p.add_argument("--flexions", default=None, type=opt.flexions,
                   help="candidate flexion angles, deg (default 0,15,...,60; to 90 for a multi-bundle knee)")
    p.add_argument("--noise", default="uniform:0.5", type=opt.noise_level, help="noise model (mm, deg)")
    p.add_argument("--robust", type=opt.integer(1, opt.MAX_ROBUST), default=3,
                   help="parameter sets averaged over (knee's + scatter draws)")
    p.add_argument("--free", type=opt.names, help="comma-separated parameters to identify")
    _knee_args(p)
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the robustness draws")
    p.add_argument("--out", default="designed_protocol.toml", help="protocol TOML to write")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_design, validate=True, out_kind="file")

    p = sub.add_parser("view", help="pictures of simulated trials: pressure maps and 3-D views (PNG, HTML)")
    p.add_argument("--protocol", default="set3", help="protocol name (set1..set4) or TOML file")
    p.add_argument("--trial", nargs="+", action="extend", metavar="ID",
                   help="trials to draw (default: the unloaded trials and one loaded trial per direction at the "
                        "first flexion)")
    _knee_args(p)
    p.add_argument("--out", default="kneenlp-view", help="output directory")
    p.set_defaults(func=cmd_view, validate=True, out_kind="dir")
    return parser


class _StderrHandler(logging.StreamHandler):
    """A log handler writing to the current ``sys.stderr`` (which tests and notebooks replace)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _announce_long_steps() -> None:
    """Show kneenlp's progress messages (e.g. a distance field being built once) on stderr."""
    log = logging.getLogger("kneenlp")
    if not any(getattr(h, "kneenlp_cli", False) for h in log.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("kneenlp: %(message)s"))
        handler.kneenlp_cli = True
        log.addHandler(handler)
        log.setLevel(logging.INFO)


def _fail(line: str, status: int, as_json: bool, error: dict | None = None) -> int:
    """End a failed command: ``line`` on stderr and, with ``--json``, the error object on stdout
    (``{"error", "file", "field"}``, ``file``/``field`` null when there is none)."""
    print(f"kneenlp: {line}", file=sys.stderr)
    if as_json:
        print(json.dumps(error or {"error": line, "file": None, "field": None}))
    return status


def _interrupted(signum: int, as_json: bool) -> int:
    if signum == signal.SIGTERM:
        return _fail("terminated (SIGTERM); finished work is kept", EXIT_TERMINATED, as_json)
    return _fail("interrupted (Ctrl-C); finished work is kept", EXIT_INTERRUPTED, as_json)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    as_json = "--json" in argv  # until the options are parsed
    from kneenlp.interrupts import Interrupted, catching_signals, pending

    with catching_signals():
        try:
            args = build_parser().parse_args(argv)
            as_json = bool(getattr(args, "json", False))
            _announce_long_steps()
            _check_inputs(args)
            return int(args.func(args))
        except InputError as exc:
            return _fail(f"error: {exc}", EXIT_INPUT, as_json, exc.to_dict())
        except ConvergenceError as exc:
            print(f"kneenlp: not converged: {exc}", file=sys.stderr)
            return 1
        except BrokenPipeError:  # output piped into e.g. `head`, which closed early
            sys.stderr.close()
            return 0
        except KeyboardInterrupt as exc:
            return _interrupted(exc.signum if isinstance(exc, Interrupted) else signal.SIGINT, as_json)
        except Exception as exc:  # a bug, not bad input: one line, unless debugging
            if pending() is not None:  # the signal's doing (e.g. raised inside a compiled kernel)
                return _interrupted(pending(), as_json)
            if os.environ.get("KNEENLP_DEBUG"):
                raise
            text = " ".join(f"{type(exc).__name__}: {exc}".split())
            return _fail(f"internal error: {text} (a bug; KNEENLP_DEBUG=1 shows the traceback)", EXIT_BUG, as_json)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
