"""A knee from its Abaqus finite-element model: cartilage surfaces, ligament fibres, Grood-Suntay frames.

``kneenlp import-abaqus DIR --out KNEE_DIR`` (:func:`import_abaqus`) reads a knee model laid out
as the S192803 deposit (Andreassen et al.; ``../shared/data/du-s192803``):

* ``geometry/``: the femoral cartilage solid (hexahedra) and the tibial cartilage solids
  (tetrahedra, element sets ``CART-TIBIA-MED`` and ``CART-TIBIA-LAT``), the surface definitions
  ``SURF-CART-FEMUR-ART``, ``SURF-CART-TIBIA-MED``, ``SURF-CART-TIBIA-LAT`` (the exterior of each
  solid, the surfaces the FE contact uses), and the tibia's bone (for the tuberosity);
* ``ligaments/``: every fibre (``CONN3D2`` connector) of ``LIG-*.inp`` grouped by its element set as
  the source names it (``ACLam_1D`` -> group ``ACLam``), its bone from ``LIGS-ATTACH.inp``
  (1900000 femur, 1200000 tibia), its force-length law from the ``*CONNECTOR ELASTICITY`` table
  of ``PROPS-*.inp`` with the ``*PARAMETER`` values of ``LIG-PARAMETERS-*.inp``;
* ``frames/GS_KIN_AXES.inp``: the Grood-Suntay frames (origin, medial-lateral, anterior-posterior
  and superior-inferior points of femur and tibia).

What the knee file then holds (millimetres; decisions documented in ``docs/real-experiment.md``):

* femoral points in the file's femoral frame and tibial points in its tibial frame, axes X = the
  anterior-posterior axis, Y = superior-inferior, Z = medial-lateral (the frames' points; for a
  left knee the medial-lateral axis points medially and ``side = "left"`` mirrors it into kneenlp's
  right-knee convention), so that kneenlp's Grood-Suntay coordinates are the file's;
* ``[reference_pose]``: the pose of the tibial frame in the femoral frame in which the model was
  imaged (kneenlp's coordinates and signs, :func:`kneenlp.model.kinematics.joint_coordinates`);
* the femoral articular surface: the exterior of the femoral cartilage solid (closed); the tibial
  surfaces: the exterior faces of each tibial solid that face the femur (outward normal within
  :data:`TIBIAL_FACING_DEG` of the tibial proximal axis);
* one ``[ligaments.<GROUP>]`` per connector element set, one bundle per fibre, with kneenlp's law
  converted exactly from the table (:func:`fibre_law`).

The fibre law.  The table gives force ``F(D)`` against the connector's change of length ``D`` from
its length ``l_i`` in the imaged model: zero up to ``D0``, ``F = c (D - D0)^2`` on the toe up to
``D4``, then linear with slope ``K`` (N/mm per fibre).  That is kneenlp's toe-linear law
(:mod:`kneenlp.model.ligament`) with slack length ``s = l_i + D0``, stiffness ``k = K s`` (N per unit
strain) and linear strain limit ``eps_l = (D4 - D0) / (2 s)``, exactly at every tabulated point
(:func:`check_fibre_law`, tested to 1e-9).  Between the tabulated toe points Abaqus interpolates
linearly, kneenlp keeps the quadratic: they differ by at most ``K (D4 - D0)^2 / 64 / ...``, a chord
error of at most 1/16 of the toe's end force over each quarter of the toe.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w
import trimesh
from scipy.spatial import cKDTree

from kneenlp.base.atomic import export_mesh_atomic, write_text_atomic
from kneenlp.base.conventions import COORDINATES, coords_to_user
from kneenlp.base.errors import InputError
from kneenlp.io.abaqus import evaluate_parameters, nodes, read_keywords, read_mesh, substitute, triangles
from kneenlp.model.kinematics import joint_coordinates
from kneenlp.model.parameters import KINDS, imported_parameter_set

#: Reference nodes of the bones in ``LIGS-ATTACH.inp``.
BONE_NODES = {1900000: "femur", 1200000: "tibia"}
#: A tibial exterior face is articular if its outward normal is within this angle of the tibial
#: proximal axis (deg): the plateaus' upper surfaces, not their sides and undersides.
TIBIAL_FACING_DEG = 70.0
#: The tuberosity: the most anterior point of the tibial bone in this band below the tibial origin
#: (mm) and within this distance of the sagittal plane (mm).
#: Width of the contact gate (mm) of an imported knee.  Its plateaus are sampled at 1 mm (the solids'
#: faces, refined: :data:`~kneenlp.model.articular.SAMPLE_EDGE`), where the gap between neighbouring
#: points at a patch's edge is ~0.1 mm; a 0.01 mm gate starts each point's force so abruptly that
#: S192803's calibration had neighbouring minima 0.013 prior sd apart (2.8e-7 in objective), found
#: or not by the last digits of a path; with 0.05 mm its global search keeps one minimum to 1e-11
#: (``benchmarks/bench_global.py``).
GATE_MM = 0.05
TUBEROSITY_BAND_MM = (20.0, 45.0)
TUBEROSITY_HALF_WIDTH_MM = 15.0

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


@dataclass
class AbaqusKnee:
    """What :func:`read_abaqus_knee` read (model coordinates, mm)."""

    femur_frame: tuple[np.ndarray, np.ndarray]  # rotation (rows: AP, SI, ML axes), origin
    tibia_frame: tuple[np.ndarray, np.ndarray]
    femur_surface: trimesh.Trimesh
    tibia_surfaces: dict[str, trimesh.Trimesh]
    fibres: list[Fibre]
    tuberosity: np.ndarray
    notes: list[str] = field(default_factory=list)
    #: each group's FE length and reference strain (mm, %) where its slack moves as one
    #: (:func:`group_shift`)
    shifts: dict[str, dict[str, float]] = field(default_factory=dict)
    #: the bones' surfaces by bone (``femur``, ``tibia``; closed), to check attachments against
    bones: dict[str, trimesh.Trimesh] = field(default_factory=dict)


#: Largest angle (deg) a frame's axes may be from orthogonal: rounding in the file, made exact; more
#: is refused (orthonormalising a 20 deg skew moved S192803's reference internal rotation by 10 deg).
MAX_FRAME_SKEW = 1.0


def _frame(points: dict[int, np.ndarray], base: int, source: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Rotation (rows: anterior-posterior, superior-inferior, medial-lateral axes) and origin of a
    Grood-Suntay frame given by its origin (``base + 1``) and axis points (``+2`` ML, ``+3`` AP,
    ``+4`` SI); the axes made exactly orthonormal (the nearest rotation), with how far off they were."""
    need = [base + i for i in (1, 2, 3, 4)]
    missing = [n for n in need if n not in points]
    if missing:
        raise InputError(f"frame node {missing[0]} missing", source=source, field="*NODE")
    for n in need:
        if np.shape(points[n]) != (3,):
            raise InputError(f"frame node {n} has {np.size(points[n])} coordinates, expected 3", source=source,
                             field="*NODE")
    o = points[need[0]]
    raw = np.vstack([points[need[2]] - o, points[need[3]] - o, points[need[1]] - o])
    length = np.linalg.norm(raw, axis=1, keepdims=True)
    for n, size in zip((need[2], need[3], need[1]), length.ravel(), strict=True):
        if not size > 1e-9:
            raise InputError(f"frame {base}: axis point {n} is the origin {need[0]}: no axis", source=source,
                             field="*NODE")
    raw = raw / length
    u, _, vt = np.linalg.svd(raw)
    rot = u @ vt
    if np.linalg.det(rot) < 0:
        raise InputError(f"frame {base}: the ML, AP and SI axes are not right-handed", source=source,
                         field="*NODE")
    off = float(np.degrees(np.max(np.arccos(np.clip(np.sum(rot * raw, axis=1), -1, 1)))))
    if off > MAX_FRAME_SKEW:
        raise InputError(f"frame {base}: its axes are {off:.1f} deg from orthogonal (at most {MAX_FRAME_SKEW:g} "
                         "deg is taken as rounding): which axis is meant is not clear", source=source, field="*NODE")
    return rot, o, off


def read_abaqus_knee(folder: str | Path) -> AbaqusKnee:
    """Read the FE model in ``folder`` (layout: module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("not a folder", source=str(folder))

    def one(sub: str, pattern: str) -> Path:
        hits = sorted((folder / sub).glob(pattern))
        if len(hits) != 1:
            raise InputError(f"expected one {sub}/{pattern}, found {len(hits)}", source=str(folder), field=sub)
        return hits[0]

    notes = []
    axes_file = one("frames", "GS_KIN_AXES.inp")
    frame_nodes = nodes(read_keywords(axes_file), str(axes_file))
    rf, of, off_f = _frame(frame_nodes, 1980000, str(axes_file))
    rt, ot, off_t = _frame(frame_nodes, 1280000, str(axes_file))
    notes.append(f"Grood-Suntay frames of {axes_file.name}: axes orthonormalised (at most {max(off_f, off_t):.3f} "
                 "deg moved)")
    # cartilage surfaces
    femur_file = one("geometry", "CART1-FEMUR*.inp")
    fmesh = read_mesh(femur_file)
    _check_millimetres(fmesh.points, str(femur_file))
    femur_surface = trimesh.Trimesh(fmesh.points, triangles(fmesh.faces("CART-FEMUR")), process=True)
    notes.append(f"femoral articular surface: exterior of the femoral cartilage solid ({femur_file.name}, "
                 f"{len(femur_surface.faces)} triangles, {femur_surface.area:.0f} mm^2, closed: "
                 f"{femur_surface.is_watertight})")
    tibia_file = one("geometry", "CART2-TIBIA*.inp")
    tmesh = read_mesh(tibia_file)
    tibia_surfaces = {}
    proximal = rt[1]
    for name, elset in (("medial", "CART-TIBIA-MED"), ("lateral", "CART-TIBIA-LAT")):
        faces = tmesh.faces(elset)
        p = tmesh.points[faces]
        normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        facing = normal @ proximal > np.cos(np.radians(TIBIAL_FACING_DEG))
        surf = trimesh.Trimesh(tmesh.points, faces[facing], process=True)
        surf.remove_unreferenced_vertices()
        tibia_surfaces[name] = surf
        notes.append(f"{name} tibial surface: the {int(facing.sum())} of {len(faces)} exterior faces of {elset} "
                     f"facing the femur ({surf.area:.0f} mm^2)")
    bone_file = one("geometry", "BONE2-TIBFIB*.inp")
    bone = read_mesh(bone_file)
    tuberosity = _tuberosity(bone.points, rt, ot, str(bone_file))
    notes.append(f"tibial tuberosity: the most anterior point of the tibial bone {TUBEROSITY_BAND_MM[0]:g}-"
                 f"{TUBEROSITY_BAND_MM[1]:g} mm below the tibial origin within {TUBEROSITY_HALF_WIDTH_MM:g} mm of "
                 "the sagittal plane")
    fibres = read_fibres(folder / "ligaments")
    bones = {}
    femur_bone = sorted((folder / "geometry").glob("BONE1-FEMUR*.inp"))
    if femur_bone:
        femur_mesh = read_mesh(femur_bone[0])
        bones["femur"] = bone_surface(femur_mesh)
        attach = folder / "ligaments" / "LIGS-ATTACH.inp"
        check_fibre_bones(fibres, femur_mesh.points, bone.points, attach)
    bones["tibia"] = bone_surface(bone)
    shifts, shift_notes = group_shift(folder / "ligaments", fibres)
    notes.append(f"{len(fibres)} ligament fibres in {len({f.group for f in fibres})} groups, laws from the "
                 f"connector tables; {len(shifts)} groups' slack moves by the FE's L / EREF")
    return AbaqusKnee((rf, of), (rt, ot), femur_surface, tibia_surfaces, fibres, tuberosity, notes + shift_notes,
                      shifts, bones)


#: Faces a bone's surface keeps in a written knee: it serves only the attachments' check (inside or
#: not, 2.5 mm deep), for which a 2-3 mm edge is fine and the package stays small.
BONE_FACES = 12_000


def bone_surface(mesh) -> trimesh.Trimesh:
    """A bone's triangulated surface (file coordinates) decimated to :data:`BONE_FACES`."""
    from fast_simplification import simplify

    surface = trimesh.Trimesh(mesh.points, triangles(next(iter(mesh.cells.values()))), process=True)
    if len(surface.faces) > BONE_FACES:
        vertices, faces = simplify(np.asarray(surface.vertices, np.float64), np.asarray(surface.faces, np.int64),
                                   target_count=BONE_FACES)
        surface = trimesh.Trimesh(vertices, faces, process=True)
    return surface


#: The femoral cartilage's extent (mm) of a human knee: far outside it the file is in other units.
FEMUR_EXTENT_MM = (20.0, 300.0)


def _check_millimetres(points: np.ndarray, source: str) -> None:
    """The model's lengths are millimetres: the femoral cartilage spans tens of them (checked first,
    so that a model in metres is named as such, not by what it breaks later)."""
    extent = float(np.ptp(np.asarray(points, float), axis=0).max()) if len(points) else 0.0
    lo, hi = FEMUR_EXTENT_MM
    if not lo <= extent <= hi:
        guess = " (metres?)" if extent < lo / 100 else ""
        raise InputError(f"the femoral cartilage spans {extent:g} length units{guess}; import-abaqus expects a "
                         f"model in mm ({lo:g}-{hi:g} mm)", source=source, field="*NODE")


def _tuberosity(points: np.ndarray, rt: np.ndarray, ot: np.ndarray, source: str) -> np.ndarray:
    local = (points - ot) @ rt.T  # tibial frame: X anterior, Y proximal, Z medial-lateral
    lo, hi = TUBEROSITY_BAND_MM
    band = (local[:, 1] <= -lo) & (local[:, 1] >= -hi) & (np.abs(local[:, 2]) <= TUBEROSITY_HALF_WIDTH_MM)
    if not band.any():
        raise InputError("no tibial bone below the tibial origin to place the tuberosity", source=source)
    return points[np.flatnonzero(band)[np.argmax(local[band, 0])]]


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


def _mirror(side: str) -> np.ndarray:
    return np.diag([1.0, 1.0, -1.0 if side == "left" else 1.0])


def reference_pose(model: AbaqusKnee, side: str) -> tuple[float, np.ndarray]:
    """kneenlp's flexion (rad) and coordinates (rad, m) of the imaged pose: the tibial frame in the
    femoral frame, in kneenlp's right-knee convention (a left knee mirrored)."""
    (rf, of), (rt, ot) = model.femur_frame, model.tibia_frame
    m = _mirror(side)
    return joint_coordinates(m @ rf @ rt.T @ m, m @ rf @ (ot - of) * 1e-3)


def import_abaqus(folder: str | Path, out: str | Path, *, side: str = "left", name: str = "imported",
                  description: str = "") -> Path:
    """Write a knee directory (``knee.toml``, ``parameters.toml``, ``meshes/*.stl``) for the FE model
    in ``folder``; returns the knee file."""
    if side not in ("left", "right"):
        raise InputError(f"side must be 'left' or 'right', got {side!r}", field="side")
    model = read_abaqus_knee(folder)
    out = Path(out)
    (out / "meshes").mkdir(parents=True, exist_ok=True)
    (rf, of), (rt, ot) = model.femur_frame, model.tibia_frame

    def fem(x):
        return (np.asarray(x) - of) @ rf.T

    def tib(x):
        return (np.asarray(x) - ot) @ rt.T

    femur = model.femur_surface.copy()
    femur.vertices = fem(femur.vertices)
    export_mesh_atomic(femur, out / "meshes" / "femur_cartilage.stl")
    for name_, surf in model.tibia_surfaces.items():
        s = surf.copy()
        s.vertices = tib(s.vertices)
        export_mesh_atomic(s, out / "meshes" / f"tibia_{name_}.stl")
    for bone, to_frame in (("femur", fem), ("tibia", tib)):
        if bone in model.bones:
            b = model.bones[bone].copy()
            b.vertices = to_frame(b.vertices)
            export_mesh_atomic(b, out / "meshes" / f"{bone}_bone.stl")
    flexion, q = reference_pose(model, side)
    q_user = coords_to_user(q)
    doc: dict = {
        "name": name,
        "description": description or f"imported from the Abaqus model in {Path(folder).name}",
        "side": side,
        "units": "mm",
        "coordinates": "femoral",
        "parameters": "parameters.toml",
        "reference_pose": {"flexion_deg": float(np.degrees(flexion)),
                           **{f"{c}_{u}": float(v) for c, u, v in zip(COORDINATES, ("deg", "deg", "mm", "mm", "mm"),
                                                                       q_user, strict=True)}},
        "landmarks": {"tibial_tuberosity": _round(tib(model.tuberosity))},
        "contact": {"femur": "meshes/femur_cartilage.stl", "gate": GATE_MM, "grid_spacing": 0.5,
                    "medial": {"tibia": "meshes/tibia_medial.stl"}, "lateral": {"tibia": "meshes/tibia_lateral.stl"}},
        **({"bones": {b: f"meshes/{b}_bone.stl" for b in model.bones}} if model.bones else {}),
        "ligaments": {},
    }
    for f in model.fibres:
        group = doc["ligaments"].setdefault(f.group, {"bundles": []})
        group["bundles"].append({
            "name": f.name, "femur": _round(fem(f.femur)), "tibia": _round(tib(f.tibia)),
            "stiffness": float(f.law.stiffness), "slack_length": float(f.law.slack_length * 1e3),
            "lin_strain": float(f.law.lin_strain * KINDS["lin_strain"].to_user)})
    for group, shift in model.shifts.items():
        doc["ligaments"][group]["slack_shift"] = shift
    header = ["kneenlp knee description, written by `kneenlp import-abaqus` (kneenlp.io.import_abaqus).",
              "Femoral points in the model's femoral Grood-Suntay frame, tibial points in its tibial frame",
              "(X anterior, Y proximal, Z the medial-lateral axis as the frames give it); mm.",
              "Bundles: stiffness N per unit strain, slack_length mm, lin_strain %.",
              "slack_shift: the group's FE length L (mm) and reference strain EREF - 1 (%): its reference-strain",
              "offset moves every fibre's slack by the same length, as the FE's EREF does.", *model.notes]
    text = "".join(f"# {h}\n" for h in header) + tomli_w.dumps(doc)
    knee_file = out / "knee.toml"
    write_text_atomic(out / "parameters.toml", imported_parameter_set(
        "an Abaqus model", "their own stiffness, slack length and linear strain limit"))
    write_text_atomic(knee_file, text)
    check_written(knee_file, folder, side)
    return knee_file


def check_written(knee_file: Path, folder: str | Path, side: str) -> None:
    """Read the written knee back with every check a knee file gets (the side against its
    collateral ligaments and plateaus, attachments against the bones): a left model imported as
    ``--side right``, or fibres whose ends sit on the wrong bones, stop here, the error naming the
    FE model (the knee is written to a staging folder that is then removed)."""
    from kneenlp.model.knee import Knee

    try:
        Knee.load(knee_file)
    except InputError as exc:
        message = exc.message.replace(f"(set side = '{'left' if side == 'right' else 'right'}')",
                                      f"(--side {'left' if side == 'right' else 'right'})")
        raise InputError(f"the knee imported from it fails its checks: {message}", source=str(folder),
                         field="--side" if exc.field == "side" else exc.field) from None


def _round(v: np.ndarray) -> list[float]:
    return [round(float(x), 6) for x in v]
