"""An Abaqus knee's ligament fibres: each ``CONN3D2`` connector's ends and its ``*CONNECTOR
ELASTICITY`` table as kneenlp's toe-linear law (:class:`FibreLaw`), the FE parameters it
depends on (``*PARAMETER``) and how a group's slack moves as one (:func:`group_shift`).
:mod:`kneenlp.io.import_abaqus` builds the knee from them; :mod:`kneenlp.io.export_abaqus` writes
calibrated values back."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from kneenlp.base.errors import InputError
from kneenlp.io.abaqus import evaluate_parameters, nodes, read_keywords, substitute
from kneenlp.model.parameters import KINDS

#: Reference nodes of the bones in ``LIGS-ATTACH.inp``.
BONE_NODES = {1900000: "femur", 1200000: "tibia"}


@dataclass(frozen=True)
class FibreLaw:
    """kneenlp's toe-linear law of one fibre (SI): slack length (m), stiffness (N per unit strain),
    linear strain limit; and the table it came from (mm, N)."""

    slack_length: float
    stiffness: float
    lin_strain: float
    table: np.ndarray  # (n, 2): force (N), change of length D (mm)
    length: float  # fibre length in the imaged model (m)


def fibre_law(table: np.ndarray, length_mm: float, source: str, name: str) -> FibreLaw:
    """The toe-linear law of a fibre of length ``length_mm`` in the imaged model from its
    ``*CONNECTOR ELASTICITY`` table (force N, change of length mm; see module docstring)."""
    table = np.asarray(table, float)
    F, D = table[:, 0], table[:, 1]
    if np.any(np.diff(D) <= 0):
        raise InputError(f"connector table of {name} is not ordered by length change", source=source, field=name)
    zero = np.flatnonzero(F == 0)
    if len(zero) == 0 or len(zero) == len(F):
        raise InputError(f"connector table of {name} has no slack point (F = 0) or no tension", source=source,
                         field=name)
    d0 = D[zero[-1]]
    loaded = D > d0
    d_l, f_l = D[loaded], F[loaded]
    if len(d_l) < 3:
        raise InputError(f"connector table of {name} has fewer than three loaded points", source=source, field=name)
    slope = (f_l[-1] - f_l[-2]) / (d_l[-1] - d_l[-2])
    # the toe ends where the quadratic and the line meet with equal slope: F = slope (D - D0)^2 / (2 t)
    # on the toe (t = its length), F = slope (D - D0 - t / 2) beyond; the line through the last two
    # points gives t from its intercept
    intercept = d_l[-1] - f_l[-1] / slope  # D where the linear part is zero: D0 + t / 2
    toe = 2 * (intercept - d0)
    slack = length_mm + d0
    if toe <= 0 or slack <= 0:
        raise InputError(f"connector table of {name} is not a toe + linear law (toe length {toe:.3g} mm, slack "
                         f"length {slack:.3g} mm)", source=source, field=name)
    law = FibreLaw(slack * 1e-3, slope * slack, toe / (2 * slack), table, length_mm * 1e-3)
    worst = float(np.max(np.abs(law_force(law, D) - F)) / max(np.max(np.abs(F)), 1e-12))
    if worst > 1e-9:
        raise InputError(f"connector table of {name} is not a toe + linear law (kneenlp's law misses a tabulated "
                         f"force by {worst:.2g} of the largest)", source=source, field=name)
    return law


def law_force(law: FibreLaw, change_mm: np.ndarray) -> np.ndarray:
    """Force (N) of kneenlp's law for a fibre at change of length ``change_mm`` from its imaged
    length (the table's abscissa): Eq. (1) of :mod:`kneenlp.model.ligament` with the law's values."""
    from kneenlp.model.ligament import force_strain_numpy

    length = law.length + np.asarray(change_mm, float) * 1e-3
    return force_strain_numpy(length / law.slack_length - 1, law.stiffness, law.lin_strain)


def table_force(law: FibreLaw, change_mm: np.ndarray) -> np.ndarray:
    """Force (N) of the Abaqus table itself: linear interpolation between its points, constant
    beyond its ends (Abaqus's default extrapolation for connector behaviour)."""
    return np.interp(change_mm, law.table[:, 1], law.table[:, 0])


@dataclass
class Fibre:
    group: str
    name: str
    femur: np.ndarray  # model coordinates, mm
    tibia: np.ndarray
    law: FibreLaw


def parameter_file(folder: Path) -> Path:
    """The one ``LIG-PARAMETERS*.inp`` of a model's ligament folder."""
    params_files = sorted(folder.glob("LIG-PARAMETERS*.inp"))
    if len(params_files) != 1:
        raise InputError(f"expected one LIG-PARAMETERS*.inp, found {len(params_files)}", source=str(folder))
    return params_files[0]


def parameter_values(folder: Path) -> dict[str, float]:
    """The ``*PARAMETER`` values of a model's ligament folder: ``LIG-PARAMETERS*.inp``'s, and each
    ``PROPS-*.inp``'s own evaluated on top of them (as :func:`connector_tables` reads each file)."""
    params = parameter_file(folder)
    base = evaluate_parameters(read_keywords(params), source=str(params))
    values = dict(base)
    for props in sorted(folder.glob("PROPS-*.inp")):
        values.update(evaluate_parameters(read_keywords(props), base, str(props)))
    return values


def connector_tables(folder: Path, scale: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
    """Each connector section's elasticity table (force N, change of length mm) by its element set
    (upper case): the ``PROPS-*.inp`` tables with the parameters of ``LIG-PARAMETERS*.inp`` and of
    the ``PROPS`` file itself evaluated in order; ``scale`` multiplies named parameters where they
    are assigned (:func:`dependencies`)."""
    params = parameter_file(folder)
    values = evaluate_parameters(read_keywords(params), source=str(params), scale=scale)
    tables: dict[str, np.ndarray] = {}
    for props in sorted(folder.glob("PROPS-*.inp")):
        behaviours: dict[str, np.ndarray] = {}
        sections: dict[str, str] = {}
        current = None
        local = dict(values)
        for kw in read_keywords(props):
            if kw.name == "PARAMETER":
                local = evaluate_parameters([kw], local, str(props), scale=scale)
            elif kw.name == "CONNECTOR SECTION":
                sections[kw.options.get("ELSET", "").upper()] = kw.options.get("BEHAVIOR", "").upper()
            elif kw.name == "CONNECTOR BEHAVIOR":
                current = kw.options.get("NAME", "").upper()
            elif kw.name == "CONNECTOR ELASTICITY" and current and kw.options.get("COMPONENT", "1") == "1":
                behaviours[current] = np.array([[substitute(v, local, str(props)) for v in row[:2]]
                                                for row in kw.data])
        for elset, behaviour in sections.items():
            if behaviour not in behaviours:
                raise InputError(f"connector section {elset} names behaviour {behaviour}, which has no elasticity "
                                 "table", source=str(props), field=elset)
            tables[elset] = behaviours[behaviour]
    return tables


def assignments(path: Path) -> dict[str, str]:
    """The ``*PARAMETER`` assignments of a file as written (name -> right-hand side; the last one
    where a name is assigned twice)."""
    out = {}
    for kw in read_keywords(path):
        if kw.name == "PARAMETER":
            for row in kw.data:
                target, eq, expr = ",".join(row).partition("=")
                if eq:
                    out[target.strip()] = expr.strip()
    return out


#: The FE parameters of a group's law a calibration writes back (by the names' endings, as the
#: model's files document them): its length in the imaged model, its reference strain + 1 (L / L0),
#: its linear stiffness (N/mm) and its number of parallel fibres.
FE_LAW_PARAMETERS = ("_L", "_EREF", "_K2", "_NUM_SP_PAR")


def dependencies(folder: Path) -> dict[str, dict[str, list[str]]]:
    """For each connector element set (upper case), the names of :data:`FE_LAW_PARAMETERS` its
    table depends on, by ending: every such parameter assigned in the ligament files is perturbed
    in turn and the tables that change are its dependants (what the files compute, including a
    name assigned again in between, as ``PROPS-MCL`` does with ``MCL_L0``)."""
    names = []
    for path in [parameter_file(folder), *sorted(folder.glob("PROPS-*.inp"))]:
        names += [n for n in assignments(path) if n.upper().endswith(FE_LAW_PARAMETERS) and n not in names]
    base = connector_tables(folder)
    out: dict[str, dict[str, list[str]]] = {elset: {} for elset in base}
    for name in names:
        moved = connector_tables(folder, {name: 1 + 1e-6})
        for elset, table in base.items():
            if not np.array_equal(moved[elset], table):
                ending = next(e for e in FE_LAW_PARAMETERS if name.upper().endswith(e))
                out[elset].setdefault(ending, []).append(name)
    return out


def group_shift(folder: Path, fibres: list[Fibre]) -> tuple[dict[str, dict[str, float]], list[str]]:
    """``{group: {"length": L (mm), "ref_strain": EREF - 1 (%)}}`` for every group whose fibres'
    slack lengths are their imaged lengths ``+ L / EREF - L`` (to 1e-9 of ``L``) with its own ``L``
    and ``EREF`` parameters: its calibration then writes back exactly
    (:class:`kneenlp.model.ligament.SlackShift`); and a note for each group that is not so."""
    values = parameter_values(folder)
    deps = dependencies(folder)
    shifts, notes = {}, []
    for group in dict.fromkeys(f.group for f in fibres):
        elset = next(e for e in (group.upper() + "_1D", group.upper()) if e in deps)
        length, eref = (deps[elset].get(e, []) for e in ("_L", "_EREF"))
        if len(length) != 1 or len(eref) != 1 or length[0] not in values or eref[0] not in values:
            notes.append(f"{group}: no single _L and _EREF parameter in the parameter file: its fibres' slack lengths "
                         "move each by its own strain, and export-abaqus cannot write its reference strain")
            continue
        L, E = values[length[0]], values[eref[0]]
        if not all(abs(f.law.slack_length * 1e3 - (f.law.length * 1e3 + L / E - L)) <= 1e-9 * L
                   for f in fibres if f.group == group):
            notes.append(f"{group}: its fibres are not slack at their imaged length + {length[0]} / {eref[0]} - "
                         f"{length[0]} (fibres in series?): each moves by its own strain")
            continue
        shifts[group] = {"length": L, "ref_strain": (E - 1) * KINDS["ref_strain"].to_user}
    return shifts, notes


def read_fibres(folder: Path) -> list[Fibre]:
    src = str(folder)
    attach_file = folder / "LIGS-ATTACH.inp"
    bone_of: dict[int, str] = {}
    for kw in read_keywords(attach_file):
        if kw.name == "ELEMENT":
            for row in kw.data:
                if len(row) >= 3 and int(row[2]) in BONE_NODES:
                    bone_of[int(row[1])] = BONE_NODES[int(row[2])]
    tables = connector_tables(folder)
    fibres = []
    for lig_file in sorted(folder.glob("LIG-*.inp")):
        if lig_file.name.upper().startswith("LIG-PARAMETERS"):
            continue
        kws = read_keywords(lig_file)
        pts = nodes(kws, str(lig_file))
        for kw in kws:
            if kw.name != "ELEMENT" or kw.options.get("TYPE", "").upper() != "CONN3D2":
                continue
            elset = kw.options.get("ELSET", "")
            group = elset[:-3] if elset.upper().endswith("_1D") else elset
            if elset.upper() not in tables:
                raise InputError(f"fibres of {elset} have no connector law in PROPS-*.inp", source=str(lig_file),
                                 field=elset)
            for row in kw.data:
                eid, a, b = (int(v) for v in row[:3])
                undefined = [n for n in (a, b) if n not in pts]
                if undefined:
                    raise InputError(f"fibre {eid} of {elset} ends at node {undefined[0]}, which no *NODE of the file "
                                     "defines", source=str(lig_file), field=str(eid))
                ends = {bone_of.get(a): a, bone_of.get(b): b}
                if set(ends) != {"femur", "tibia"}:
                    raise InputError(f"fibre {eid} of {elset}: LIGS-ATTACH.inp does not fix one end to the femur and "
                                     "the other to the tibia", source=str(attach_file), field=str(eid))
                femur, tibia = pts[ends["femur"]], pts[ends["tibia"]]
                length = float(np.linalg.norm(femur - tibia))
                law = fibre_law(tables[elset.upper()], length, str(lig_file), f"{elset} fibre {eid}")
                fibres.append(Fibre(group, f"{group}_{eid}", femur, tibia, law))
    if not fibres:
        raise InputError("no ligament fibres (CONN3D2 elements in LIG-*.inp)", source=src)
    with_fibres = {f.group.upper() + "_1D" for f in fibres} | {f.group.upper() for f in fibres}
    empty = sorted(s for s in tables if s not in with_fibres)
    if empty:
        raise InputError(f"connector section {empty[0]} has a law but no fibres (CONN3D2 elements) in LIG-*.inp: "
                         "a ligament would disappear", source=src, field=empty[0])
    return fibres


def check_fibre_bones(fibres: list[Fibre], femur_bone: np.ndarray, tibia_bone: np.ndarray, attach_file: Path) -> None:
    """Each fibre joins the bones it is fixed to: its femoral end nearer the femur's bone than the
    tibia's, its tibial end the other way round (the S192803 deposit: 30 of 31 fibres, the femoral
    ends a median 3.4 mm from the femur and 31 mm from the tibia).  When most fibres have both ends
    on the other bone, the femur and tibia reference nodes of ``LIGS-ATTACH.inp`` were swapped."""
    femur, tibia = cKDTree(femur_bone), cKDTree(tibia_bone)
    ends_f, ends_t = np.array([f.femur for f in fibres]), np.array([f.tibia for f in fibres])
    swapped = (tibia.query(ends_f)[0] < femur.query(ends_f)[0]) & (femur.query(ends_t)[0] < tibia.query(ends_t)[0])
    if 2 * swapped.sum() > len(fibres):
        raise InputError(f"{swapped.sum()} of {len(fibres)} fibres have their femoral end on the tibia's bone and "
                         "their tibial end on the femur's: are the femur and tibia reference nodes "
                         f"({', '.join(f'{n} {b}' for n, b in BONE_NODES.items())}) swapped?", source=str(attach_file),
                         field="ELEMENT")
