"""The argument parser of the command line: every subcommand, its options and their types
(:mod:`kneenlp.cli.options` checks values by type and range)."""

from __future__ import annotations

import argparse

from kneenlp.base.modes import (
    Criterion,
    ExportFormat,
    Groups,
    Method,
    NlCommon,
    PriorChoice,
    Side,
    Strategy,
    StudyStart,
    names,
)
from kneenlp.base.resources import shipped_knees
from kneenlp.cli import options as opt
from kneenlp.cli.inputs import MAX_STUDY_FITS, set_names


def _knee_args(p: argparse.ArgumentParser, parameters: bool = True) -> None:
    p.add_argument("--knee", help="knee description TOML, or the name of a shipped knee: "
                                  f"{', '.join(shipped_knees())} (default: default, Lenhart 2015)")
    if parameters:
        p.add_argument("--parameters", help="parameter set TOML (reference values and fixed parameters)")
    p.add_argument("--element", action="append", default=[], metavar="MODULE:FACTORY",
                   help="add user force elements made by this importable factory (repeatable)")


def _data_args(p: argparse.ArgumentParser, help: str) -> None:
    """The measured data: a CSV, or a problem folder naming it with its knee and parameter table."""
    p.add_argument("data", nargs="?", help=f"{help}; or give --problem")
    p.add_argument("--problem", metavar="DIR",
                   help="a problem folder (problem.toml: the knee, the data, the parameter table, the noise, the "
                        "hold-outs; e.g. problems/s192803): instead of DATA and --knee; options given override it")


def _workers_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=opt.integer(1, opt.MAX_WORKERS), default=None,
                   help="processes that independent calibrations share: the hold-outs' (each hold-out's own "
                        "starts then run in turn), identify's further starts (default: all cores)")


def _multistart_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--multistart", type=opt.integer(1, opt.MAX_STARTS), default=None, metavar="N",
                   help="number of starts, the lowest converged kept (a real experiment's calibration: the "
                        "fit, then N-1 starts half a prior sd about it; default: the problem's, else 1)")


def _starts_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--starts", type=opt.integer(1, opt.MAX_STARTS), default=None, metavar="N",
                   help="a real experiment's calibration by the global search: N starts (the knee's values and "
                        "Sobol points over the priors' central 95 %%), each screened, the best refined by the NLP, "
                        "the lowest deepened; its minima are reported and, with --out, waterfall.png and the "
                        "finished solves (search/, a rerun resumes them) written (docs/real-experiment.md); "
                        "default: the problem's, else 16 for a real experiment's calibration (1: the local "
                        "calibration from the knee's values, a quick look), 1 for a scatter fit")


def _dask_args(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--scheduler", type=opt.scheduler, help=f"{what} the Dask scheduler at tcp://HOST:PORT")
    p.add_argument("--dask", action="store_true", help=f"{what} a local Dask cluster of --workers processes")


def _prior_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--priors", choices=names(PriorChoice), default=None,
                   help="default: the MAP estimate, every free parameter with its prior (from the parameter file "
                        "or the shipped defaults centred on the knee's values, docs/priors.md); none: least squares "
                        "on the data alone.  Default: 'default' for a real experiment's calibration, 'none' for data "
                        "the model produced (the paper's least squares)")
    p.add_argument("--prior-weight", type=opt.prior_weight, default=None, metavar="VAR",
                   help="the misfit variance (mm^2 and deg^2) the priors are weighed against, or 'estimate' (from "
                        "the fit's residuals); default: the declared noise's variance, else 1 (docs/priors.md)")


def build_parser() -> argparse.ArgumentParser:
    parser = opt.OneLineParser(prog="kneenlp", description="Command-line interface: ``kneenlp <command> ...``.")
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
    p.add_argument("--experiment", default="simulated", metavar="NAME|FILE.toml",
                   help="the experiment simulated: where its force acts, the coordinates it holds and observes "
                        "(an experiment file, copied beside measured.csv; default: simulated)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("diagnose", help="model adequacy: where the fit fails and which effect is missing")
    _data_args(p, "measured-data CSV")
    _knee_args(p)
    p.add_argument("--noise", default=None, type=opt.noise_level,
                   help="noise model of the data (default: the problem's, else uniform:0.5)")
    p.add_argument("--refit", type=opt.integer(0, opt.MAX_CASES), default=4,
                   help="refit the best N candidates (default 4)")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the start scatter")
    p.add_argument("--held-out", type=opt.integer(0, opt.MAX_CASES), default=None, metavar="N",
                   help="real experiments: judge the N best-ranked candidates by their held-out error (each "
                        "calibrated beside the default and cross-validated, each calibration by the global search: "
                        "several minutes each; default 2, 0 skips)")
    _workers_arg(p)
    _starts_arg(p)
    _dask_args(p, "the global search's solves (--starts) on")
    p.add_argument("--simulated-limits", action="store_true",
                   help="detection limits from simulated noise-free data instead of the linearised test "
                        "(a few seconds per candidate parameter; exact for nonlinear effects)")
    p.add_argument("--out", help="write residual_map.png/.csv, laxity_fit.png and diagnosis.json here")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("identify", help="identify ligament parameters from measured data (simultaneous NLP)")
    _data_args(p, "measured-data CSV (as written by 'kneenlp simulate --noise')")
    _knee_args(p)
    p.add_argument("--free", type=opt.names,
                   help="comma-separated parameters to identify (default: k and ref_strain of all)")
    p.add_argument("--noise", type=opt.noise_level, help="noise model of the data for the covariance, e.g. uniform:0.5")
    p.add_argument("--weighted", action="store_true", help="weight coordinates by inverse noise variance")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the paper's start scatter")
    _multistart_arg(p)
    _starts_arg(p)
    _dask_args(p, "the global search's solves (--starts) on")
    p.add_argument("--method", default="simultaneous", choices=names(Method),
                   help="simultaneous NLP (default) or the paper's nested Complex method")
    p.add_argument("--solver", default="ipopt", type=opt.solver, help="CasADi nlpsol plugin (default ipopt)")
    p.add_argument("--protocol", help="protocol the data must match (default: the one named in the data)")
    p.add_argument("--with-effect", action="append", default=[], metavar="NAME",
                   help="also identify this candidate effect's parameters (repeatable; see 'kneenlp diagnose')")
    p.add_argument("--pivot-tolerance", type=opt.fraction, default=None, metavar="F",
                   help="real experiments: fit the ligament parameters whose pivot is at least F of the largest "
                        "(default 0.02; larger fits fewer: worse on these trials, often better on others)")
    p.add_argument("--also-free", type=opt.names, default=None, metavar="NAMES",
                   help="real experiments: also fit these comma-separated parameters, effects or elements, e.g. "
                        "the experiment's frames tibial_origin,femoral_origin,tibial_axes or attachments "
                        "PCLal_femoral_attachment (see 'kneenlp diagnose')")
    p.add_argument("--keep-outliers", action="store_true",
                   help="real experiments: fit every trial (default: trials the outlier test flags are set aside "
                        "and reported, docs/real-experiment.md)")
    p.add_argument("--strategy", default=None, choices=names(Strategy),
                   help="calibration (a real experiment's: MAP, registration and load point, outlier test), scatter "
                        "(the paper's: least squares from a seeded scatter) or auto (default: calibration for data "
                        "of a laboratory experiment)")
    _prior_args(p)
    p.add_argument("--held-out", action="store_true",
                   help="real experiments: judge the calibration by what it predicts: cross-validated (each load "
                        "direction and the highest flexion held out) beside its fit, and with --also-free before "
                        "and after (about a minute per calibration)")
    _workers_arg(p)
    p.add_argument("--profile", type=opt.names, default=None, metavar="NAMES",
                   help="profile-likelihood intervals (95 %%, bounds respected) of these comma-separated free "
                        "parameters, beside the Laplace standard errors")
    p.add_argument("--out", help="also write fit.json, fit_trials.csv and calibrated.toml here (real experiments: "
                                 "set_aside.csv, the trials the outlier test set aside, predicted)")
    p.add_argument("--json", action="store_true", help="print JSON instead of the report")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("compare-methods", help="simultaneous NLP vs the paper's nested Complex method")
    p.add_argument("data", help="measured-data CSV")
    _knee_args(p)
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the start scatter / Complex")
    p.add_argument("--max-evals", type=opt.integer(1, opt.MAX_EVALS), default=5000,
                   help="Complex evaluation budget")
    p.add_argument("--max-seconds", type=opt.positive, default=None, help="Complex wall-time budget")
    p.add_argument("--max-solves", type=opt.integer(1, 10**7), default=75_000,
                   help="real experiments: the nested method's budget in rootfinder solves (trial equilibria; "
                        "default 75000, its best objective reported after 1k, 5k, 20k and 75k)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(validate=True)

    p = sub.add_parser("study", help="noise study: the paper's Monte Carlo (Table 3, Fig. 3) at any scale")
    p.add_argument("--sets", default="1,2,3,4", type=set_names,
                   help="protocols: 1,2,3,4 or names/files (default 1,2,3,4)")
    p.add_argument("--samples", type=opt.integer(1, opt.MAX_SAMPLES), default=20,
                   help="noise samples per set (default 20)")
    p.add_argument("--noise", default="uniform:0.5", type=opt.noise, help="uniform:B or gaussian:SIGMA (mm, deg)")
    p.add_argument("--seed", type=opt.SEED, default=0, help="study seed; each sample's seed derives from it")
    p.add_argument("--method", default="simultaneous", choices=names(Method))
    _knee_args(p, parameters=False)
    p.add_argument("--free", type=opt.names, help="comma-separated parameters to identify")
    p.add_argument("--with-effect", action="append", default=[], metavar="NAME",
                   help="also identify this candidate effect's parameters (repeatable)")
    p.add_argument("--start", default="scatter", choices=names(StudyStart),
                   help="fit starts: scattered like the paper (default) or at the true values")
    p.add_argument("--out", default="kneenlp-study", help="study directory (resumable)")
    p.add_argument("--workers", type=opt.integer(1, opt.MAX_WORKERS), default=None,
                   help="local processes (default: all cores)")
    _dask_args(p, "run on")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.add_argument("--yes", action="store_true",
                   help=f"run a study of more than {MAX_STUDY_FITS:,} fits (sets x samples) after its estimate")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("export", help="write the identification NLP for other solvers (.nl, CasADi, C)")
    p.add_argument("data", help="measured-data CSV")
    p.add_argument("--format", required=True, choices=names(ExportFormat), help="export format")
    p.add_argument("--out", default="kneenlp-export", help="output directory")
    _knee_args(p)
    p.add_argument("--free", type=opt.names, help="comma-separated parameters to identify")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the start scatter")
    p.add_argument("--with-effect", action="append", default=[], metavar="NAME",
                   help="also free this candidate effect's parameters (repeatable)")
    p.add_argument("--nl-common", default="defined", choices=names(NlCommon),
                   help="shared subexpressions as .nl defined variables (default) or lifted auxiliary variables")
    p.add_argument("--approximate", action="store_true",
                   help=".nl of a mesh knee: write its contact as the second-order expansion at the start poses "
                        "(an approximation, its error in the file); without it such a .nl is refused")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("import-osim", help="turn an OpenSim knee model into a kneenlp knee (multi-bundle)")
    p.add_argument("model", help="the .osim file")
    p.add_argument("--out", required=True, help="directory for knee.toml, parameters.toml and meshes/")
    p.add_argument("--geometry", help="folder of the model's meshes (default: beside the model)")
    p.add_argument("--groups", default="fine", choices=names(Groups),
                   help="bundle groups: fine (ACLam, ACLpl, ...) or coarse (ACL, PCL, MCL, ...)")
    p.add_argument("--femur-mesh", help="femoral surface to use instead of the model's femoral contact mesh")
    p.add_argument("--femur-offset", type=opt.finite, default=0.0,
                   help="mm the articular surface lies outside --femur-mesh (cartilage thickness on bone)")
    p.add_argument("--tuberosity", type=opt.point3, metavar="X,Y,Z",
                   help="tibial tuberosity, mm in the tibia body's frame (default: the patellar-tendon insertions, "
                        "else estimated from the tibial mesh)")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("import-abaqus", help="turn an Abaqus FE knee model (cartilage, fibres, frames) into a knee")
    p.add_argument("model", help="folder of the FE model: geometry/, ligaments/, frames/ (as the S192803 deposit)")
    p.add_argument("--out", required=True, help="directory for knee.toml, parameters.toml and meshes/")
    p.add_argument("--side", required=True, choices=names(Side), help="the knee's side")
    p.add_argument("--name", help="the knee's name (default: the --out folder's name)")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("import-laxity", help="robotic laxity measurements (MATLAB struct) -> measured-data CSV")
    p.add_argument("mat", help="MATLAB file with a processed_laxity_trial struct array")
    p.add_argument("--out", required=True, help="the measured-data CSV to write")
    p.add_argument("--side", required=True, choices=names(Side),
                   help="the knee's side (the file's signs are anatomical; the side is recorded and checked "
                        "against the knee a fit uses)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(validate=True, out_kind="file")

    p = sub.add_parser("predict", help="simulate every measured trial at its measured load and flexion; compare")
    _data_args(p, "measured-data CSV (e.g. from import-laxity)")
    _knee_args(p)
    p.add_argument("--out", help="write predicted.csv and predicted_laxity.png here")
    p.add_argument("--json", action="store_true", help="print JSON: rms (mm, deg by column), trials, converged")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("cross-validate", help="calibrate without some trials and predict them (held-out errors)")
    _data_args(p, "measured-data CSV of a real experiment (e.g. from import-laxity)")
    _knee_args(p)
    p.add_argument("--hold-out", action="append", default=[], metavar="NAME",
                   help="only this hold-out (repeatable): 'flexion <F> deg' (every trial at a nominal flexion: "
                        "the highest by default, any other by name) or a load direction such as anterior or "
                        "valgus; default: the highest flexion and every load direction")
    p.add_argument("--seed", type=opt.SEED, default=0, help="seed of the calibrations (default 0)")
    _multistart_arg(p)
    _starts_arg(p)
    _dask_args(p, "the global search's solves (--starts) on")
    p.add_argument("--pivot-tolerance", type=opt.fraction, default=None, metavar="F",
                   help="the calibrations fit the ligament parameters whose pivot is at least F of the largest "
                        "(default 0.02, see 'kneenlp identify')")
    p.add_argument("--also-free", type=opt.names, default=None, metavar="NAMES",
                   help="the calibrations also fit these parameters or effects (see 'kneenlp identify')")
    p.add_argument("--keep-outliers", action="store_true",
                   help="the calibrations fit every trial they keep (see 'kneenlp identify'); the held-out "
                        "trials are always predicted")
    _prior_args(p)
    p.add_argument("--twins", type=opt.integer(0, 100), default=0, metavar="N",
                   help="hold out the same trials of N twins of the experiment too: the knee calibrated on "
                        "every trial as the knee, its predictions plus noise at the calibration's level (seeded "
                        "by --seed); the error a model that is exactly right would have (default 0); with --out "
                        "each draw is written to OUT/store as it finishes and a rerun resumes from there")
    _workers_arg(p)
    p.add_argument("--out", help="write cross_validation.csv and each hold-out's predicted_<name>.csv here")
    p.add_argument("--json", action="store_true", help="print JSON: one row per hold-out (RMS in mm, deg)")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("export-osim", help="write a fit of an imported knee into a copy of its OpenSim model")
    p.add_argument("fit", help="the fit's JSON (kneenlp identify --json) or calibrated.toml (identify --out)")
    p.add_argument("--knee", required=True, help="the imported knee's knee.toml")
    p.add_argument("--model", required=True, help="the OpenSim model the knee was imported from")
    p.add_argument("--out", required=True, help="the calibrated .osim to write")
    p.set_defaults(validate=True, out_kind="file")

    p = sub.add_parser("export-abaqus", help="write a calibration into a copy of the Abaqus model a knee came from")
    p.add_argument("calibration", help="calibrated.toml (identify --out) or the fit's JSON (identify --json)")
    p.add_argument("--knee", required=True, help="the imported knee (a name or its knee.toml)")
    p.add_argument("--model", required=True, help="the Abaqus model's folder the knee was imported from")
    p.add_argument("--out", required=True, help="the folder for the calibrated copy of the model")
    p.set_defaults(validate=True, out_kind="dir")

    p = sub.add_parser("identifiability", help="which parameters a protocol can identify, before fitting")
    p.add_argument("--protocol", default="set4", help="protocol name or TOML file")
    p.add_argument("--free", type=opt.names,
                   help="comma-separated parameters (default: stiffness and reference strain of each)")
    p.add_argument("--noise", default="uniform:0.5", type=opt.noise_level, help="noise model (mm, deg)")
    _knee_args(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(validate=True)

    p = sub.add_parser("design", help="design a laxity protocol with few load cases and tight estimates")
    p.add_argument("--max-cases", type=opt.integer(1, opt.MAX_CASES), default=22,
                   help="largest number of load cases (default 22)")
    p.add_argument("--criterion", default="A", choices=names(Criterion),
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
    p.set_defaults(validate=True, out_kind="file")

    p = sub.add_parser("view", help="pictures of simulated trials: pressure maps and 3-D views (PNG, HTML)")
    p.add_argument("--protocol", default="set3", help="protocol name (set1..set4) or TOML file")
    p.add_argument("--trial", nargs="+", action="extend", metavar="ID",
                   help="trials to draw (default: the unloaded trials and one loaded trial per direction at the "
                        "first flexion)")
    _knee_args(p)
    p.add_argument("--out", default="kneenlp-view", help="output directory")
    p.set_defaults(validate=True, out_kind="dir")
    return parser
