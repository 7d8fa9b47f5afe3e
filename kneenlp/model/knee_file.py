"""Knee files: the TOML reader that turns a knee file (meshes, attachments, landmarks, contact
settings, a parameter set) into the fields of a :class:`~kneenlp.model.knee.Knee`, in SI, with
every check a user's file needs (one-line errors naming the file and the field): the structure by
its schema (:mod:`kneenlp.model.knee_schema`), then the geometry against a knee's; where shipped
knees live (:func:`available_knees`, :func:`knee_file`, :func:`resolve_knee`).  The file format is
described in :mod:`kneenlp.model.knee` and docs/inputs.md."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from kneenlp.base.conventions import POSE_ENVELOPE_USER, coordinate_columns, coords_from_user
from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.resources import resource, shipped_knees
from kneenlp.base.schema import validated
from kneenlp.base.tomlfile import read_toml
from kneenlp.geometry.decimate import (
    MAX_MESH_FACES,
    MAX_READ_FACES,
    MAX_TEXT_MESH_BYTES,
    decimate,
    read_binary_stl,
)
from kneenlp.model.articular import (
    Compartment,
    mesh_path,
)
from kneenlp.model.frames import Frame
from kneenlp.model.kinematics import reference_transform
from kneenlp.model.knee_contact_file import ContactReading
from kneenlp.model.knee_ligament_file import NEAR_ORIGIN, LigamentReading
from kneenlp.model.knee_schema import knee_document
from kneenlp.model.ligament import Ligament
from kneenlp.model.parameters import LIGAMENT_KINDS, ParameterSet
from kneenlp.model.structures import structure_tables

#: Ligament names (prefixes, upper case) on the medial and the lateral side of the knee, the
#: evidence :meth:`KneeFile.check_side` weighs against the declared side.

#: Longest plausible ligament (m, attachment distance in the reference pose; the superficial MCL
#: is about 0.1 m): attachments further apart are a typo or mixed units.
MAX_LIGAMENT_LENGTH = 0.3
#: Deepest an attachment may lie inside a bone or cartilage mesh (m): attachments lie on the bone
#: surface, up to 1.2 mm inside the meshes of the shipped knees (s192803's posterior capsule in its
#: femoral cartilage solid); deeper is a slip (docs/inputs.md).
ATTACHMENT_DEPTH = 2.5e-3
#: Ligament names (prefixes, upper case) on the medial and the lateral side of the knee, the
#: evidence :meth:`KneeFile.check_side` weighs against the declared side.
MEDIAL_LIGAMENTS = ("MCL", "SMCL", "DMCL", "POL", "PMC")
LATERAL_LIGAMENTS = ("LCL", "FCL", "PFL", "ALS", "ALL")
#: The knee ``Knee.default()`` loads.
DEFAULT_KNEE = "default"
#: Plausible size of a knee (m): the largest extent of the tibial cartilage (human plateaus: 60-90
#: mm) must lie in this range, far enough from any real knee (a rabbit's to a horse's) that only a
#: unit slip (a knee 1000x too big or too small: ``units`` not matching the numbers) is caught.
KNEE_SIZE_RANGE = (5e-3, 0.5)
#: Plausible range (mm) of the contact lengths of a knee file: the gate (0.01 mm by default), the
#: cartilage on a bone surface and the distance field's grid.  A value outside is a unit slip (a
#: gate of 0.01 "mm" in a metre knee is 10 mm) or, for the grid, a field too coarse to represent
#: cartilage or too fine to fit in memory.
PLAUSIBLE_MM = {"gate": (1e-4, 0.1), "femur_offset": (0.0, 6.0), "grid_spacing": (0.05, 2.0),
                "wrap_radius": (0.5, 60.0), "wrap_clearance": (0.0, 5.0)}
#: Landmarks in the femur's frame (the others are the tibia's), and the two ends of the limb.
FEMORAL_LANDMARKS = ("hip_center", "medial_epicondyle", "lateral_epicondyle")
LIMB_LANDMARKS = ("hip_center", "ankle_center")
#: Distance (m) of the hip and ankle centres from the knee: femora and tibiae are 0.25-0.55 m long,
#: so closer is a point of the knee given as the hip (it would turn the frame), further a unit slip.
LIMB_REACH = (0.15, 1.0)
#: The landmarks kneenlp knows at the knee (any other name is the user's own and only kept).
KNEE_LANDMARKS = ("medial_epicondyle", "lateral_epicondyle", "tibial_tuberosity", "medial_plateau_edge",
                  "lateral_plateau_edge")
#: Furthest (m) any of them (epicondyles, tuberosity, plateau edges) lies from the knee.
KNEE_REACH = 0.15


def available_knees() -> list[str]:
    """Names of the knees shipped with the package."""
    return shipped_knees()


def knee_file(name: str = DEFAULT_KNEE) -> Path:
    """The knee TOML of a shipped knee (inside the installed package)."""
    if name not in available_knees():
        raise unknown_name("knee", name, available_knees())
    return resource("knees", name, "knee.toml")


def resolve_knee(path: str | Path) -> Path:
    """The knee file ``path`` names: a file as it is; a directory's ``knee.toml``; the name of a
    shipped knee where no such file or knee directory exists (a folder of that name elsewhere, e.g.
    one holding other outputs, does not hide the shipped knee)."""
    p = Path(path)
    if p.is_dir() and (p / "knee.toml").is_file():
        return p / "knee.toml"
    if str(path) in available_knees() and not p.is_file():
        return knee_file(str(path))
    if p.is_dir():
        raise InputError("a directory without knee.toml (give the knee file, or a shipped knee: "
                         f"{', '.join(available_knees())})", source=str(path))
    return p


def default_knee_file() -> Path:
    """The knee TOML of the embedded default knee."""
    return knee_file(DEFAULT_KNEE)


class KneeFile(ContactReading, LigamentReading):
    """One knee TOML being read: its document, units and the map into the femoral frame."""

    def __init__(self, path: Path):
        """Read ``path`` and check it against :func:`~kneenlp.model.knee_schema.knee_document`; the
        file's unit (``scale`` to m), side (``mirror``) and reference pose (rad, SI)."""
        self.path, self.src = path, str(path)
        doc = read_toml(path)
        units = doc.get("units", "mm") if isinstance(doc, dict) else "mm"
        #: the file checked against its schema (:func:`~kneenlp.model.knee_schema.knee_document`)
        self.spec = validated(knee_document(), doc, self.src, context={"units": units})
        self.units = self.spec.units
        self.scale = 1e-3 if self.units == "mm" else 1.0
        self.mirror = np.array([1.0, 1.0, -1.0 if self.spec.side == "left" else 1.0])
        self.coordinates = self.spec.coordinates
        self.frame = Frame.identity()
        self.notes: list[str] = []
        #: attachments read so far: (field, point in the femoral frame at the reference pose, bone)
        self.attachments: list[tuple[str, np.ndarray, str]] = []
        #: the bones' distance fields built so far for paths over them, by mesh file
        self.bone_fields: dict = {}
        self.reference_pose = self.read_reference_pose()
        self.reference = reference_transform(*self.reference_pose)

    def read_reference_pose(self) -> tuple[float, np.ndarray]:
        """``[reference_pose]``: the imaged pose of the tibial frame in the femoral frame, in kneenlp's
        coordinates and signs (deg, mm in the file; rad and SI returned), or zero (the frames coincide)."""
        pose = self.spec.reference_pose
        if pose is None:
            return 0.0, np.zeros(5)
        flexion = pose.flexion_deg
        q_user = np.array([getattr(pose, c) for c in coordinate_columns()])
        if np.any(np.abs(q_user) > POSE_ENVELOPE_USER) or not -30 <= flexion <= 120:
            raise InputError("beyond any knee pose (|rotations| <= 30/60 deg, |translations| <= 25 mm, flexion -30 "
                             "... 120 deg): mm and deg expected", source=self.src, field="reference_pose")
        return float(np.radians(flexion)), coords_from_user(q_user)

    def at_reference(self, tibial_points: np.ndarray) -> np.ndarray:
        """Tibial points (tibial frame) in the femoral frame at the reference pose."""
        R, p = self.reference
        return np.asarray(tibial_points, float) @ R.T + p

    # ------------------------------------------------------------------ raw values (scan, m, right knee)
    def raw_point(self, value: tuple[float, float, float]) -> np.ndarray:
        """A point of the file (its unit, its side) in scan coordinates: m, a left knee mirrored."""
        return np.array(value) * self.scale * self.mirror

    def length(self, given: float | None, key: str, default_mm: float, fld: str, positive: bool = True) -> float:
        """A length setting in the file's unit -> m (defaults are given in mm, whatever the unit),
        checked against :data:`PLAUSIBLE_MM` (a length written in the other unit is caught)."""
        if given is None:
            return default_mm * 1e-3
        value = given * self.scale
        if value < 0 or (positive and value == 0):
            raise InputError(f"must be {'> 0' if positive else '>= 0'}", source=self.src, field=fld)
        lo, hi = PLAUSIBLE_MM.get(key, (0.0, np.inf))
        if value and not lo <= value * 1e3 <= hi:
            raise InputError(f"{given!r} is {value * 1e3:.4g} mm in this file's unit ({self.units!r}); "
                             f"{key} is {lo:g}-{hi:g} mm (default {default_mm:g} mm): written in another unit?",
                             source=self.src, field=fld)
        return value

    def mesh(self, value: str, fld: str) -> trimesh.Trimesh:
        """A mesh named in the file, in scan coordinates (m, mirrored for a left knee), its size
        checked against :data:`KNEE_SIZE_RANGE` on its own (one mesh in the other unit is caught
        before any work, not only when the knee's overall size is)."""
        # the contact resolution: the distance field's grid (a femur decimated to twice it changed the
        # contact force by up to 3 %, to it by less than 1 %: benchmarks/bench_decimation.py)
        resolution = self.length(self.spec.contact.grid_spacing, "grid_spacing", 0.5, "contact.grid_spacing")
        mesh = read_mesh(mesh_path(self.path.parent, value, self.src, fld), self.scale, self.mirror,
                         field=fld, knee_file=self.src)
        self.check_extent(mesh.vertices, str(value), fld)
        mesh, note = decimate(mesh, resolution)
        if note:
            self.notes.append(f"{fld} ({value}): {note}")
        return mesh

    def point(self, value: tuple[float, float, float]) -> np.ndarray:
        """A point of the file in the femoral frame (m)."""
        return self.frame(self.raw_point(value))

    # ------------------------------------------------------------------ the knee
    def fields(self, parameters) -> dict:
        """The :class:`~kneenlp.model.knee.Knee` this file describes, as its constructor's keyword
        arguments (SI), with ``parameters`` (a parameter set or its file) replacing the file's own."""
        spec, src = self.spec, self.src
        raw_landmarks = {k: self.raw_point(v) for k, v in spec.landmarks.items()}
        geometry = self.contact(raw_landmarks)
        self.check_size(geometry["compartments"])
        landmarks = {k: self.frame(v) for k, v in raw_landmarks.items()}
        if "tibial_tuberosity" not in landmarks:
            raise InputError("missing (anterior/posterior loads act there)", source=src,
                             field="landmarks.tibial_tuberosity")
        ligaments = self.ligaments()
        self.check_side(ligaments, geometry["compartments"], landmarks)
        candidates = self.candidates()
        self.check_attachments(geometry | {"bones": self.bones()})
        params = self.parameter_set(parameters, ligaments)
        contact = spec.contact
        return dict(name=spec.name if spec.name is not None else self.path.stem, ligaments=ligaments,
                    compartments=geometry["compartments"], tuberosity=landmarks["tibial_tuberosity"],
                    parameters=params, gate=self.length(contact.gate, "gate", 0.01, "contact.gate"),
                    working_set=contact.working_set, landmarks=landmarks, source=src,
                    description=spec.description, candidates=candidates, femur=geometry["femur"],
                    axis=geometry["axis"], structures=self.structures(), notes=self.notes,
                    reference_pose=self.reference_pose, side=spec.side)

    def check_side(self, ligaments: dict[str, Ligament], compartments: dict[str, Compartment],
                   landmarks: dict[str, np.ndarray]) -> None:
        """The declared ``side`` against the geometry, in the model's frame (a right knee: Z lateral):
        the collateral ligaments (medial: MCL, POL; lateral: LCL, PFL, ALS/ALL, fibular side), the
        compartments the file names itself and the epicondyles.  A mirrored knee declared the other
        side puts each of them on the wrong side; one contradiction is an error naming it."""
        evidence = []  # (what, lateral-minus-medial z, m)
        z = {side: [float(np.mean([[b.femur[2], b.tibia[2]] for b in lig.bundles]))
                    for name, lig in ligaments.items() if name.upper().startswith(prefixes)]
             for side, prefixes in (("medial", MEDIAL_LIGAMENTS), ("lateral", LATERAL_LIGAMENTS))}
        if z["medial"] and z["lateral"]:
            evidence.append(("the lateral collateral ligaments (LCL ...) lie medial of the medial ones (MCL ...)",
                             np.mean(z["lateral"]) - np.mean(z["medial"])))
        elif z["medial"] or z["lateral"]:
            side = "medial" if z["medial"] else "lateral"
            evidence.append((f"the {side} collateral ligaments lie on the {'lateral' if side == 'medial' else 'medial'}"
                             " side", -np.mean(z[side]) if side == "medial" else np.mean(z[side])))
        named = {n for n, t in self.spec.contact.compartments().items() if t.tibia is not None}
        if named == {"medial", "lateral"}:
            evidence.append(("the file's lateral plateau ([contact.lateral]) lies medial of its medial one",
                             compartments["lateral"].points[:, 2].mean() - compartments["medial"].points[:, 2].mean()))
        if {"medial_epicondyle", "lateral_epicondyle"} <= set(landmarks):
            evidence.append(("the lateral epicondyle lies medial of the medial one",
                             landmarks["lateral_epicondyle"][2] - landmarks["medial_epicondyle"][2]))
        wrong = [what for what, dz in evidence if dz < 0]
        if wrong:
            side = self.spec.side
            other = "left" if side == "right" else "right"
            raise InputError(f"the knee is declared {side!r}, but {wrong[0]} once it is read as a {side} knee: "
                             f"is it a {other} knee? (set side = {other!r})", source=self.src, field="side")

    def check_landmarks(self, raw: dict[str, np.ndarray], tibia: list[np.ndarray]) -> None:
        """Landmarks (scan coordinates, m) against the knee's own size, before any fit uses them: the
        hip and ankle centres :data:`LIMB_REACH` from the knee (the tibial cartilage's centre at the
        reference pose), the :data:`KNEE_LANDMARKS` within :data:`KNEE_REACH` of it (a landmark of the
        user's own within the limb's reach) and, in a femoral-frame file, none of those within
        :data:`NEAR_ORIGIN` of the origin (a point in metres in a millimetre file);
        a knee in scan coordinates needs ``hip_center``: nothing else gives the femur's long axis."""
        if self.coordinates == "scan" and "hip_center" not in raw:
            raise InputError("a knee in scan coordinates needs the hip centre (the femoral Y axis points to it; the "
                             "scanner's axes say nothing about the femur): give landmarks.hip_center, or give the "
                             "knee in its femoral frame (coordinates = 'femoral')", source=self.src,
                             field="landmarks.hip_center")
        centre = self.at_reference(np.vstack(tibia)).mean(axis=0)
        for name, point in raw.items():
            fld = f"landmarks.{name}"
            if self.coordinates == "femoral" and self.units == "mm" and np.linalg.norm(point) < NEAR_ORIGIN \
                    and name in (*LIMB_LANDMARKS, *KNEE_LANDMARKS):
                raise InputError(f"{np.linalg.norm(point) * 1e3:.3g} mm from the origin of the femoral frame: a "
                                 "point in m with units = 'mm'?", source=self.src, field=fld)
            here = self.at_reference(point) if name not in FEMORAL_LANDMARKS else point
            dist = float(np.linalg.norm(here - centre))
            lo, hi = LIMB_REACH if name in LIMB_LANDMARKS else (0.0, KNEE_REACH) if name in KNEE_LANDMARKS \
                else (0.0, LIMB_REACH[1])  # a landmark of the user's own: anywhere on the limb
            if dist < lo:
                raise InputError(f"{dist * 1e3:.3g} mm from the knee (the tibial cartilage's centre), less than "
                                 f"{lo * 1e3:g} mm: the {name.replace('_', ' ')} at the knee? (a point of the knee "
                                 "copied, or the wrong landmark given)", source=self.src, field=fld)
            if dist > hi:
                other = "m" if self.units == "mm" else "mm"
                raise InputError(f"{dist * 1e3:.4g} mm from the knee (the tibial cartilage's centre), more than "
                                 f"{hi * 1e3:g} mm: a typo, or a point in {other} with units = {self.units!r}?",
                                 source=self.src, field=fld)

    def check_size(self, compartments: dict[str, Compartment]) -> None:
        """The knee's size against :data:`KNEE_SIZE_RANGE`: a unit slip names the likely cause."""
        points = np.vstack([c.points for c in compartments.values()])
        self.check_extent(points, "the tibial cartilage", "units")

    def check_extent(self, points: np.ndarray, what: str, fld: str) -> None:
        """The largest extent of ``points`` (m) against :data:`KNEE_SIZE_RANGE` (each mesh on its own
        when read, the whole tibial cartilage once built): outside, a unit slip is named."""
        size = float(np.ptp(np.asarray(points, float), axis=0).max())
        lo, hi = KNEE_SIZE_RANGE
        if lo <= size <= hi:
            return
        other = "m" if self.units == "mm" else "mm"
        raise InputError(f"{what} spans {size * 1e3:.3g} mm with units = {self.units!r}, "
                         f"{'1000x' if size > hi else '1/1000 of'} a knee's: is it in {other}? (set units = "
                         f"{other!r}, or convert it)", source=self.src, field=fld)

    def structures(self) -> dict[str, object]:
        """The knee's value of every built-in structure's table the file declares (SI, checked;
        :mod:`kneenlp.model.structures`), by table name."""
        return {t.name: t.read(getattr(self.spec, t.name), self.src) for t in structure_tables()
                if t.read is not None and getattr(self.spec, t.name) is not None}

    def parameter_set(self, parameters, ligaments: dict[str, Ligament]) -> ParameterSet:
        """The knee's parameter set (SI): ``parameters`` (a set or its file) or the file's own,
        checked to give exactly the properties of ``ligaments``."""
        src = self.src
        if isinstance(parameters, ParameterSet):
            params = parameters
        elif parameters is not None:
            params = ParameterSet.load(parameters)
        elif self.spec.parameters is not None:
            name = self.spec.parameters
            path = self.path.parent / name
            if not is_file(path):
                raise InputError(f"parameter file {name!r} not found ({path})", source=src, field="parameters")
            params = ParameterSet.load(path)
        else:
            raise InputError("no parameter set: give 'parameters = FILE' or pass one", source=src,
                             field="parameters")
        return check_parameter_set(params, ligaments, src)


def check_parameter_set(params: ParameterSet, ligaments: dict[str, Ligament], knee_source: str | None) -> ParameterSet:
    """``params`` if it gives exactly the properties of ``ligaments`` (of the knee file
    ``knee_source``), else an error naming both files."""
    src = knee_source or "the knee"
    extra = sorted({n.split(".")[0] for n in params.names() if n not in params.meta}
                   - set(ligaments) - {"contact"})
    if extra:
        raise InputError(f"unknown ligament {extra[0]!r}; known: {', '.join(ligaments)} (the ligaments of "
                         f"{src})", source=params.source or src, field=f"ligaments.{extra[0]}")
    missing = [f"{n}.{k}" for n, lig in ligaments.items() if not lig.grouped
               for k in LIGAMENT_KINDS if f"{n}.{k}" not in params]
    if missing:
        raise InputError(f"parameter set {params.source or params.name} lacks {', '.join(missing)}",
                         source=knee_source, field="parameters")
    return params










def is_file(path: Path) -> bool:
    """``path.is_file()``, False for a name the system cannot look up (too long, an invalid byte)."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False


def check_stl(path: Path, knee_file: str, field: str) -> int:
    """A binary STL's size against the triangle count in its header (84 + 50 bytes a triangle): a
    truncated file is named as such (trimesh would try it as ASCII and fail obscurely).  Returns the
    count (0 for another format or an ASCII STL)."""
    if path.suffix.lower() != ".stl":
        return 0
    try:
        size = path.stat().st_size
        with path.open("rb") as f:
            head = f.read(84)
    except OSError as exc:
        raise InputError(f"cannot read mesh {path.name} ({type(exc).__name__}: {exc.strerror or exc})",
                         source=knee_file, field=field) from None
    if head[:5].lower() == b"solid" and b"\0" not in head[:80]:
        return 0  # ASCII STL (a binary one may start with "solid" too, but its header is padded with NULs)
    if size < 84:
        raise InputError(f"mesh {path.name} is truncated: {size} bytes, less than a binary STL's 84-byte header",
                         source=knee_file, field=field)
    n = int.from_bytes(head[80:84], "little")
    if n > MAX_READ_FACES:
        raise InputError(f"mesh {path.name} announces {n:,} triangles, more than the {MAX_READ_FACES:,} a knee reads "
                         "(meshes are decimated to the contact resolution anyway): decimate it before",
                         source=knee_file, field=field)
    if size < 84 + 50 * n:
        raise InputError(f"mesh {path.name} is truncated: its header announces {n} triangles ({84 + 50 * n} bytes), "
                         f"the file has {size} bytes (an interrupted copy or export?)", source=knee_file, field=field)
    return n


def read_mesh(path: Path, scale: float, mirror: np.ndarray, *, field: str, knee_file: str) -> trimesh.Trimesh:
    """Load a mesh, validate it and convert it to metres (mirrored for a left knee).  A binary STL
    of more than :data:`~kneenlp.geometry.decimate.MAX_MESH_FACES` faces is read by a lean reader,
    to be decimated by the caller (:func:`~kneenlp.geometry.decimate.decimate`)."""
    if not is_file(path):
        raise InputError(f"mesh file not found: {path}", source=knee_file, field=field)
    binary_faces = check_stl(path, knee_file, field)
    if binary_faces > MAX_MESH_FACES:  # a lean reader (trimesh's takes 1.9 GB for 2 M faces)
        mesh = trimesh.Trimesh(*read_binary_stl(path, binary_faces), process=False)
        mesh.metadata["faces_read"] = binary_faces
        return _checked_mesh(mesh, path, (scale, mirror), (knee_file, field), merge=False)
    size = path.stat().st_size
    if size > MAX_TEXT_MESH_BYTES:
        raise InputError(f"mesh {path.name} is {size / 1e6:.0f} MB, more than the {MAX_TEXT_MESH_BYTES / 1e6:.0f} "
                         "MB read in this format (a knee load stays below 2 GB): save it as binary STL, or decimate it",
                         source=knee_file, field=field)
    try:
        mesh = trimesh.load(path, force="mesh", process=False)  # unprocessed: processing drops NaN vertices
    except ImportError:  # trimesh's fallback for an unreadable file wants optional modules
        raise InputError(f"cannot read mesh {path.name}: not a valid {path.suffix.lstrip('.').upper()} file "
                         "(corrupt or truncated?)", source=knee_file, field=field) from None
    except Exception as exc:  # trimesh raises many exception types for broken files
        raise InputError(f"cannot read mesh {path.name} ({type(exc).__name__}: {' '.join(str(exc).split())})",
                         source=knee_file, field=field) from None
    return _checked_mesh(mesh, path, (scale, mirror), (knee_file, field))


def _checked_mesh(mesh: object, path: Path, convert: tuple[float, np.ndarray], where: tuple[str, str],
                  merge: bool = True) -> trimesh.Trimesh:
    """:func:`read_mesh`'s checks and conversion of a mesh as read: ``convert = (scale, mirror)`` to
    metres, mirrored; ``where = (knee_file, field)`` the errors name; ``merge``: merge duplicate
    vertices."""
    scale, mirror = convert
    knee_file, field = where
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"mesh {path.name} has no triangles (empty, truncated or not a mesh?)", source=knee_file,
                         field=field)
    bad = ~np.isfinite(np.asarray(mesh.vertices, float)).all(axis=1)
    if bad.any():
        raise InputError(f"mesh {path.name} has {int(bad.sum())} non-finite vertices (NaN or inf; the first: "
                         f"vertex {int(np.argmax(bad))})", source=knee_file, field=field)
    if merge:
        mesh.process(validate=False)  # as trimesh.load(process=True): merge duplicate vertices
    area = np.asarray(mesh.area_faces)
    # zero area: a height below a micrometre per metre of the mesh (float32 rounding of a vertex on an
    # edge leaves 1e-8 of it)
    tri = np.asarray(mesh.triangles)
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    flat = 2 * area <= 1e-6 * max(float(np.ptp(mesh.vertices, axis=0).max()), 1e-300) * longest
    if flat.mean() > 0.5:
        raise InputError(f"mesh {path.name}: {int(flat.sum())} of {len(flat)} faces are degenerate (zero area: "
                         "repeated or collinear vertices); a broken export?", source=knee_file, field=field)
    total = float(area.sum()) * scale**2  # kept: the decimation needs it, and a large mesh's areas cost seconds
    mesh = mesh.copy()
    if flat.any():  # zero-area faces carry no surface, and their normals are noise: dropped
        mesh.update_faces(~flat)
        mesh.remove_unreferenced_vertices()
    mesh.vertices = np.asarray(mesh.vertices, float) * scale * mirror
    mesh.metadata["area"] = total
    if mirror[2] < 0:
        mesh.invert()  # keep the face orientation after mirroring
    return mesh
