"""Knee files: the TOML reader that turns a knee file (meshes, attachments, landmarks, contact
settings, a parameter set) into the fields of a :class:`~kneenlp.model.knee.Knee`, in SI, with
every check a user's file needs (one-line errors naming the file and the field): the structure by
its schema (:mod:`kneenlp.model.knee_schema`), then the geometry against a knee's; where shipped
knees live (:func:`available_knees`, :func:`knee_file`, :func:`resolve_knee`).  The file format is
described in :mod:`kneenlp.model.knee` and docs/inputs.md."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from kneenlp.base.conventions import POSE_ENVELOPE_USER, coordinate_columns, coords_from_user
from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.resources import resource, shipped_knees
from kneenlp.base.schema import validated
from kneenlp.base.tomlfile import read_toml
from kneenlp.geometry.axes import FlexionAxis, fit_flexion_axis, split_condyles
from kneenlp.geometry.decimate import (
    MAX_MESH_FACES,
    MAX_READ_FACES,
    MAX_TEXT_MESH_BYTES,
    decimate,
    read_binary_stl,
)
from kneenlp.geometry.distance import MeshDistance, winding_number
from kneenlp.geometry.rim import OpenEdges
from kneenlp.geometry.sdf import DistanceField
from kneenlp.geometry.shell import articular_faces, shell_thickness
from kneenlp.model.articular import (
    SAMPLE_EDGE,
    Compartment,
    FemoralSurface,
    femoral_box,
    mesh_path,
    sampled_plateau,
    split_tibia,
    tibial_samples,
)
from kneenlp.model.frames import Frame, angle_deg, axes_from_flexion, landmark_axes
from kneenlp.model.kinematics import reference_transform
from kneenlp.model.knee_schema import BundleTable, SlackShiftTable, knee_document
from kneenlp.model.laws import DEFAULT_LAW, DEFAULT_PRESSURE_LAW, law_named
from kneenlp.model.ligament import Bundle, Ligament, SlackShift
from kneenlp.model.parameters import KINDS, LIGAMENT_KINDS, ParameterSet
from kneenlp.model.paths import CylinderWrap, LigamentPath, StraightPath, ViaPoints
from kneenlp.model.structures import structure_tables

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
                "wrap_radius": (0.5, 60.0)}
#: Longest plausible ligament (m, attachment distance in the reference pose; the superficial MCL
#: is about 0.1 m): attachments further apart are a typo or mixed units.
MAX_LIGAMENT_LENGTH = 0.3
#: Landmarks in the femur's frame (the others are the tibia's), and the two ends of the limb.
FEMORAL_LANDMARKS = ("hip_center", "medial_epicondyle", "lateral_epicondyle")
LIMB_LANDMARKS = ("hip_center", "ankle_center")
#: Distance (m) of the hip and ankle centres from the knee: femora and tibiae are 0.25-0.55 m long,
#: so closer is a point of the knee given as the hip (it would turn the frame), further a unit slip.
LIMB_REACH = (0.15, 1.0)
#: Least angle (deg) between the knee-to-hip line and the fitted flexion axis (about 90 in a femur).
HIP_AXIS_ANGLE = 45.0
#: The landmarks kneenlp knows at the knee (any other name is the user's own and only kept).
KNEE_LANDMARKS = ("medial_epicondyle", "lateral_epicondyle", "tibial_tuberosity", "medial_plateau_edge",
                  "lateral_plateau_edge")
#: Furthest (m) any of them (epicondyles, tuberosity, plateau edges) lies from the knee.
KNEE_REACH = 0.15
#: A point (attachment or landmark) this close to the femoral frame's origin (m) in a millimetre
#: file is a point written in metres (the origin lies between the condyles, no attachment there).
NEAR_ORIGIN = 0.5e-3
#: Fewest faces of a femoral mesh (the shipped ones: 11,700-22,300): fewer cannot represent condyles.
MIN_FEMUR_FACES = 500
#: Least vertices and area (m^2) of a tibial plateau's cartilage mesh (real: 360-2300 vertices,
#: 820-1350 mm^2 in the shipped knees): contact acts at the vertices.
MIN_PLATEAU_POINTS = 20
MIN_PLATEAU_AREA = 100e-6
#: Deepest (m) the tibial cartilage may lie inside the femoral articular surface at the reference
#: pose (0.1-0.3 mm in the shipped knees; the distance field is accurate to 1.5 mm inside).
MAX_REFERENCE_PENETRATION = 1.5e-3
#: Deepest an attachment may lie inside a bone or cartilage mesh (m): attachments lie on the bone
#: surface, up to 1.2 mm inside the meshes of the shipped knees (s192803's posterior capsule in its
#: femoral cartilage solid); deeper is a slip (docs/inputs.md).
ATTACHMENT_DEPTH = 2.5e-3


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


class KneeFile:
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

    def check_plateau(self, mesh: trimesh.Trimesh, fld: str, plateaus: int, what: str = "the mesh") -> None:
        """A tibial cartilage mesh of ``plateaus`` plateaus has enough points and area to carry contact:
        :data:`MIN_PLATEAU_POINTS` vertices and :data:`MIN_PLATEAU_AREA` each (a one-triangle or
        truncated mesh failed later with "residual inf")."""
        area, points = float(mesh.area), len(mesh.vertices)
        if points < MIN_PLATEAU_POINTS * plateaus or area < MIN_PLATEAU_AREA * plateaus:
            raise InputError(f"{what} has {len(mesh.faces)} faces, {points} vertices, {area * 1e6:.3g} mm^2: too few "
                             "to carry contact (a plateau's cartilage is 500-1500 mm^2; contact acts at the vertices, "
                             f"at least {MIN_PLATEAU_POINTS} and {MIN_PLATEAU_AREA * 1e6:g} mm^2 a plateau): a "
                             "placeholder, truncated or wrong file, or the wrong unit?", source=self.src, field=fld)

    def check_facing(self, femur: trimesh.Trimesh, tibiae: dict[str, trimesh.Trimesh], offset: float,
                     fld: str) -> None:
        """The femoral surface against the tibial cartilage at the reference pose (scan coordinates):
        its faces nearest the tibia face it (outward normals: an inside-out mesh makes every point
        penetrate, "residual 867"), and the cartilage lies at most :data:`MAX_REFERENCE_PENETRATION`
        inside the articular surface (the femoral mesh moved out by ``offset``), measured at points
        whose nearest femoral point is not on an open edge of the mesh."""
        points = self.at_reference(np.vstack([m.vertices for m in tibiae.values()]))
        facing, volume = facing_fraction(femur, points), centroid_volume(femur)
        if volume < 0 and (facing is None or facing < 0.5):
            raise InputError(f"the femoral mesh is inside-out: its signed volume is {volume * 1e6:.3g} cm^3"
                             + (f" and {100 * (1 - facing):.0f} % of its faces nearest the tibia point away from it"
                                if facing is not None else "") + " (normals into the bone): flip its faces (e.g. "
                             "trimesh's mesh.invert()) or fix the export", source=self.src, field=fld)
        depth = reference_penetration(femur, points, offset)
        if depth > MAX_REFERENCE_PENETRATION:
            where = "its reference_pose" if self.spec.reference_pose is not None else "the tibial meshes' placement"
            raise InputError(f"the tibial cartilage lies {depth * 1e3:.3g} mm inside the femoral articular surface "
                             f"at the reference pose (at most {MAX_REFERENCE_PENETRATION * 1e3:g} mm; real scans: 0.3 "
                             f"mm): check {where}, femur_offset ({offset * 1e3:g} mm) and that both bones are in the "
                             "same frame and unit", source=self.src, field="contact.tibia")

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

    def check_length(self, femur: np.ndarray, tibia: np.ndarray, fld: str) -> float:
        """Attachment distance (m) of a bundle in the reference pose: at least 1 mm, at most
        :data:`MAX_LIGAMENT_LENGTH`."""
        length = float(np.linalg.norm(femur - self.at_reference(tibia)))
        if length < 1e-3:
            raise InputError("attachments closer than 1 mm", source=self.src, field=fld)
        if length > MAX_LIGAMENT_LENGTH:
            raise InputError(f"attachments {length * 1e3:.4g} mm apart, more than any knee ligament "
                             f"({MAX_LIGAMENT_LENGTH * 1e3:g} mm): a typo, or a point in another unit than "
                             f"units = {self.units!r}?", source=self.src, field=fld)
        return length

    def attach(self, femur: np.ndarray, tibia: np.ndarray, femur_field: str, tibia_field: str) -> None:
        """Remember a bundle's attachments (femoral frame; tibial frame) for :meth:`check_attachments`;
        in a millimetre file in the femoral frame, a point within :data:`NEAR_ORIGIN` of the origin is
        one written in metres."""
        if self.coordinates == "femoral" and self.units == "mm":
            for point, fld in ((femur, femur_field), (tibia, tibia_field)):
                if np.linalg.norm(point) < NEAR_ORIGIN:
                    raise InputError(f"{np.linalg.norm(point) * 1e3:.3g} mm from the origin of the frame, where no "
                                     "ligament attaches: a point in m with units = 'mm'?", source=self.src,
                                     field=fld)
        self.attachments += [(femur_field, np.asarray(femur, float), "femoral"),
                             (tibia_field, self.at_reference(tibia), "tibial")]

    def check_attachments(self, geometry: dict) -> None:
        """No attachment lies more than :data:`ATTACHMENT_DEPTH` inside a mesh of the knee
        (:meth:`attachment_depths`)."""
        inside = self.attachment_depths(geometry, ATTACHMENT_DEPTH)
        if inside:
            fld, what, name, bone, depth = max(inside, key=lambda row: row[-1])
            raise InputError(f"the {bone} attachment lies {depth * 1e3:.1f} mm inside the {what} ({name}) "
                             "in the reference pose; attachments lie on the bone surface (at most "
                             f"{ATTACHMENT_DEPTH * 1e3:g} mm inside): a typo or a sign slip, the femoral and "
                             "tibial points swapped, or a point in another frame or unit?", source=self.src, field=fld)

    def bones(self) -> list[tuple[str, str, trimesh.Trimesh]]:
        """``[bones]``: (what, file, surface in the femoral frame at the reference pose, m) of each
        bone the file gives: closed, or open only away from the knee (a shaft cut off), so that its
        winding number tells its inside (:meth:`attachment_depths`)."""
        table = self.spec.bones
        out = []
        for bone, tibial in (("femur", False), ("tibia", True)):
            value = None if table is None else getattr(table, bone)
            if value is None:
                continue
            fld = f"bones.{bone}"
            mesh = self.frame.mesh(self.mesh(value, fld))
            if tibial:
                mesh.vertices = self.at_reference(mesh.vertices)
            out.append((f"{'tibial' if tibial else 'femoral'} bone", str(value), mesh))
        return out

    def attachment_depths(self, geometry: dict, deeper_than: float = 0.0) -> list[tuple[str, str, str, str, float]]:
        """The attachments more than ``deeper_than`` (m) inside a mesh of the knee (the femoral mesh
        as given, without ``femur_offset``; each tibial mesh at the reference pose), as (field, mesh,
        mesh source, bone, depth in m).  Inside: the mesh's winding number around the point exceeds
        1/2 (:func:`~kneenlp.geometry.distance.winding_number`), which holds for closed meshes and
        for open ones enclosing the point (a cropped bone); a cartilage sheet encloses nothing but
        the points just under it."""
        if not self.attachments:
            return []
        meshes = []
        femur = geometry["femur"]
        if femur is not None:
            meshes.append(("femoral mesh", " + ".join(femur.sources), femur.mesh, 1.0))
        meshes += [(what, name, mesh, 1.0) for what, name, mesh in geometry.get("bones", [])]
        R, p = self.reference
        for c in geometry["compartments"].values():
            if not c.sphere:
                m = c.tibia_mesh.copy()
                m.vertices = np.asarray(m.vertices) @ R.T + p
                meshes.append((f"{c.name} tibial mesh", c.name, m, -1.0))  # tibial orientation is not used
        points = np.array([x for _, x, _ in self.attachments])
        found = []
        for what, name, mesh, sign in meshes:
            lo, hi = mesh.bounds
            idx = np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
            if not len(idx):
                continue
            depth = np.abs(MeshDistance(mesh)(points[idx], certify=False)[0])
            idx, depth = idx[depth > deeper_than], depth[depth > deeper_than]
            if not len(idx):
                continue
            w = winding_number(mesh, points[idx])
            inside = (w > 0.5) if sign > 0 else (np.abs(w) > 0.5)
            found += [(self.attachments[i][0], what, name, self.attachments[i][2], float(d))
                      for i, d in zip(idx[inside], depth[inside], strict=True)]
        return found

    def structures(self) -> dict[str, object]:
        """The knee's value of every built-in structure's table the file declares (SI, checked;
        :mod:`kneenlp.model.structures`), by table name."""
        return {t.name: t.read(getattr(self.spec, t.name), self.src) for t in structure_tables()
                if getattr(self.spec, t.name) is not None}

    def contact(self, raw_landmarks: dict[str, np.ndarray]) -> dict:
        """The articular geometry in the femoral frame (m): read the tibial cartilage and the femoral
        surfaces (scan coordinates), fit the flexion axis, build the femoral frame from them and map
        the compartments and the femoral surface into it.  ``raw_landmarks``: scan coordinates, m."""
        tibiae, approx = self.read_tibiae(raw_landmarks)
        femur_raw, sources, spheres, offset = self.read_femur(tibiae, raw_landmarks, approx)
        axis = None
        if femur_raw is not None:
            axis, approx = self.fit_axis(femur_raw, tibiae, raw_landmarks.get("hip_center"), approx)
        axis = self.map_to_frame(axis, spheres, raw_landmarks, approx, offset)
        compartments = self.compartments(tibiae, spheres, axis)
        mesh_compartments = [n for n in tibiae if n not in spheres]
        femur = None
        if femur_raw is not None and mesh_compartments:
            femur = self.femoral_surface(femur_raw, [compartments[n] for n in mesh_compartments], axis, offset,
                                         sources)
        return {"compartments": compartments, "femur": femur, "axis": axis}

    def read_tibiae(self, raw_landmarks: dict[str, np.ndarray]) -> tuple[dict[str, trimesh.Trimesh], np.ndarray]:
        """The tibial cartilage per compartment (scan coordinates, m), read per compartment or once
        and split into plateaus, each checked to carry contact, and the scan's approximate anterior,
        proximal and lateral directions (rows; :meth:`approximate_axes`).  The landmarks (scan
        coordinates, m) are checked against the cartilage's position."""
        contact, tables = self.spec.contact, self.spec.contact.compartments()
        whole = self.mesh(contact.tibia, "contact.tibia") if contact.tibia is not None else None
        tibiae = {name: self.mesh(t.tibia, f"contact.{name}.tibia") for name, t in tables.items()
                  if t.tibia is not None}
        for name, mesh in ({"": whole} if whole is not None else tibiae).items():
            self.check_plateau(mesh, f"contact.{name}.tibia" if name else "contact.tibia", 2 if not name else 1)
        self.check_landmarks(raw_landmarks, [m.vertices for m in ([whole] if whole is not None else tibiae.values())])
        approx = self.approximate_axes(raw_landmarks)
        if whole is not None:
            tibiae, _, how = split_tibia(whole, approx[2])
            self.notes.append(f"tibial cartilage split into plateaus: {how}")
            unknown = set(tables) - set(tibiae)
            if unknown:
                raise InputError(f"compartment {sorted(unknown)[0]!r} has no plateau; the split gives medial, lateral",
                                 source=self.src, field="contact")
            for name, mesh in tibiae.items():
                self.check_plateau(mesh, "contact.tibia", 1, f"its {name} plateau")
        return tibiae, approx

    def read_femur(self, tibiae: dict[str, trimesh.Trimesh], raw_landmarks: dict[str, np.ndarray],
                   approx: np.ndarray) -> tuple[trimesh.Trimesh | None, list[str], dict, float]:
        """The femoral surface (scan coordinates, m; None with spheres only), its mesh files, the
        explicit spheres (name -> (centre in scan coordinates, radius), m) and the femoral offset (m),
        the femoral mesh checked against the tibial one (bone order, facing, penetration)."""
        contact, tables, src = self.spec.contact, self.spec.contact.compartments(), self.src
        spheres = {name: (self.raw_point(t.sphere_center),
                          self.length(t.sphere_radius, "sphere_radius", 0.0, f"contact.{name}.sphere_radius"))
                   for name, t in tables.items() if t.sphere_center is not None}
        named = [("contact.femur", contact.femur)] + [(f"contact.{n}.femur", t.femur) for n, t in tables.items()]
        femur_parts = [self.mesh(value, fld) for fld, value in named if value is not None]
        sources = [value for _, value in named if value is not None]
        mesh_compartments = [n for n in tibiae if n not in spheres]
        if mesh_compartments and not femur_parts:
            raise InputError(f"compartment {mesh_compartments[0]!r} has neither a femoral mesh (contact.femur) "
                             "nor an explicit sphere (sphere_center, sphere_radius)", source=src, field="contact")
        femur_raw = trimesh.util.concatenate(femur_parts) if femur_parts else None
        if femur_raw is not None and len(femur_raw.faces) < MIN_FEMUR_FACES:
            raise InputError(f"the femoral mesh has {len(femur_raw.faces)} faces: too coarse to represent the condyles "
                             f"(at least {MIN_FEMUR_FACES}; real femoral meshes have 10,000-30,000): a placeholder or "
                             "over-decimated file?", source=src, field="contact.femur")
        if femur_raw is not None:
            check_bone_order(femur_raw, tibiae, self.at_reference, raw_landmarks.get("hip_center"), approx[1], src)
        offset = self.length(contact.femur_offset, "femur_offset", 0.0, "contact.femur_offset", positive=False)
        if femur_raw is not None and mesh_compartments:
            self.check_facing(femur_raw, {n: tibiae[n] for n in mesh_compartments}, offset,
                              "contact.femur" if contact.femur is not None else "contact")
        return femur_raw, sources, spheres, offset

    def fit_axis(self, femur_raw: trimesh.Trimesh, tibiae: dict[str, trimesh.Trimesh], hip: np.ndarray | None,
                 approx: np.ndarray) -> tuple[FlexionAxis, np.ndarray]:
        """The flexion axis fitted to the femoral condyles (scan coordinates, m) and the approximate
        axes (rows) of the last fit.  The fitted regions depend on the approximate axes, so the fit
        is repeated with the axes of the last one until the axis settles (1e-4 deg, 1e-7 m): the
        frame does not depend on how the scan was oriented.  ``hip``: the hip centre (m) or None."""
        cents = {n: m.vertices.mean(axis=0) for n, m in tibiae.items()}
        if {"medial", "lateral"} <= set(cents):
            med, lat = cents["medial"], cents["lateral"]
        else:
            s = {n: c @ approx[2] for n, c in cents.items()}
            med, lat = cents[min(s, key=s.get)], cents[max(s, key=s.get)]
        axis = split = None
        for _ in range(5):
            try:
                with warnings.catch_warnings(), np.errstate(all="ignore"):  # a failed fit says why below
                    warnings.simplefilter("ignore")
                    split = split_condyles(femur_raw, med, lat, approx[1])
                    new = fit_flexion_axis(femur_raw, split, approx[1], approx[0], approx[2])
            except (ValueError, np.linalg.LinAlgError, TypeError) as exc:
                raise InputError(f"cannot fit cylinders to the femoral condyles ({exc}; {len(femur_raw.faces)} "
                                 "faces): check that the femoral mesh is in the file's unit (units = "
                                 f"{self.units!r}) and covers both condyles with more than a few faces, that "
                                 "landmarks.hip_center is the hip (it sets the proximal direction) and that the "
                                 "tibial meshes are the tibia's", source=self.src, field="contact.femur") from None
            if hip is not None:
                tilt = angle_deg(hip - new.point, new.direction)
                if min(tilt, 180 - tilt) < HIP_AXIS_ANGLE:
                    raise InputError(f"the hip centre lies {min(tilt, 180 - tilt):.0f} deg from the flexion axis "
                                     "fitted to the condyles (a femur's shaft is about 90 deg from it): a medial "
                                     "or lateral point given as the hip, or the femoral mesh in another frame?",
                                     source=self.src, field="landmarks.hip_center")
            settled = axis is not None and angle_deg(new.direction, axis.direction) < 1e-4 \
                and np.linalg.norm(new.point - axis.point) < 1e-7
            axis = new
            if settled:
                break
            approx = axes_from_flexion(axis.direction, hip - axis.point if hip is not None else approx[1])
        self.notes.append(f"femoral condyles split by a {split.describe()}")
        return axis, approx

    def map_to_frame(self, axis: FlexionAxis | None, spheres: dict, raw_landmarks: dict[str, np.ndarray],
                     approx: np.ndarray, offset: float) -> FlexionAxis | None:
        """Build the femoral frame (:meth:`build_frame`; scan coordinates, m) and return the flexion
        axis in it (None without a femoral mesh), noting both (``offset``: the femoral offset, m)."""
        self.frame = self.build_frame(axis, spheres, raw_landmarks, approx)
        self.notes.append(f"frame: {self.frame.how}")
        if axis is None:
            return None
        axis = axis.mapped(self.frame.rotation, self.frame.origin)
        where = ("" if self.frame.how.startswith("cylinders") else  # else: the frame came from elsewhere
                 f"; {angle_deg(axis.direction, [0, 0, 1]):.2f} deg from the femoral Z axis, "
                 f"{np.linalg.norm(np.cross(axis.point, axis.direction)) * 1e3:.2f} mm from the origin")
        self.notes.append(f"flexion axis: {axis.describe(offset)}{where}")
        return axis

    def compartments(self, tibiae: dict[str, trimesh.Trimesh], spheres: dict,
                     axis: FlexionAxis | None) -> dict[str, Compartment]:
        """The compartments in the femoral frame (tibial meshes and points in the tibial frame, m;
        condyle centres and sphere radii in m) with their pressure laws."""
        contact, tables = self.spec.contact, self.spec.contact.compartments()
        compartments = {}
        for name, raw in tibiae.items():
            mesh = sampled_plateau(self.frame.mesh(raw))
            if len(mesh.vertices) != len(raw.vertices):
                edge = float(np.median(raw.edges_unique_length))
                self.notes.append(f"tibial cartilage {name!r}: median edge {edge * 1e3:.2g} mm, refined to "
                                  f"{len(mesh.vertices)} contact points from {len(raw.vertices)} vertices (edges of "
                                  f"at most {SAMPLE_EDGE * 1e3:g} mm)")
            points, areas = tibial_samples(mesh)
            if name in spheres:
                centre, radius = self.frame(spheres[name][0]), spheres[name][1]
            else:
                centre, radius = self.condyle_centre(axis, self.at_reference(points)), None
            own = tables[name].law if name in tables else None
            spec = own if own is not None else contact.law if contact.law is not None else DEFAULT_PRESSURE_LAW
            where = f"contact.{name}.law" if own is not None else "contact.law"
            law = law_named(spec, source=self.src, field=where, kind="pressure")
            compartments[name] = Compartment(name, mesh, points, areas, centre, radius, law)
        return compartments

    def femoral_surface(self, femur_raw: trimesh.Trimesh, compartments: list[Compartment], axis: FlexionAxis | None,
                        offset: float, sources: list[str]) -> FemoralSurface:
        """The femoral surface in the femoral frame (m), moved out by ``offset`` (m), with the box
        of its distance field (grid ``grid_spacing``, m) over the tibial points of the mesh
        ``compartments`` across the flexion range; its memory checked before any allocation."""
        fmesh = self.frame.mesh(femur_raw)
        pts = np.vstack([c.points for c in compartments])
        spacing = self.length(self.spec.contact.grid_spacing, "grid_spacing", 0.5, "contact.grid_spacing")
        try:
            box = femoral_box(fmesh, self.at_reference(pts), axis, np.degrees(self.reference_pose[0]))
        except ValueError as exc:  # the tibia never comes near the femur over the flexion range
            raise InputError(f"{exc} (more than 8 mm apart at every flexion): is the tibia placed in the "
                             "femur's frame and in the file's unit?", source=self.src, field="contact.tibia") from None
        try:  # before any allocation
            DistanceField.check_memory(box, spacing)
        except ValueError as exc:
            raise InputError(str(exc), source=self.src, field="contact.grid_spacing") from None
        articular = None
        if not offset and shell_thickness(fmesh) is not None:  # a segmented cartilage: depth below its articular side
            on_axis = (axis.point, axis.direction) if axis is not None else (np.zeros(3), np.array([0, 0, 1.0]))
            articular = articular_faces(fmesh, *on_axis)
        return FemoralSurface(fmesh, offset, spacing, box, sources, articular)

    def approximate_axes(self, raw_landmarks: dict[str, np.ndarray]) -> np.ndarray:
        """Anterior, proximal and lateral directions of the scan (rows), good enough to choose the
        regions the fits use: from the ISB landmarks when the file has them, else the scan's axes."""
        isb = {"hip_center", "medial_epicondyle", "lateral_epicondyle"}
        if self.coordinates == "scan" and isb <= set(raw_landmarks):
            return landmark_axes(raw_landmarks, self.src)
        return np.eye(3)

    def build_frame(self, axis: FlexionAxis | None, spheres: dict, raw_landmarks: dict, approx: np.ndarray) -> Frame:
        """The femoral frame in scan coordinates (m): the identity for a file in the femoral frame,
        else by ``frame``: the flexion ``axis`` and the hip (or ``approx``'s proximal row), or the
        ISB landmarks with the origin between the condyle or sphere centres."""
        if self.coordinates == "femoral":
            if self.spec.frame is not None:
                raise InputError("only with coordinates = 'scan'", source=self.src, field="frame")
            return Frame.identity()
        method = self.spec.frame or ("cylinders" if axis is not None else "landmarks")
        if method == "cylinders":
            if axis is None:
                raise InputError("frame = 'cylinders' needs a femoral mesh (contact.femur)", source=self.src,
                                 field="frame")
            hip = raw_landmarks.get("hip_center")
            up = hip - axis.point if hip is not None else approx[1]
            rotation = axes_from_flexion(axis.direction, up)
            why = "hip centre" if hip is not None else "the scan's proximal axis (no landmarks.hip_center)"
            return Frame(rotation, axis.point,
                         f"cylinders: Z = flexion axis, origin = knee centre (midpoint of the cylinder centres), "
                         f"Y towards the {why}; femoral axes in scan coordinates X "
                         f"({', '.join(f'{v:.3f}' for v in rotation[0])}), Y "
                         f"({', '.join(f'{v:.3f}' for v in rotation[1])}), Z "
                         f"({', '.join(f'{v:.3f}' for v in rotation[2])})")
        rotation = landmark_axes(raw_landmarks, self.src)
        centres = [c for c, _ in spheres.values()] if axis is None else [axis.medial.centre, axis.lateral.centre]
        origin = np.mean(centres, axis=0)
        return Frame(rotation, origin, "landmarks (ISB: hip centre and epicondyles), origin at the midpoint of "
                                       f"the condyle centres; flexion axis {'fitted' if axis else 'not fitted'}")

    @staticmethod
    def condyle_centre(axis: FlexionAxis | None, points: np.ndarray) -> np.ndarray:
        """The cylinder centre of the condyle on the side of the plateau ``points``."""
        if axis is None:
            return np.array([0.0, 0.0, np.sign(points[:, 2].mean()) * 0.02])
        side = (points.mean(axis=0) - axis.point) @ axis.direction
        return axis.lateral.centre if side >= 0 else axis.medial.centre

    def ligaments(self) -> dict[str, Ligament]:
        """``[ligaments.<NAME>]``: each ligament's bundles (attachments in m, femoral frame) and law."""
        ligaments = {}
        for name, lig in self.spec.ligaments.items():
            fld = f"ligaments.{name}"
            law = law_named(lig.law if lig.law is not None else DEFAULT_LAW, source=self.src, field=f"{fld}.law")
            path = self.ligament_path(lig, fld)
            if lig.bundles is not None:
                bundles = [dataclasses.replace(b, path=path) for b in self.bundles(lig.bundles, f"{fld}.bundles")]
                ligaments[name] = Ligament(name, bundles, reference=self.reference, law=law,
                                           shift=self.slack_shift(lig.slack_shift, f"{fld}.slack_shift"))
                continue
            femur, tibia = self.point(lig.femur), self.point(lig.tibia)
            self.check_length(femur, tibia, fld)
            self.attach(femur, tibia, f"{fld}.femur", f"{fld}.tibia")
            ligaments[name] = Ligament(name, [Bundle(femur, tibia, path=path)], reference=self.reference, law=law)
        return ligaments

    def ligament_path(self, lig, fld: str) -> LigamentPath:
        """A ligament's path: its ``via`` points or the cylinder it ``wrap``s, in the model's frames
        (m; a left knee mirrored, which turns a wrap's side), else the straight path."""
        if lig.via is not None and lig.wrap is not None:
            raise InputError("give via points or a wrapping cylinder, not both", source=self.src, field=f"{fld}.via")
        if lig.via is not None:
            return ViaPoints(tuple(tuple(self.point(v)) for v in lig.via.tibia),
                             tuple(tuple(self.point(v)) for v in lig.via.femur))
        if lig.wrap is None:
            return StraightPath()
        table, fld = lig.wrap, f"{fld}.wrap"
        axis = self.point(table.axis) - self.point((0.0, 0.0, 0.0))
        if not np.linalg.norm(axis) > 0:
            raise InputError("must not be zero", source=self.src, field=f"{fld}.axis")
        side = (1 if table.side == "positive" else -1) * int(self.mirror[2])
        return CylinderWrap(self.point(table.centre), axis, self.length(table.radius, "wrap_radius", 10.0,
                                                                         f"{fld}.radius"), table.body, side)

    def slack_shift(self, table: SlackShiftTable | None, fld: str) -> SlackShift | None:
        """``[ligaments.<NAME>.slack_shift]``: the group's length (file unit -> m) and reference strain
        (% -> fraction); the group's slack length ``length / (1 + ref_strain)`` must be positive."""
        if table is None:
            return None
        shift = SlackShift(table.length * self.scale, table.ref_strain / KINDS["ref_strain"].to_user)
        if not shift.length > 0:
            raise InputError("must be > 0", source=self.src, field=f"{fld}.length")
        if not 1 + shift.ref_strain > 0:
            raise InputError("must be > -100 %", source=self.src, field=f"{fld}.ref_strain")
        return shift

    def bundles(self, tables: list[BundleTable], fld: str) -> list[Bundle]:
        """The bundles of a multi-bundle ligament: ``[[ligaments.<NAME>.bundles]]`` tables with
        ``name``, ``femur``, ``tibia``, ``stiffness`` (N per unit strain), ``slack_length`` (file
        length unit) or ``ref_strain`` (%), and ``transition_strain`` (OpenSim's, default 0.06) or
        ``lin_strain`` (%, the paper's limit = transition / 2)."""
        src = self.src
        out = []
        for i, b in enumerate(tables):
            f = f"{fld}[{i}]"
            femur, tibia = self.point(b.femur), self.point(b.tibia)
            length = self.check_length(femur, tibia, f)
            self.attach(femur, tibia, f"{f}.femur", f"{f}.tibia")
            if b.stiffness < 0:
                raise InputError("must be >= 0 (N per unit strain)", source=src, field=f"{f}.stiffness")
            if (b.slack_length is None) == (b.ref_strain is None):
                raise InputError("give slack_length or ref_strain", source=src, field=f)
            if b.slack_length is not None:
                slack = b.slack_length * self.scale
                if slack <= 0:
                    raise InputError("must be > 0", source=src, field=f"{f}.slack_length")
                ref = length / slack - 1
            else:
                ref = b.ref_strain / KINDS["ref_strain"].to_user
            if b.lin_strain is not None:
                lin = b.lin_strain / KINDS["lin_strain"].to_user
            else:
                lin = (b.transition_strain if b.transition_strain is not None else 0.06) / 2
            if lin <= 0:
                raise InputError("must be > 0", source=src, field=f"{f}.transition_strain")
            out.append(Bundle(femur, tibia, b.name if b.name is not None else f"{fld}{i}", b.stiffness, ref, lin))
        return out

    def candidates(self) -> list[Ligament]:
        """``[candidates.<NAME>]``: candidate bundles of model adequacy (attachments in m, femoral
        frame; the reference strain given in %, stored as a fraction)."""
        out = []
        for cname, cand in self.spec.candidates.items():
            fld = f"candidates.{cname}"
            fem = [self.point(v) for v in cand.femur]
            tib = [self.point(v) for v in cand.tibia]
            for i, (f, t) in enumerate(zip(fem, tib, strict=True)):
                self.check_length(f, t, fld)
                self.attach(f, t, f"{fld}.femur[{i}]", f"{fld}.tibia[{i}]")
            ref = cand.ref_strain / KINDS["ref_strain"].to_user
            out.append(Ligament(cname, [Bundle(f, t) for f, t in zip(fem, tib, strict=True)], candidate=True,
                                defaults={"ref_strain": ref}, description=cand.description,
                                reference=self.reference))
        return out

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


def check_bone_order(femur: trimesh.Trimesh, tibiae: dict[str, trimesh.Trimesh], at_reference,
                     hip: np.ndarray | None, proximal: np.ndarray, src: str) -> None:
    """The femoral and tibial meshes are two bones, the femur's on the hip's side of the tibia's
    (scan coordinates, the tibia placed by ``at_reference``; towards ``hip`` when the file has it,
    else along ``proximal``): a mesh given twice or the two swapped is an input error naming the
    slip, not a failed fit later."""
    tibia = trimesh.util.concatenate(list(tibiae.values()))
    gap, _ = cKDTree(np.asarray(femur.vertices)).query(np.asarray(tibia.vertices), 1)
    scale = float(np.median(tibia.edges_unique_length)) or 1.0
    if np.mean(gap < 1e-6 * scale) > 0.5:
        raise InputError("the tibial mesh is (part of) the femoral mesh: the same file given twice?", source=src,
                         field="contact.tibia")
    centre = at_reference(tibia.vertices).mean(axis=0)
    up = (hip - centre) if hip is not None else np.asarray(proximal, float)
    if (femur.vertices.mean(axis=0) - centre) @ up < 0:
        towards = "the hip centre" if hip is not None else "the scan's proximal axis"
        raise InputError(f"the tibial mesh lies above the femoral one (towards {towards}): the femoral and tibial "
                         "meshes swapped?", source=src, field="contact.tibia")


def centroid_volume(mesh: trimesh.Trimesh) -> float:
    """Signed volume (m^3) of the cones from the vertex centroid to the faces: the enclosed volume
    for a closed mesh (negative when inside-out); for an open bone surface, whose centroid lies in
    the bone, positive with outward normals (21-38 cm^3 for the shipped femoral meshes)."""
    t = np.asarray(mesh.triangles, float) - np.asarray(mesh.vertices, float).mean(axis=0)
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def facing_fraction(surface: trimesh.Trimesh, points: np.ndarray, reach: float = 0.01) -> float | None:
    """Of the ``points`` within ``reach`` (m) of a face centre of ``surface``, the fraction whose
    nearest face's normal points towards them (1 for a surface facing them with outward normals, 0
    for an inside-out one); None when no point is that near."""
    centres = np.asarray(surface.triangles_center)
    dist, face = cKDTree(centres).query(points, 1, distance_upper_bound=reach, workers=-1)
    ok = np.isfinite(dist)
    if not ok.any():
        return None
    face = face[ok]
    return float(np.mean(np.einsum("ij,ij->i", surface.face_normals[face], points[ok] - centres[face]) > 0))


def reference_penetration(surface: trimesh.Trimesh, points: np.ndarray, offset: float, most: int = 20_000) -> float:
    """Deepest (m, >= 0) any of ``points`` (at most ``most`` of them, evenly strided) lies inside the
    surface ``offset`` outside ``surface``, among points whose nearest surface point is not on an
    open edge (beyond an edge the signed distance is no depth)."""
    pts = np.asarray(points, float)
    if len(pts) > most:
        pts = pts[np.linspace(0, len(pts) - 1, most).round().astype(int)]
    lo, hi = surface.bounds
    pts = pts[np.all((pts >= lo - offset - 0.01) & (pts <= hi + offset + 0.01), axis=1)]
    if not len(pts):
        return 0.0
    d, closest, _ = MeshDistance(surface)(pts, certify=False)
    inner = OpenEdges(surface).distance(closest) > 1e-9
    d = d[inner] - offset
    return float(max(0.0, -d.min())) if d.size else 0.0


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
        return _checked_mesh(mesh, path, scale, mirror, knee_file, field, merge=False)
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
    return _checked_mesh(mesh, path, scale, mirror, knee_file, field)


def _checked_mesh(mesh: object, path: Path, scale: float, mirror: np.ndarray, knee_file: str, field: str,
                  merge: bool = True) -> trimesh.Trimesh:
    """:func:`read_mesh`'s checks and conversion of a mesh as read (``merge``: merge duplicate vertices)."""
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
