"""The commands: each parses nothing and prints its result (thin: call the library, write the
outputs through a staging directory, print); :data:`COMMANDS` maps a command's name to it."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from kneenlp.base.atomic import staged_directory, write_csv_atomic, write_error, write_text_atomic
from kneenlp.base.errors import InputError
from kneenlp.cli.inputs import MAX_STUDY_FITS, check_names, effect_values, knee_from_args, knee_reference, study_size
from kneenlp.cli.starts import prior_options, search_starts, search_workers, start_workers, worker_count

#: Candidates ``diagnose`` judges by their held-out error on a real experiment (``--held-out``).
HELD_OUT_CANDIDATES = 2


def cmd_diagnose(args) -> int:
    from kneenlp.adequacy.basefit import base_fit
    from kneenlp.adequacy.diagnosis import diagnose
    from kneenlp.estimation.calibrate import calibrate
    from kneenlp.estimation.choice import real_experiment
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.validation import crossval, crossval_report

    knee = knee_from_args(args)
    data = args.measured  # read and checked by the options layer
    real = real_experiment(data)
    minima = None
    if real:  # the base model of a real experiment is its calibration (registration included);
        # every trial: the residual map shows a trial identify would set aside
        calibration = calibrate(KneeModel.of(knee), data, noise=args.noise, seed=args.seed, keep_outliers=True,
                                starts=search_starts(args, calibration=True), workers=search_workers(args))
        fit = calibration.fit
        minima = [m.fit for m in calibration.search.competing()] if calibration.search else None
    else:
        if args.held_out:
            raise InputError("judges a real experiment's calibrations (data of a laboratory experiment)",
                             field="--held-out")
        fit = base_fit(knee, data, args.noise, seed=args.seed)
    d = diagnose(fit, args.noise, refit=args.refit, limits="simulated" if args.simulated_limits else "linear",
                 minima=minima)
    n = (HELD_OUT_CANDIDATES if args.held_out is None else args.held_out) if real else 0
    judged = crossval.judge(KneeModel.of(knee), data, [[s.effect] for s in d.ranking[:n]], seed=args.seed,
                            workers=search_workers(args), starts=search_starts(args, calibration=True)) if n else []
    extra = {"held_out": [j.record() for j in judged],
             "held_out_recommended": (best.name if (best := crossval.judged_best(judged)) else None)} if judged else {}
    if args.out:
        with staged_directory(args.out) as stage:
            d.write(stage.path)
            if judged:
                write_text_atomic(stage.path / "held_out.json", json.dumps(extra, indent=2))
    if args.json:
        print(json.dumps(json.loads(d.to_json()) | extra, indent=2))
    else:
        print("\n".join([d.report(), *crossval_report.judgement_lines(judged)]) if judged else d.report())
    return 0


def experiment_from_arg(value: str):
    """``--experiment``: a shipped experiment's name or an experiment file -> (experiment, its file)."""
    from pathlib import Path

    from kneenlp.experiment.kind import Experiment, experiment_named

    if value.endswith(".toml"):
        if not Path(value).is_file():
            raise InputError("file not found", source=value, field="--experiment")
        return Experiment.load(value), Path(value)
    try:
        return experiment_named(value), None
    except InputError as exc:
        raise exc.with_context(field="--experiment") from None


def cmd_simulate(args) -> int:
    import numpy as np

    from kneenlp.experiment.protocol import Protocol
    from kneenlp.figures import plots
    from kneenlp.simulation import simulate

    protocol = Protocol.load(args.protocol)
    knee = knee_from_args(args)
    experiment, experiment_file = experiment_from_arg(args.experiment)
    result = simulate(knee, protocol, parameters=effect_values(knee, args.with_effect), experiment=experiment)
    table = result.table()
    recruitment = result.recruitment() if any(t.direction == "none" for t in protocol.trials) else None
    with staged_directory(args.out) as stage:
        out = stage.path
        write_csv_atomic(table, out / "kinematics.csv", index=False, float_format="%.10g")
        write_text_atomic(out / "knee_report.txt", result.knee.report() + "\n")  # how the files became the model
        written = [out / "kinematics.csv", out / "knee_report.txt"]
        if recruitment is not None:
            write_csv_atomic(recruitment, out / "ligament_recruitment.csv", index=False, float_format="%.6g")
            written.append(out / "ligament_recruitment.csv")
        biased = bool(np.any(result.model.bias_user(result.model.theta(result.parameters)) != 0))
        if (args.noise not in (None, "none") or biased) and not result.failed:  # a registration bias shows only there
            measured = result.measured(args.noise, args.seed)
            write_csv_atomic(measured, out / "measured.csv", index=False, float_format="%.10g")
            written.append(out / "measured.csv")
            if experiment_file is not None:  # the data name their experiment: its file goes beside them
                written.append(write_text_atomic(out / f"{experiment.name}.toml", experiment_file.read_text()))
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
        for s in result.solutions:
            if s.note:
                print(f"NOTE: {s.trial.id}: {s.note}")
        print("wrote: " + ", ".join(str(p) for p in written))
    return 1 if result.failed else 0












def held_out_judgements(knee, args) -> list:
    """``identify --held-out``: the calibration (without ``--also-free``) and, given, with it, judged by
    their held-out errors (:func:`kneenlp.validation.crossval.judge`)."""
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.validation import crossval

    options = {k: v for k, v in (("pivot_tolerance", args.pivot_tolerance), ("keep_outliers", args.keep_outliers))
               if v} | prior_options(args)
    return crossval.judge(KneeModel.of(knee), args.measured, [args.also_free] if args.also_free else [],
                          noise=args.noise, seed=args.seed, workers=worker_count(args), **options)


def cmd_identify(args) -> int:
    from kneenlp.estimation.calibrated import NO_RECORD, posterior
    from kneenlp.estimation.identify import identification
    from kneenlp.estimation.profile import profile, profile_lines
    from kneenlp.figures.plots import waterfall
    from kneenlp.io import inferencedata
    from kneenlp.validation import crossval_report

    knee = knee_from_args(args)
    check_names(knee, args)
    given = {"pivot_tolerance": args.pivot_tolerance, "also_free": args.also_free,
             "keep_outliers": args.keep_outliers or None}
    calibration = identification(knee, args.measured, method=args.method, strategy=args.strategy, free=args.free,
                                 seed=args.seed, noise=args.noise, weighted=args.weighted,
                                 multistart=args.multistart, solver=args.solver, **start_workers(args),
                                 protocol=args.protocol, with_effects=args.with_effect, **prior_options(args),
                                 **{k: v for k, v in given.items() if v is not None})
    fit = calibration.fit
    if args.held_out and calibration.record is NO_RECORD:
        raise InputError("judges a real experiment's calibration (data of a laboratory experiment)",
                         field="--held-out")
    judged = held_out_judgements(knee, args) if args.held_out else []
    intervals = profile(fit, args.profile) if args.profile else []
    summary = json.dumps(json.loads(fit.to_json()) | calibration.summary()
                         | ({"profile": [i.record() for i in intervals]} if intervals else {})
                         | ({"held_out": [j.record() for j in judged]} if judged else {}), indent=2)
    if args.out:
        with staged_directory(args.out) as stage:
            write_csv_atomic(fit.table(), stage.path / "fit_trials.csv", index=False, float_format="%.10g")
            write_text_atomic(stage.path / "fit.json", summary)
            write_text_atomic(stage.path / "calibrated.toml", calibration.to_toml())
            if calibration.search is not None:
                waterfall(calibration.search.objectives(), calibration.search.best.hits,
                          stage.path / "waterfall.png")
            if calibration.set_aside is not None:  # the trials the outlier test set aside, predicted
                write_csv_atomic(calibration.set_aside.table(), stage.path / "set_aside.csv", index=False,
                                 float_format="%.10g")
            if inferencedata.available():  # the posterior's draws for ArviZ
                inferencedata.write_inference_data(stage.path / "posterior.nc", fit, posterior(fit), seed=args.seed)
    notes = [] if not args.out or inferencedata.available() else [
        "posterior.nc (ArviZ InferenceData) not written: pip install 'kneenlp[arviz]'"]
    if args.json:
        print(summary)
    else:
        judgement = crossval_report.judgement_lines(judged) if judged else []
        print("\n".join([calibration.report(), *profile_lines(intervals), *judgement, *notes]))
    return 0 if fit.success else 1


def _calibration_comparison(out: dict) -> str:
    """``compare_calibration``'s result as a table (MAP objective: mm^2 + deg^2)."""
    p = out["problem"]
    fit = f"MAP (priors weighed against {p['prior_weight']:g})" if p["priors"] else "least squares"
    lines = [f"the calibration's problem: {p['trials']} trials, {p['free']} free parameters, {fit}",
             f"{'method':36s} {'MAP objective':>14s} {'evaluations':>12s} {'seconds':>8s} {'max resid':>10s}  status"]
    for r in out["methods"]:
        lines.append(f"{r['method']:36s} {r['map_objective']:14.6g} {r['evaluations']:12d} {r['seconds']:8.1f} "
                     f"{r['max_residual']:10.2e}  {r['status']}{'' if r['success'] else ' (NOT CONVERGED)'}")
    lines.append("nested, best MAP objective after N rootfinder solves: "
                 + ", ".join(f"{k:,}: {v:.6g}" for k, v in out["nested_checkpoints"].items()))
    return "\n".join(lines)


def cmd_compare_methods(args) -> int:
    from kneenlp.estimation.choice import real_experiment
    from kneenlp.estimation.compare import compare_calibration, compare_methods
    from kneenlp.experiment.kneemodel import KneeModel

    if real_experiment(args.measured):
        out = compare_calibration(KneeModel.of(knee_from_args(args)), args.measured, seed=args.seed,
                                  max_solves=args.max_solves, max_seconds=args.max_seconds)
        print(json.dumps(out, indent=2) if args.json else _calibration_comparison(out))
        return 0 if all(r["success"] for r in out["methods"]) else 1
    out = compare_methods(knee_from_args(args), args.measured, seed=args.seed, max_evals=args.max_evals,
                          max_seconds=args.max_seconds)
    rows, units = out["methods"], out["units"]
    if args.json:
        print(json.dumps({"units": units, "methods": rows}, indent=2))
    else:
        names = list(units)
        head = f"{'method':13s} {'objective':>12s} " + " ".join(f"{n:>14s}" for n in names)
        print(head + f" {'evaluations':>12s} {'seconds':>8s} {'max resid':>10s}")
        unit_row = " ".join(f"{'[' + units[n] + ']':>14s}" for n in names)
        print(f"{'':13s} {'[mm2+deg2]':>12s} {unit_row}")
        for r in rows:
            vals = " ".join(f"{r['params'][n]:14.6g}" for n in names)
            print(f"{r['method']:13s} {r['objective']:12.6g} {vals} {r['evaluations']:12d} {r['seconds']:8.2f}"
                  f" {r['max_residual']:10.2e}")
        print("evaluations: IPOPT iterations (simultaneous); trial equilibrium solves (nested)")
        print(f"largest relative parameter difference: {100 * rows[1]['max_relative_difference']:.3f} %")
    return 0 if all(r["success"] for r in rows) else 1


def cmd_study(args) -> int:
    from kneenlp.studies.study import StudySpec, run_study
    from kneenlp.studies.truth import StudyTruths

    size = study_size(args)
    if args.samples * len(args.sets) > MAX_STUDY_FITS:
        print(f"kneenlp: note: {size}", file=sys.stderr)
    spec = StudySpec(sets=tuple(args.sets), samples=args.samples, noise=args.noise, seed=args.seed,
                     method=args.method, knee=knee_reference(args.knee),
                     free=tuple(args.free) if args.free else None,
                     start=args.start, elements=tuple(args.element), with_effects=tuple(args.with_effect))
    truths = StudyTruths.of(spec)
    check_names(truths.model, args)  # built once here; forked workers share it
    study = run_study(spec, args.out, workers=args.workers, scheduler=args.scheduler, dask_local=args.dask,
                      progress=False if args.quiet else None, truths=truths)
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
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.io.export import export_problem, write_export

    model = KneeModel.of(knee_from_args(args))
    check_names(model, args)
    if args.format == "nl" and model.ws_size and not args.approximate:
        raise InputError("a mesh knee's contact cannot be written exactly as .nl (AMPL has no distance field): "
                         "use --format casadi or --format c (exact), or add --approximate for its second-order "
                         "expansion at the start poses", field="--format")
    prob = export_problem(model, args.measured, free=args.free, seed=args.seed, with_effects=args.with_effect,
                          contact="expansion" if args.format == "nl" else "exact",
                          layout="loop" if args.format == "c" else "vector")
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
    if args.format == "c" and prob.meta.get("working_sets"):
        print("note: this C source holds the mesh knee's femoral distance field as one constant array; "
              "gcc -shared -fPIC -O0 compiles the default knee's in ~10 s, -O1 in ~70 s (docs/solvers.md)",
              file=sys.stderr)
    return 0


def cmd_design(args) -> int:
    from kneenlp.design.optimal import candidate_pool, default_flexions, design, rse_text, write_protocol

    knee = knee_from_args(args)
    check_names(knee, args)
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
    from kneenlp.base.errors import unknown_name
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
    result = simulate(knee_from_args(args), protocol)
    with staged_directory(args.out) as stage:
        written = views.write_views(result, chosen, stage.path)
    written = [stage.final(p) for p in written]
    failed = [s for s in result.failed if s.trial.id in chosen]
    for s in failed:
        print(f"NOT CONVERGED: {s.trial.id}: {s.reason}")
    print("\n".join(str(p) for p in written))
    return 1 if failed else 0


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


def cmd_export_abaqus(args) -> int:
    from kneenlp.io.export_abaqus import export_abaqus

    if Path(args.out).resolve() == Path(args.model).resolve():
        raise InputError("is the --model folder itself: the calibrated copy would overwrite the model it is made "
                         "from; give another folder", source=args.out, field="--out")
    with staged_directory(args.out) as stage:
        report = export_abaqus(args.calibration, args.knee, args.model, stage.path)
        stray = sorted({p.relative_to(args.out) for p in Path(args.out).rglob("*") if p.is_file()
                        and stage.path not in p.parents} - {p.relative_to(stage.path) for p in stage.path.rglob("*")})
        if stray:
            raise InputError(f"holds {len(stray)} file(s) this export does not write (e.g. {stray[0]}), which would "
                             "sit beside the calibrated model: give an empty or new folder", source=args.out,
                             field="--out")
    report.out = Path(args.out)
    print(report.text())
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
    from kneenlp.prediction.predict import predict, write_prediction

    knee = knee_from_args(args)
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
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.validation import crossval, crossval_report

    model = KneeModel.of(knee_from_args(args))
    store = Path(args.out) / "store" if args.out else None  # each draw and each search's solves as they finish
    results = crossval.cross_validate(model, args.measured, args.hold_out or None, reference_draws=args.twins,
                                      store=store, workers=search_workers(args), explain=True, seed=args.seed,
                                      pivot_tolerance=args.pivot_tolerance, also_free=args.also_free,
                                      keep_outliers=args.keep_outliers, multistart=args.multistart,
                                      starts=search_starts(args, calibration=True),
                                      **prior_options(args))
    table = crossval_report.table(results)
    written = []
    if args.out:
        with staged_directory(args.out) as stage:
            write_csv_atomic(table, stage.path / "cross_validation.csv", index=False, float_format="%.6g")
            for r in results:
                slug = r.name.replace(" ", "_")
                write_csv_atomic(r.prediction.table(), stage.path / f"predicted_{slug}.csv", index=False,
                                 float_format="%.10g")
        written = [str(stage.final(stage.path / "cross_validation.csv"))]
    if args.json:
        print(json.dumps({"units": "mm, deg", "hold_outs": table.to_dict(orient="records"), "outputs": written},
                         indent=2))
    else:
        print(crossval_report.report(results))
        if written:
            print("wrote: " + ", ".join(written))
    return 0 if all(r.prediction.converged.all() for r in results) else 1


def cmd_identifiability(args) -> int:
    from kneenlp.design.identifiability import identifiability

    knee = knee_from_args(args)
    check_names(knee, args)
    result = identifiability(knee, args.protocol, free=args.free, noise=args.noise)
    if args.json:
        print(json.dumps({"rank": result.rank, "identifiable": result.identifiable, "free": result.free,
                          "stderr": result.stderr, "unidentified_directions": result.directions(),
                          "singular_values": result.singular_values.tolist()}, indent=2))
    else:
        print(result.report())
    return 0


#: The command of each name (the parser's subcommands).
COMMANDS = {
    "simulate": cmd_simulate,
    "diagnose": cmd_diagnose,
    "identify": cmd_identify,
    "compare-methods": cmd_compare_methods,
    "study": cmd_study,
    "export": cmd_export,
    "import-osim": cmd_import_osim,
    "import-abaqus": cmd_import_abaqus,
    "import-laxity": cmd_import_laxity,
    "predict": cmd_predict,
    "cross-validate": cmd_cross_validate,
    "export-osim": cmd_export_osim,
    "export-abaqus": cmd_export_abaqus,
    "identifiability": cmd_identifiability,
    "design": cmd_design,
    "view": cmd_view,
}
