"""Calibrated ligaments back into the Abaqus model a knee was imported from.

``kneenlp export-abaqus CALIBRATION --knee KNEE --model MODEL_DIR --out OUT_DIR``
(:func:`export_abaqus`): ``OUT_DIR`` is a copy of the FE model in which only the numbers the
calibration changed are changed, so that the FE model runs as before with the calibrated
ligaments.  ``CALIBRATION`` is ``calibrated.toml`` (``identify --out``) or the fit's JSON
(``identify --json``).

What is written, per ligament group (a connector element set; the FE parameters each group's
table depends on are found by perturbing them, :func:`kneenlp.io.abaqus_fibres.dependencies`):

* its reference-strain offset ``d`` as ``EREF' = EREF + d`` in ``LIG-PARAMETERS*.inp``: the FE
  group's slack length ``L / EREF`` is what an imported knee's
  :class:`~kneenlp.model.ligament.SlackShift` moves, so the written group is the calibrated one
  exactly (toe and stiffness per length included);
* its stiffness scale ``s`` as ``K2' = s K2``, where every group that shares the ``K2`` has the
  same scale; otherwise (S192803's ``MCL_K2`` serves MCLa, MCLm and MCLp) as the group's own number
  of parallel fibres ``num_sp_par' = num_sp_par / s`` in its ``PROPS`` file (the table's forces
  are ``K2 / num_sp_par`` times the same lengths).

Everything else stays: the registration and the robot's load point belong to the experiment, not
to the FE model; an attachment shift would move the FE's nodes, and the contact is the FE's own
deformable cartilage.  They are reported with their values, not written.

Exact or refused: the written files are read back by the importer's own reader and every fibre's
force is compared with the calibrated knee's at lengths across its slack, toe and linear parts;
more than 1e-9 of the largest force apart refuses the export (so does a number that is written as
an expression in the file, a shared ``EREF`` with different offsets, or a scale <= 0).
"""

from __future__ import annotations

import json
import math
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.io.abaqus_fibres import (
    Fibre,
    assignments,
    dependencies,
    law_force,
    parameter_file,
    parameter_values,
    read_fibres,
)
from kneenlp.model.knee import Knee
from kneenlp.model.ligament import Bundle, Ligament, bundle_law, force_strain_numpy
from kneenlp.model.parameters import KINDS, ParameterSet

#: Largest force difference (share of the fibre's largest) between the written FE law and the
#: calibrated knee's at which the export is exact.
ROUND_TRIP_TOL = 1e-9
#: Strains (from each fibre's imaged length) at which the round trip compares forces.
ROUND_TRIP_STRAINS = np.linspace(-0.3, 0.3, 121)


def read_calibration(path: str | Path) -> dict[str, float]:
    """The parameter values (SI, by name) of ``calibrated.toml`` or of a fit's JSON (``params``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", source=str(path))
    if path.suffix.lower() == ".toml":
        return dict(ParameterSet.load(path).values)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the fit ({exc})", source=str(path)) from None
    params = doc.get("params") if isinstance(doc, dict) else None
    if not isinstance(params, dict) or not params:
        raise InputError("no 'params' object: expected the JSON of 'kneenlp identify --json' or calibrated.toml",
                         source=str(path), field="params")
    for name, value in params.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(f"expected a finite number, got {value!r}", source=str(path), field=f"params.{name}")
    return {k: float(v) for k, v in params.items()}


def checked_values(knee: Knee, path: str | Path) -> tuple[KneeModel, dict[str, float]]:
    """The knee's model and every parameter's calibrated value (SI): the knee's own values updated
    by the calibration in ``path``, whose names must all be the model's."""
    params = read_calibration(path)
    model = KneeModel.of(knee)
    known = model.parameter_names
    for name in params:
        if name not in known:
            raise unknown_name("parameter", name, known, source=str(path)).with_context(field=name)
    theta = model.theta(params)
    return model, {n: float(theta[model.index(n)]) for n in known}


@dataclass(frozen=True)
class Change:
    """One FE number written: its file (name), parameter, old and new value, and why."""

    file: str
    name: str
    old: float
    new: float
    why: str


@dataclass
class AbaqusExport:
    """What :func:`export_abaqus` wrote and left out."""

    out: Path
    changes: list[Change]
    #: the round trip's largest force difference, as a share of each fibre's largest force
    round_trip: float
    fibres: int
    #: ``(parameter, value in its user unit, unit, why not written)`` of every parameter the FE
    #: files do not hold that the calibration moved from neutral
    not_written: list[tuple[str, float, str, str]] = field(default_factory=list)

    def text(self) -> str:
        lines = [f"wrote {self.out}: the FE model with the calibrated ligaments"]
        if self.changes:
            lines.append("FE parameters changed (file: name old -> new):")
            lines += [f"  {c.file}: {c.name} {c.old:.10g} -> {c.new:.10g}  ({c.why})" for c in self.changes]
        else:
            lines.append("no FE parameter changed: the calibration keeps every group at the model's values")
        lines.append(f"round trip: the written files give every one of the {self.fibres} fibres the calibrated "
                     f"knee's force to {self.round_trip:.1e} of its largest (at {len(ROUND_TRIP_STRAINS)} lengths)")
        if self.not_written:
            lines.append("not written (not the FE model's ligament numbers):")
            lines += [f"  {n} = {v:.4g} {u}  ({why})" for n, v, u, why in self.not_written]
        return "\n".join(lines)


def _elset(group: str, deps: dict[str, dict[str, list[str]]], source: str) -> str:
    for name in (group.upper() + "_1D", group.upper()):
        if name in deps:
            return name
    raise InputError(f"the knee's ligament {group} has no connector section in the model's PROPS-*.inp: is the "
                     "knee imported from this model?", source=source, field=group)


def _one(deps: dict[str, list[str]], ending: str, group: str, source: str) -> str:
    names = deps.get(ending, [])
    if len(names) != 1:
        raise InputError(f"{group}'s connector law depends on {len(names)} parameters ending {ending} "
                         f"({', '.join(names) or 'none'}): export-abaqus writes one", source=source, field=group)
    return names[0]


def planned_changes(knee: Knee, values: dict[str, float], ligaments: Path) -> list[tuple[str, float, str]]:
    """``(FE parameter, new value, why)`` of the numbers that carry the calibrated ``values`` (SI)
    of the knee's groups into the model's ligament folder ``ligaments`` (module docstring)."""
    src = str(ligaments)
    deps = dependencies(ligaments)
    fe = parameter_values(ligaments)
    groups = {g: lig for g, lig in knee.ligaments.items() if lig.grouped}
    uses: dict[str, list[str]] = {}  # FE parameter -> the knee's groups whose table depends on it
    for g in groups:
        for names in deps[_elset(g, deps, src)].values():
            for n in names:
                uses.setdefault(n, []).append(g)
    plan: list[tuple[str, float, str]] = []
    model = _FeModel(src, deps, fe, uses)
    for g, lig in groups.items():
        offset, scale = values[f"{g}.ref_strain_offset"], values[f"{g}.k_scale"]
        own = deps[_elset(g, deps, src)]
        if offset != 0.0:
            plan += _reference_strain(model, g, lig, values)
        if scale != 1.0:
            if not scale > 0:
                raise InputError(f"{g}.k_scale is {scale:g}: an FE connector without stiffness has no table; remove "
                                 "the group's connectors from the FE model instead", field=f"{g}.k_scale")
            k2 = _one(own, "_K2", g, src)
            if all(values[f"{h}.k_scale"] == scale for h in uses[k2]):
                plan.append((k2, fe[k2] * scale, f"{', '.join(uses[k2])}.k_scale {scale:.6g}"))
            else:
                fibres = _one(own, "_NUM_SP_PAR", g, src)
                if uses[fibres] != [g]:
                    raise InputError(f"{k2} and {fibres} are shared by {', '.join(uses[fibres])} with different "
                                     "stiffness scales: no number of the model carries them", source=src, field=g)
                plan.append((fibres, fe[fibres] / scale, f"{g}.k_scale {scale:.6g}; {k2} is shared by "
                                                         f"{', '.join(uses[k2])}"))
    return list(dict.fromkeys(plan))


@dataclass(frozen=True)
class _FeModel:
    """What :func:`planned_changes` reads of the model's ligament folder ``src``: its parameters'
    dependencies per connector section (``deps``) and values (``fe``), and the knee's groups whose
    table depends on each parameter (``uses``)."""

    src: str
    deps: dict[str, dict[str, list[str]]]
    fe: dict[str, float]
    uses: dict[str, list[str]]


def _reference_strain(model: _FeModel, group: str, lig: Ligament,
                      values: dict[str, float]) -> list[tuple[str, float, str]]:
    """The ``EREF`` that carries the reference-strain offset of ``group`` (the knee's ligament
    ``lig``) among the calibrated ``values`` (SI; module docstring)."""
    src, fe, uses = model.src, model.fe, model.uses
    own = model.deps[_elset(group, model.deps, src)]
    eref, length = _one(own, "_EREF", group, src), _one(own, "_L", group, src)
    offset = values[f"{group}.ref_strain_offset"]
    shift = lig.shift
    if shift is None:
        raise InputError(f"{group} moves its fibres' slack each by its own strain (no slack_shift in the knee file): "
                         "re-import the FE model (import-abaqus) so that its offset is the FE's EREF",
                         field=f"{group}.ref_strain_offset")
    if (abs(shift.length * 1e3 - fe[length]) > 1e-9 * fe[length]
            or abs(1 + shift.ref_strain - fe[eref]) > 1e-9 * fe[eref]):
        raise InputError(f"the knee's {group}.slack_shift (L {shift.length * 1e3:.6g} mm, EREF "
                         f"{1 + shift.ref_strain:.6g}) is not the model's ({length} {fe[length]:.6g}, {eref} "
                         f"{fe[eref]:.6g}): is the knee imported from this model?", source=src, field=group)
    sharing = uses[eref]
    if any(values[f"{h}.ref_strain_offset"] != offset for h in sharing):
        raise InputError(f"{eref} is shared by {', '.join(sharing)} with different reference-strain offsets: no "
                         "number of the model carries them", source=src, field=group)
    return [(eref, 1 + (shift.ref_strain + offset),
             f"{', '.join(sharing)}.ref_strain_offset {offset * KINDS['ref_strain'].to_user:+.4g} %")]


def write_number(path: Path, name: str, value: float) -> float:
    """Replace the number assigned to ``name`` in ``path`` (every ``NAME = number`` line) by
    ``value``; returns the old number.  A name assigned by an expression is refused: the file's
    formulas are the FE user's, only its numbers are the calibration's."""
    text = path.read_text()
    pattern = re.compile(rf"^(\s*{re.escape(name)}\s*=\s*)([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)(\s*)$",
                         re.MULTILINE)
    found = pattern.findall(text)
    if not found:
        raise InputError(f"{name} is not assigned a plain number here (an expression?): export-abaqus changes numbers "
                         "only", source=str(path), field=name)
    path.write_text(pattern.sub(lambda m: f"{m.group(1)}{value!r}{m.group(3)}", text))
    return float(found[-1][1])


def round_trip(knee: Knee, values: dict[str, float], before: list[Fibre], after: list[Fibre]) -> float:
    """The largest difference, as a share of each fibre's largest force, between the forces of the
    written FE laws (``after``) and those of the calibrated knee (``values``, SI) at the fibres' own
    imaged lengths (``before``: the model's fibres; :data:`ROUND_TRIP_STRAINS`)."""
    written = {f.name: f for f in after}
    worst = 0.0
    for f in before:
        lig = knee.ligaments.get(f.group)
        g = written.get(f.name)
        if lig is None or g is None or not lig.grouped:
            raise InputError(f"fibre {f.name} is not in both the knee and the written model: is the knee imported "
                             "from this model?", field=f.name)
        imaged = f.law.length
        own = Bundle(f.femur, f.tibia, f.name, f.law.stiffness, imaged / f.law.slack_length - 1, f.law.lin_strain)
        group = (values[f"{f.group}.k_scale"], values[f"{f.group}.ref_strain_offset"])
        slack, k, lin = bundle_law(own, imaged, imaged, group, lig.shift)
        change = imaged * ROUND_TRIP_STRAINS
        expected = force_strain_numpy((imaged + change) / slack - 1, k, lin)
        got = law_force(g.law, change * 1e3)
        worst = max(worst, float(np.max(np.abs(got - expected)) / max(np.max(np.abs(expected)), 1e-12)))
    return worst


def not_written(model: KneeModel, values: dict[str, float]) -> list[tuple[str, float, str, str]]:
    """The calibrated parameters the FE model's ligament numbers do not hold, where the calibration
    moved them from the knee's own values: ``(name, value in its user unit, unit, why)``."""
    own = model.theta()
    experiment = {p.name for part in model.measurement.parts for p in part.parameters()}
    out = []
    for name in model.parameter_names:
        value = values[name]
        if name.endswith((".k_scale", ".ref_strain_offset")) or value == own[model.index(name)]:
            continue
        kind = KINDS[model.parameter(name).kind]
        why = ("the experiment's frames and loads, not the FE model's" if name in experiment
               else "an attachment shift: the FE's nodes would move by it" if name.split(".")[-1].startswith(
                   ("femur_", "tibia_")) else "not among the FE model's ligament numbers")
        out.append((name, value * kind.to_user, kind.unit, why))
    return out


def export_abaqus(calibration: str | Path, knee: Knee | str | Path, model: str | Path,
                  out: str | Path) -> AbaqusExport:
    """Write into the folder ``out`` a copy of the Abaqus model ``model`` (the folder ``knee`` was
    imported from) with the calibration ``calibration`` (``calibrated.toml`` or a fit's JSON) in its
    ligament numbers (module docstring); returns what was written and the round trip's check."""
    model, out = Path(model), Path(out)
    if not (model / "ligaments").is_dir():
        raise InputError("not an Abaqus model folder (no ligaments/)", source=str(model), field="--model")
    knee = knee if isinstance(knee, Knee) else Knee.load(knee)
    kneemodel, values = checked_values(knee, calibration)
    plan = planned_changes(knee, values, model / "ligaments")
    shutil.copytree(model, out, dirs_exist_ok=True)
    ligaments = out / "ligaments"
    homes = {n: p for p in [parameter_file(ligaments), *sorted(ligaments.glob("PROPS-*.inp"))] for n in assignments(p)}
    changes = []
    for name, new, why in plan:
        old = write_number(homes[name], name, new)
        changes.append(Change(homes[name].name, name, old, new, why))
    worst = round_trip(knee, values, read_fibres(model / "ligaments"), read_fibres(ligaments))
    if not worst <= ROUND_TRIP_TOL:
        raise InputError(f"the written model's fibre forces differ from the calibrated knee's by {worst:.2g} of their "
                         f"largest (exact means {ROUND_TRIP_TOL:g}): not written", source=str(model))
    return AbaqusExport(out, changes, worst, len(read_fibres(ligaments)), not_written(kneemodel, values))

