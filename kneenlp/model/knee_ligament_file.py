"""A knee file's ligaments: bundles, laws, paths, slack shifts and candidates, their attachments
checked against the bones (:class:`LigamentReading`, one part of the knee file's reader
:class:`~kneenlp.model.knee_file.KneeFile`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from kneenlp.base.errors import InputError
from kneenlp.geometry.distance import MeshDistance, winding_number
from kneenlp.model.knee_schema import BundleTable, SlackShiftTable
from kneenlp.model.laws import DEFAULT_LAW, law_named
from kneenlp.model.ligament import Bundle, Ligament, SlackShift
from kneenlp.model.parameters import KINDS
from kneenlp.model.paths import CylinderWrap, LigamentPath, StraightPath, ViaPoints

#: Longest plausible ligament (m, attachment distance in the reference pose; the superficial MCL
#: is about 0.1 m): attachments further apart are a typo or mixed units.
MAX_LIGAMENT_LENGTH = 0.3
#: Deepest an attachment may lie inside a bone or cartilage mesh (m): attachments lie on the bone
#: surface, up to 1.2 mm inside the meshes of the shipped knees (s192803's posterior capsule in its
#: femoral cartilage solid); deeper is a slip (docs/inputs.md).
ATTACHMENT_DEPTH = 2.5e-3
#: A point (attachment or landmark) this close to the femoral frame's origin (m) in a millimetre
#: file is a point written in metres (the origin lies between the condyles, no attachment there).
NEAR_ORIGIN = 0.5e-3


class LigamentReading:
    """Reads a knee file's ligaments (a part of :class:`~kneenlp.model.knee_file.KneeFile`, whose
    state it uses: ``spec``, ``src``, ``attachments`` and its unit-aware readers): each ligament's
    bundles, law and path, the candidates, the bones the attachments are checked against."""

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
