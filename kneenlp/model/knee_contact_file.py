"""A knee file's articular geometry: tibial cartilage per compartment, the femoral surface, the
flexion axis fitted to the condyles and the femoral frame (:class:`ContactReading`, one part of
the knee file's reader :class:`~kneenlp.model.knee_file.KneeFile`)."""

from __future__ import annotations

import warnings

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from kneenlp.base.errors import InputError
from kneenlp.geometry.axes import FlexionAxis, fit_flexion_axis, split_condyles
from kneenlp.geometry.distance import MeshDistance
from kneenlp.geometry.rim import OpenEdges
from kneenlp.geometry.sdf import DistanceField
from kneenlp.geometry.shell import articular_faces, shell_thickness
from kneenlp.model.articular import (
    SAMPLE_EDGE,
    Compartment,
    FemoralSurface,
    femoral_box,
    sampled_plateau,
    split_tibia,
    tibial_samples,
)
from kneenlp.model.frames import Frame, angle_deg, axes_from_flexion, landmark_axes
from kneenlp.model.laws import DEFAULT_PRESSURE_LAW, law_named

#: Ligament names (prefixes, upper case) on the medial and the lateral side of the knee, the
#: evidence :meth:`KneeFile.check_side` weighs against the declared side.

#: Least angle (deg) between the knee-to-hip line and the fitted flexion axis (about 90 in a femur).
HIP_AXIS_ANGLE = 45.0
#: Fewest faces of a femoral mesh (the shipped ones: 11,700-22,300): fewer cannot represent condyles.
MIN_FEMUR_FACES = 500
#: Least vertices and area (m^2) of a tibial plateau's cartilage mesh (real: 360-2300 vertices,
#: 820-1350 mm^2 in the shipped knees): contact acts at the vertices.
MIN_PLATEAU_POINTS = 20
MIN_PLATEAU_AREA = 100e-6
#: Deepest (m) the tibial cartilage may lie inside the femoral articular surface at the reference
#: pose (0.1-0.3 mm in the shipped knees; the distance field is accurate to 1.5 mm inside).
MAX_REFERENCE_PENETRATION = 1.5e-3


class ContactReading:
    """Reads a knee file's articular geometry (a part of
    :class:`~kneenlp.model.knee_file.KneeFile`, whose state it uses: ``spec``, ``src``, ``frame``,
    ``notes`` and its unit-aware readers): the tibial plateaus, the femoral surface, the flexion
    axis fitted to the condyles and the femoral frame built from them, each checked."""

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

    def check_bone_order(self, femur: trimesh.Trimesh, tibiae: dict[str, trimesh.Trimesh], hip: np.ndarray | None,
                         proximal: np.ndarray) -> None:
        """The femoral and tibial meshes are two bones, the femur's on the hip's side of the tibia's
        (scan coordinates, the tibia placed by :meth:`at_reference`; towards ``hip`` when the file has
        it, else along ``proximal``): a mesh given twice or the two swapped is an input error naming the
        slip, not a failed fit later."""
        src = self.src
        tibia = trimesh.util.concatenate(list(tibiae.values()))
        gap, _ = cKDTree(np.asarray(femur.vertices)).query(np.asarray(tibia.vertices), 1)
        scale = float(np.median(tibia.edges_unique_length)) or 1.0
        if np.mean(gap < 1e-6 * scale) > 0.5:
            raise InputError("the tibial mesh is (part of) the femoral mesh: the same file given twice?", source=src,
                             field="contact.tibia")
        centre = self.at_reference(tibia.vertices).mean(axis=0)
        up = (hip - centre) if hip is not None else np.asarray(proximal, float)
        if (femur.vertices.mean(axis=0) - centre) @ up < 0:
            towards = "the hip centre" if hip is not None else "the scan's proximal axis"
            raise InputError(f"the tibial mesh lies above the femoral one (towards {towards}): the femoral and tibial "
                             "meshes swapped?", source=src, field="contact.tibia")

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
            self.check_bone_order(femur_raw, tibiae, raw_landmarks.get("hip_center"), approx[1])
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
