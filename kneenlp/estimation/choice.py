"""What a real experiment's calibration fits: the probe that engages groups slack in every trial,
the free parameters (its choice, a user's, a file's or a :class:`~kneenlp.model.params.Parameters`'),
the extras by name and the priors of the engaged groups.  :mod:`kneenlp.estimation.calibrate` fits them."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg

from kneenlp.base.conventions import COORDINATES
from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.model.params import Parameters, declared_free, default_free, named_parameters
from kneenlp.model.priors import Prior
from kneenlp.solvers.forward import forward_solver

if TYPE_CHECKING:
    from kneenlp.estimation.calibration_options import CalibrationOptions

#: Smallest pivot (relative to the largest) of a parameter the calibration frees.
PIVOT_TOLERANCE = 0.02


#: Strain (fraction) at which the probe engages a group slack in every trial: inside the toe region.
ENGAGE_STRAIN = 0.02


REGISTRATION = [f"registration.{c}" for c in COORDINATES]


#: The robot's load point, freed in the calibration of joint loads (module docstring).
LOAD_POINT = "load_point.lateral"


def real_experiment(data: MeasuredData) -> bool:
    """Data from a real knee's experiment rather than from the model: as the data declare
    (:class:`~kneenlp.experiment.kind.Experiment`)."""
    return data.experiment.laboratory


def engaged_probe(model: KneeModel, data: MeasuredData, theta: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """(the probe's parameter vector, the groups it engaged): ``theta`` with every grouped ligament
    slack in every trial engaged to :data:`ENGAGE_STRAIN` (module docstring)."""
    solver = forward_solver(model)
    probe, engaged = theta.copy(), []
    for _ in range(3):  # the poses move with the engaged groups: a few passes settle them
        solutions = [s for s in solver.solve(data.trials, probe) if s.converged]
        moved = False
        for element in model.elements:
            offset = f"{element.name}.ref_strain_offset"
            column = f"{element.name}_strain_pct"
            if offset not in model.parameter_names or not solutions or column not in solutions[0].outputs:
                continue
            most = max(s.outputs[column] for s in solutions)
            if most < ENGAGE_STRAIN / 2 and (most < 0 or element.name in engaged):
                i = model.index(offset)
                hi = model.parameter(offset).bounds[1]
                probe[i] = min(hi, probe[i] + (ENGAGE_STRAIN - most) * (1 + probe[i]))
                moved = True
                if element.name not in engaged:
                    engaged.append(element.name)
        if not moved:
            break
    return probe, engaged


def calibration_free(model: KneeModel, data: MeasuredData, theta: np.ndarray | None = None,
                     pivot_tolerance: float | None = None) -> tuple[list[str], list[str]]:
    """(parameters to fit, ligament parameters left fixed): the registration and the ligament
    parameters the trials determine at ``theta`` (default: the knee's values; see
    :func:`engaged_probe`): those whose pivot is at least ``pivot_tolerance`` (default
    :data:`PIVOT_TOLERANCE`) of the largest."""
    pivot_tolerance = PIVOT_TOLERANCE if pivot_tolerance is None else pivot_tolerance
    candidates = default_free(model)
    names = [*REGISTRATION, *candidates]
    problem = IdentificationProblem.from_data(model, data, names)
    theta = model.theta() if theta is None else theta
    solutions = forward_solver(model).solve(data.trials, theta)
    ok = np.array([s.converged for s in solutions])
    q = np.array([s.q for s in solutions])
    S = problem.sensitivities(q, theta, names)  # (T * 5) x n, mm or deg per SI unit
    rows = np.repeat(ok, 5)
    scaled = S[rows] * np.array([model.parameter(n).scale for n in names])
    _, R, piv = scipy.linalg.qr(scaled, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    keep = {names[piv[i]] for i in range(len(diag)) if diag[i] >= pivot_tolerance * diag[0]}
    free = [*REGISTRATION, *[n for n in candidates if n in keep]]
    return free, [n for n in candidates if n not in keep]


def also_free_names(model: KneeModel, names: list[str]) -> list[str]:
    """Model parameters named by ``names``: parameter names, effect names for all of an effect's
    parameters (``PCLal_femoral_attachment`` is ``PCLal.femur_anterior``, ``.femur_proximal``,
    ``.femur_lateral``) or element names for all of an element's (``tibial_origin``); an unknown
    name is an :class:`InputError` listing the effects and elements.  In the model's order, whatever
    the order named: the reduced-space fit stops within the mesh contact's cost noise, at a point
    that depends on the order of its unknowns (S192803: sum of squares 113-117 for two orders of the
    same six effects), and the same names must give the same calibration."""
    return named_parameters(model, names, "--also-free")


def from_params(model: KneeModel, params: Parameters, **given) -> tuple[list[str], dict, dict, dict[str, str]]:
    """(free, priors, start, ties) of a calibration given ``params``: its varied parameters, their
    priors (None: none), the varied values that differ from the knee's (the start there) and its
    ties; refused beside any of ``given`` (:meth:`~kneenlp.model.params.Parameters.checked_against`),
    or with a fixed value other than the knee's (a calibration starts from the knee's parameter
    file: put it there)."""
    moved = params.checked_against(model, given)
    fixed = [n for n in moved if not params[n].vary]
    if fixed:
        raise InputError(f"{fixed[0]} is fixed at another value than the knee's: a calibration starts from the "
                         "knee's parameter file; put the value there (--parameters, Knee.with_parameters)",
                         field=f"parameters.{fixed[0]}")
    return params.free, params.priors(), moved, params.ties()


def check_calibration(data: MeasuredData, options: CalibrationOptions) -> None:
    """Refuse options that contradict each other, and data without a load (:func:`calibrate`)."""
    free, pivot_tolerance, also_free = options.free, options.pivot_tolerance, options.also_free
    if free is not None and pivot_tolerance is not None:
        raise InputError("chooses what the calibration fits, --free names it: give one", field="--pivot-tolerance")
    if free is not None and also_free:
        raise InputError("adds to what the calibration chooses, --free names it all: give one", field="--also-free")
    if all(t.dominant == "none" for t in data.trials):
        raise InputError(f"every trial of {data.source or 'the data'} is unloaded: laxity under load is what "
                         "determines the ligaments", field="data")


def calibration_choice(model: KneeModel, data: MeasuredData, options: CalibrationOptions, probe: np.ndarray,
                       engaged: list[str]) -> tuple[list[str], list[str]]:
    """(parameters to fit, parameters left at the knee's values) of :func:`calibrate`: a user's
    ``free`` (of the ``options``) as given, else the parameter table's ``free = true`` entries, else the
    calibration's choice: with priors every ligament parameter (unless ``pivot_tolerance``), without
    them those the trials determine at the ``probe`` (:func:`calibration_free`) and the offsets of the
    ``engaged`` groups; the load point for joint loads (``load_point``); less what the table declares
    fixed."""
    free, pivot_tolerance = options.free, options.pivot_tolerance
    declared = declared_free(model, [])  # the parameter table's free = true entries, if any
    if free is None and declared:
        free = declared
    if free is not None:  # a user's --free (or the table's) is kept as given
        return free, []
    fixed: list[str] = []
    if options.with_priors and pivot_tolerance is None:
        free = [*REGISTRATION, *default_free(model)]
    else:
        free, fixed = calibration_free(model, data, probe, pivot_tolerance)
        # an engaged group's offset is always fitted: the data, not the probe, decide how taut it is
        offsets = [f"{g}.ref_strain_offset" for g in engaged]
        free += [n for n in offsets if n not in free]
        fixed = [n for n in fixed if n not in offsets]
    if options.load_point and any(t.axes == "jcs" for t in data.trials):
        free = [*free, LOAD_POINT]
    # less what the parameter table declares fixed (free = false); in the model's order, as a parameter
    # table's (the fit's path, and so its local minimum, depends on the order)
    kept = declared_free(model, free)
    return sorted(kept, key=model.index), fixed + [n for n in free if n not in kept]


def engaged_priors(model: KneeModel, probe: np.ndarray, engaged: list[str], free: list[str]) -> dict[str, Prior]:
    """The priors of the reference-strain offsets of the groups the probe engaged
    (:func:`engaged_probe`), centred on the probe's value instead of the knee's: a group slack in
    every trial of a laxity experiment is the import's artefact (S192803: the FE model's slack
    lengths were set with deformable cartilage, and leave the cruciates and collaterals slack on
    rigid bones), not knowledge that it is slack; the probe's 2 % of toe strain in its most
    stretching trial is the prior's mean, with the kind's width."""
    out = {}
    for group in engaged:
        name = f"{group}.ref_strain_offset"
        if name in free:
            value = float(probe[model.index(name)])
            out[name] = dataclasses.replace(model.parameter(name).default_prior(value), source="engaged probe")
    return out
