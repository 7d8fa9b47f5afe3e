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

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w
import trimesh

from kneenlp.base.atomic import export_mesh_atomic, write_text_atomic
from kneenlp.base.conventions import COORDINATES, coords_to_user
from kneenlp.base.errors import InputError
from kneenlp.io.abaqus import nodes, read_keywords, read_mesh, triangles
from kneenlp.io.abaqus_fibres import Fibre, check_fibre_bones, group_shift, read_fibres
from kneenlp.model.kinematics import joint_coordinates
from kneenlp.model.parameters import KINDS, imported_parameter_set

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
