"""A knee file's ligaments: bundles, laws, paths, slack shifts and candidates, their attachments
checked against the bones (:class:`LigamentReading`, one part of the knee file's reader
:class:`~kneenlp.model.knee_file.KneeFile`)."""

from __future__ import annotations

import numpy as np
import trimesh

from kneenlp.base.errors import InputError
from kneenlp.geometry.distance import MeshDistance, winding_number
from kneenlp.model.bone_wrap import BONE_REACH, BoneWrap, bone_field
from kneenlp.model.kinematics import reference_transform
from kneenlp.model.knee_schema import BundleTable, SlackShiftTable
from kneenlp.model.laws import DEFAULT_LAW, law_named
from kneenlp.model.ligament import Bundle, Ligament, SlackShift
from kneenlp.model.parameters import KINDS
from kneenlp.model.paths import CylinderWrap, EllipsoidWrap, LigamentPath, StraightPath, ViaPoints, WrapPath

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
#: Flexions (deg) over which a wrapping obstacle is looked for on its bundle's straight path, at the
#: reference laxity pose: an obstacle never met there is noted (the path stays straight).
WRAP_FLEXIONS = np.arange(0.0, 121.0, 5.0)


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
        """``[ligaments.<NAME>]``: each ligament's bundles (attachments in m, femoral frame), their
        paths and the law."""
        ligaments = {}
        for name, lig in self.spec.ligaments.items():
            fld = f"ligaments.{name}"
            law = law_named(lig.law if lig.law is not None else DEFAULT_LAW, source=self.src, field=f"{fld}.law")
            path = self.ligament_path(lig, fld)
            if lig.bundles is not None:
                bundles = self.bundles(lig.bundles, f"{fld}.bundles", path)
                if lig.via is not None and any(t.wrap is not None for t in lig.bundles):
                    raise InputError("give via points or wrapping obstacles, not both", source=self.src,
                                     field=f"{fld}.via")
                ligaments[name] = Ligament(name, bundles, reference=self.reference, law=law,
                                           shift=self.slack_shift(lig.slack_shift, f"{fld}.slack_shift"))
                for i, b in enumerate(bundles):
                    own = lig.bundles[i].wrap is not None
                    self.check_path(b, f"{fld}.bundles[{i}]" if own else f"{fld}.wrap", b.name)
                continue
            femur, tibia = self.point(lig.femur), self.point(lig.tibia)
            self.check_length(femur, tibia, fld)
            self.attach(femur, tibia, f"{fld}.femur", f"{fld}.tibia")
            ligaments[name] = Ligament(name, [Bundle(femur, tibia, path=path)], reference=self.reference, law=law)
            self.check_path(ligaments[name].bundles[0], f"{fld}.wrap", name)
        return ligaments

    def ligament_path(self, lig, fld: str) -> LigamentPath:
        """A ligament's path: its ``via`` points or the obstacle it ``wrap``s, in the model's frames
        (m; a left knee mirrored), else the straight path."""
        if lig.via is not None and lig.wrap is not None:
            raise InputError("give via points or a wrapping obstacle, not both", source=self.src, field=f"{fld}.via")
        if lig.via is not None:
            for side, points in (("tibia", lig.via.tibia), ("femur", lig.via.femur)):
                for i, v in enumerate(points):  # checked against the bones as the attachments are
                    point = self.point(v)
                    self.attachments.append((f"{fld}.via.{side}[{i}]", self.at_reference(point) if side == "tibia"
                                             else point, "tibial" if side == "tibia" else "femoral"))
            return ViaPoints(tuple(tuple(self.point(v)) for v in lig.via.tibia),
                             tuple(tuple(self.point(v)) for v in lig.via.femur))
        return StraightPath() if lig.wrap is None else self.wrap_path(lig.wrap, f"{fld}.wrap")

    def direction(self, value, fld: str) -> np.ndarray:
        """A direction of the file in the femoral frame's axes (unit)."""
        axis = self.point(value) - self.point((0.0, 0.0, 0.0))
        if not np.linalg.norm(axis) > 0:
            raise InputError("must not be zero", source=self.src, field=fld)
        return axis / np.linalg.norm(axis)

    def wrap_path(self, table, fld: str) -> LigamentPath:
        """The path over a ``[...wrap]`` table's obstacle (a left knee mirrored, which turns a
        cylinder's side), or over a bone of ``[bones]``."""
        if table.shape == "bone":
            return self.bone_path(table, fld)
        centre = self.point(table.centre)
        if table.shape == "cylinder":
            side = (1 if table.side == "positive" else -1) * int(self.mirror[2])
            return CylinderWrap(centre, self.direction(table.axis, f"{fld}.axis"),
                                self.length(table.radius, "wrap_radius", 10.0, f"{fld}.radius"), table.body, side)
        axes = np.column_stack([self.direction(v, f"{fld}.axes[{i}]") for i, v in enumerate(table.axes)])
        if not np.allclose(axes.T @ axes, np.eye(3), atol=1e-6):
            raise InputError("the three directions must be orthogonal", source=self.src, field=f"{fld}.axes")
        axes[:, 2] *= np.sign(np.linalg.det(axes))  # a mirrored knee's axes, right-handed again
        radii = [self.length(r, "wrap_radius", 10.0, f"{fld}.radii") for r in table.radii]
        return EllipsoidWrap(centre, axes, np.array(radii), table.body)

    def bone_path(self, table, fld: str) -> BoneWrap:
        """The path over the surface of the bone ``[bones]`` gives for the table's ``body`` (in that
        body's frame), its field built once per mesh (:func:`~kneenlp.model.bone_wrap.bone_field`)."""
        value = None if self.spec.bones is None else getattr(self.spec.bones, table.body)
        if value is None:
            raise InputError(f"a path over the {table.body}'s surface needs its mesh: give [bones] {table.body}",
                             source=self.src, field=f"{fld}.body")
        if value not in self.bone_fields:
            self.bone_fields[value] = bone_field(self.frame.mesh(self.mesh(value, f"bones.{table.body}")))
        clearance = self.length(table.clearance, "wrap_clearance", 0.0, f"{fld}.clearance", positive=False)
        return BoneWrap(self.bone_fields[value], table.body, clearance, f"{table.body} bone ({value})")

    def check_path(self, bundle: Bundle, fld: str, name: str) -> None:
        """A wrapping obstacle holds neither attachment in the reference pose (one line naming the
        bundle), and one the straight path never meets between 0 and 120 deg flexion at the
        reference laxity pose is noted: the path then stays straight (``name``: the bundle's)."""
        path = bundle.path
        if not isinstance(path, WrapPath):
            return
        R, p = self.reference
        for where in path.inside(bundle.femur, bundle.tibia, R, p):
            raise InputError(f"bundle {name!r}: its {where} attachment lies inside the wrapping {path.shape} in "
                             "the reference pose, where the path is not defined (OpenSim silently runs it straight)",
                             source=self.src, field=fld)
        for where in path.uncovered(bundle.femur, bundle.tibia, R, p) if isinstance(path, BoneWrap) else []:
            raise InputError(f"bundle {name!r}: its {where} attachment lies outside the {path.bone}'s distance field "
                             f"(within {BONE_REACH * 1e3:.0f} mm of the knee's origin), where its path cannot follow "
                             "the bone", source=self.src, field=fld)
        laxity = np.asarray(self.reference_pose[1], float)
        if not any(path.wraps(bundle.femur, bundle.tibia, *reference_transform(np.radians(f), laxity))
                   for f in WRAP_FLEXIONS):
            self.notes.append(f"{fld}: bundle {name!r} never meets its obstacle between 0 and 120 deg flexion "
                              "(its path stays straight)")

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

    def bundles(self, tables: list[BundleTable], fld: str, path: LigamentPath) -> list[Bundle]:
        """The bundles of a multi-bundle ligament: ``[[ligaments.<NAME>.bundles]]`` tables with
        ``name``, ``femur``, ``tibia``, ``stiffness`` (N per unit strain), ``slack_length`` (file
        length unit) or ``ref_strain`` (%), and ``transition_strain`` (OpenSim's, default 0.06) or
        ``lin_strain`` (%, the paper's limit = transition / 2); each bundle's path is its own ``wrap``
        or the ligament's ``path``, and a slack length is of that path's length in the reference pose."""
        src = self.src
        out = []
        for i, b in enumerate(tables):
            f = f"{fld}[{i}]"
            femur, tibia = self.point(b.femur), self.point(b.tibia)
            length = self.check_length(femur, tibia, f)
            self.attach(femur, tibia, f"{f}.femur", f"{f}.tibia")
            own = path if b.wrap is None else self.wrap_path(b.wrap, f"{f}.wrap")
            if not isinstance(own, StraightPath):
                length = own.length(femur, tibia, *self.reference)
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
            out.append(Bundle(femur, tibia, b.name if b.name is not None else f"{fld}{i}", b.stiffness, ref, lin,
                              path=own))
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
