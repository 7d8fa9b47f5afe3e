"""The knee file declared as a schema: its tables, their keys, types and which go together
(:class:`~kneenlp.model.knee_file.KneeFile` reads the meshes, fits the frame and checks the
geometry against a knee's: a unit slip, a mirrored knee, an attachment inside a bone).  Lengths
and points are in the file's unit (``units``), angles in degrees."""

from __future__ import annotations

import functools
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, PrivateAttr, create_model, model_validator

from kneenlp.base.conventions import coordinate_columns
from kneenlp.base.modes import FrameMethod
from kneenlp.base.schema import Number, Point, Table, fail
from kneenlp.model.structures import StructureTable, structure_tables

#: The compartments a knee file may describe in ``[contact.<compartment>]`` tables.
COMPARTMENTS = ("medial", "lateral")


def mesh_name(value: object) -> str:
    """A mesh file name (relative to the knee file)."""
    if not isinstance(value, str) or not value:
        raise fail(f"expected a mesh file name, got {value!r}")
    return value


def file_name(value: object) -> str:
    """A parameter file name (relative to the knee file)."""
    if not isinstance(value, str) or not value.strip():
        raise fail(f"expected a parameter file name, got {value!r}")
    return value


def to_working_set(value: object) -> int:
    """Points per compartment and trial of sphere contact (0: every point)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise fail(f"must be an integer >= 0 (0: every point), got {value!r}")
    return value


MeshName = Annotated[str, BeforeValidator(mesh_name)]


class CompartmentTable(Table):
    """``[contact.<compartment>]``: the compartment's tibial cartilage mesh, its femoral mesh or an
    explicit sphere (centre, radius), and its pressure law."""

    tibia: MeshName | None = None
    femur: MeshName | None = None
    sphere_center: Point | None = None
    sphere_radius: Number | None = None
    law: str | None = None

    @model_validator(mode="after")
    def _one_femoral_surface(self) -> CompartmentTable:
        """A femoral mesh or an explicit sphere (both its centre and radius), not both."""
        if (self.sphere_center is None) != (self.sphere_radius is None):
            raise fail("an explicit sphere needs both sphere_center and sphere_radius")
        if self.sphere_center is not None and self.femur is not None:
            raise fail("give either a femoral mesh or an explicit sphere")
        return self


class ContactTable(Table):
    """``[contact]``: the settings of contact (gate, working set, distance-field grid, femoral
    offset: lengths in the file's unit), the meshes shared by both compartments, the pressure law,
    and the compartments' own tables.  The tibial cartilage is given once (split into plateaus) or
    per compartment."""

    gate: Number | None = None
    working_set: Annotated[int, BeforeValidator(to_working_set)] = 0
    grid_spacing: Number | None = None
    femur: MeshName | None = None
    femur_offset: Number | None = None
    tibia: MeshName | None = None
    law: str | None = None
    medial: CompartmentTable | None = None
    lateral: CompartmentTable | None = None
    _order: tuple[str, ...] = PrivateAttr(default=())

    @model_validator(mode="wrap")
    @classmethod
    def _file_order(cls, data: Any, handler: Any) -> ContactTable:
        """Keep the order of the compartments in the file (the order of the knee's elements)."""
        table = handler(data)
        if isinstance(data, dict):
            table._order = tuple(k for k in data if k in COMPARTMENTS and data[k] is not None)
        return table

    @model_validator(mode="after")
    def _tibial_cartilage(self) -> ContactTable:
        """The tibial cartilage once (``contact.tibia``) or in every compartment's table."""
        tables = self.compartments()
        if self.tibia is not None:
            if any(t.tibia is not None for t in tables.values()):
                raise fail("give the tibial cartilage either once for both plateaus or per compartment", "tibia")
            return self
        for name, table in tables.items():
            if table.tibia is None:
                raise fail("missing mesh file", f"{name}.tibia")
        if not tables:
            raise fail("no tibial cartilage: give contact.tibia or [contact.medial] and [contact.lateral]")
        return self

    def compartments(self) -> dict[str, CompartmentTable]:
        """The ``[contact.<compartment>]`` tables, in the file's order."""
        order = self._order or COMPARTMENTS
        return {n: getattr(self, n) for n in order if getattr(self, n) is not None}


class WrapTable(Table):
    """``[ligaments.<NAME>.wrap]`` (every bundle of the ligament) or a bundle's own ``wrap``: the
    obstacle its path wraps, fixed to ``body``, centred at ``centre`` (that body's frame, file
    unit).  A ``cylinder`` (:class:`kneenlp.model.paths.CylinderWrap`, the default shape) along
    ``axis``, of ``radius``, passed on ``side`` (``positive``: counterclockwise about the axis
    going from the tibial to the femoral attachment); an ``ellipsoid``
    (:class:`kneenlp.model.paths.EllipsoidWrap`) of semi-axes ``radii`` (file unit) along ``axes``
    (three orthogonal directions), passed on the side away from its centre; or the ``bone``'s own
    surface (:class:`kneenlp.model.bone_wrap.BoneWrap`: the mesh ``[bones]`` gives for ``body``),
    kept ``clearance`` (file unit, default 0) off it."""

    shape: Literal["cylinder", "ellipsoid", "bone"] = "cylinder"
    body: Literal["femur", "tibia"] = Field(description='body ("femur" or "tibia")')
    centre: Point | None = Field(None, description="centre (a point of the axis)")
    clearance: Number | None = None
    axis: Point | None = None
    radius: Number | None = None
    side: Literal["positive", "negative"] | None = None
    axes: list[Point] | None = Field(None, min_length=3, max_length=3)
    radii: Point | None = None

    @model_validator(mode="after")
    def _keys_of_the_shape(self) -> WrapTable:
        """A cylinder's centre, axis, radius and side; an ellipsoid's centre, axes and radii; a bone
        surface's optional clearance; nothing of another shape."""
        need = {"cylinder": ("centre", "axis", "radius", "side"), "ellipsoid": ("centre", "axes", "radii"), "bone": ()}
        own = {**need, "bone": ("clearance",)}[self.shape]
        for key in need[self.shape]:
            if getattr(self, key) is None:
                raise fail(f"a wrapping {self.shape} needs {key}", key)
        for key in ("centre", "axis", "radius", "side", "axes", "radii", "clearance"):
            if key not in own and getattr(self, key) is not None:
                shape = next(n for n, keys in {**need, "bone": ("clearance",)}.items() if key in keys)
                raise fail(f"{key} belongs to a {shape}, not a {self.shape}", key)
        return self


class BundleTable(Table):
    """``[[ligaments.<NAME>.bundles]]``: attachments, ``stiffness`` (N per unit strain),
    ``slack_length`` (file unit) or ``ref_strain`` (%), ``transition_strain`` (OpenSim's,
    default 0.06) or ``lin_strain`` (%), and the obstacle its own path wraps (``wrap``, in place of
    the ligament's)."""

    name: str | None = None
    femur: Point = Field(description="attachment")
    tibia: Point = Field(description="attachment")
    stiffness: Number = Field(description="stiffness (N per unit strain)")
    slack_length: Number | None = None
    ref_strain: Number | None = None
    transition_strain: Number | None = None
    lin_strain: Number | None = None
    wrap: WrapTable | None = None


class SlackShiftTable(Table):
    """``[ligaments.<NAME>.slack_shift]``: the group's reference-strain offset moves every bundle's
    slack length by one length, as the FE model's group (:class:`kneenlp.model.ligament.SlackShift`):
    the group's reference ``length`` (file unit, Abaqus ``L``) and ``ref_strain`` (%, ``EREF - 1``)."""

    length: Number = Field(description="the group's reference length (file unit)")
    ref_strain: Number = Field(description="the group's reference strain (%)")


class ViaTable(Table):
    """``[ligaments.<NAME>.via]``: every bundle's path runs through ``tibia`` points (tibial frame,
    from its attachment outwards), then ``femur`` points (femoral frame, towards its attachment)."""

    tibia: list[Point] = Field(default_factory=list)
    femur: list[Point] = Field(default_factory=list)


class LigamentTable(Table):
    """``[ligaments.<NAME>]``: one bundle's attachments (femur in the femoral frame, tibia in the
    tibial one) or ``bundles`` (and how their slack moves, ``slack_shift``), the law and, given,
    the cylinder every bundle's path wraps (``wrap``) or its via points (``via``; straight paths
    by default)."""

    femur: Point | None = None
    tibia: Point | None = None
    bundles: list[BundleTable] | None = Field(None, min_length=1)
    slack_shift: SlackShiftTable | None = None
    law: str | None = None
    wrap: WrapTable | None = None
    via: ViaTable | None = None

    @model_validator(mode="after")
    def _attachments(self) -> LigamentTable:
        """Both attachments of a single-bundle ligament."""
        if self.bundles is None:
            for key in ("femur", "tibia"):
                if getattr(self, key) is None:
                    raise fail("missing attachment", key)
            if self.slack_shift is not None:
                raise fail("a slack shift needs [[bundles]] with their own properties", "slack_shift")
        return self


class CandidateTable(Table):
    """``[candidates.<NAME>]``: a candidate effect of model adequacy, a bundle (``kind =
    "bundle"``) per pair of ``femur`` and ``tibia`` points, ``ref_strain`` (%)."""

    kind: Literal["bundle"] = Field(description='kind (kind = "bundle")')
    description: str = ""
    femur: list[Point] = Field(min_length=1, description="attachments")
    tibia: list[Point] = Field(min_length=1, description="attachments")
    ref_strain: Number = 0.0

    @model_validator(mode="after")
    def _pairs(self) -> CandidateTable:
        """One tibial point per femoral point."""
        if len(self.femur) != len(self.tibia):
            raise fail("femur and tibia must be equally long lists of [x, y, z]")
        return self


#: ``[reference_pose]``: the imaged pose of the tibial frame in the femoral frame (deg, mm).
ReferencePose = create_model(
    "ReferencePose", __base__=Table, __doc__="The imaged pose (flexion and the five coordinates; deg, mm).",
    **{k: (Number, Field(description="(give all six coordinates of the imaged pose)"))
       for k in ["flexion_deg", *coordinate_columns()]})


class BonesTable(Table):
    """``[bones]``: the bones' surfaces (closed meshes, in the coordinates of the contact meshes:
    the femur's as ``contact.femur``, the tibia's as the tibial cartilage), read only to check that no
    ligament attachment lies inside a bone (an articular surface alone cannot tell the inside of a
    condyle from the intercondylar notch)."""

    femur: MeshName | None = None
    tibia: MeshName | None = None


class KneeTables(Table):
    """A knee file: name, side, units (of every length and point), coordinates (``femoral`` or
    ``scan``, then mapped by ``frame``), the parameter file, the reference pose, landmarks, contact,
    bones, ligaments, candidate effects; :data:`KneeDocument` adds the structures' tables."""

    name: str | None = None
    description: str = ""
    side: Literal["right", "left"] = "right"
    units: Literal["mm", "m"] = "mm"
    coordinates: Literal["femoral", "scan"] = "femoral"
    frame: FrameMethod | None = None
    parameters: Annotated[str, BeforeValidator(file_name)] | None = None
    reference_pose: ReferencePose | None = None
    landmarks: dict[str, Point] = Field(default_factory=dict)
    contact: ContactTable = Field(default_factory=dict, validate_default=True)
    bones: BonesTable | None = None
    ligaments: dict[str, LigamentTable] = Field(min_length=1, description="table [ligaments.<NAME>]")
    candidates: dict[str, CandidateTable] = Field(default_factory=dict)


def knee_document() -> type[KneeTables]:
    """The schema of a knee file: :class:`KneeTables` and every built-in structure's table
    (:func:`~kneenlp.model.structures.structure_tables`)."""
    return _knee_document(structure_tables())


@functools.cache
def _knee_document(tables: tuple[StructureTable, ...]) -> type[KneeTables]:
    return create_model("KneeDocument", __base__=KneeTables, __doc__=KneeTables.__doc__,
                        **{t.name: (t.schema | None, None) for t in tables if t.schema is not None})
