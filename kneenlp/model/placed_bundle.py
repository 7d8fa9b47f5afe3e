"""A one-bundle structure placed on a knee by anatomy (the popliteus tendon, the oblique popliteal
ligament: :mod:`kneenlp.model.structures`): its attachments are offsets from the attachments of a
ligament the knee already has, its stiffness and reference strain default to the medians of
priors from the literature (docs/research/wrapping-and-posterolateral-corner.md, section 4).

A knee file declares one by its table (``[popliteus]``, ``[oblique_popliteal]``)::

    [popliteus]
    candidate = true                # neutral (k = 0): diagnose may free it; false: in the base model
    femur_offset = [4.0, -8.0, -1.0]  # mm, femoral frame (anterior, proximal, lateral), from the anchor's
    tibia_offset = [-5.0, -10.0, -12.0]  # mm, tibial frame, from the anchor's tibial attachment

The offsets are the structure's defaults when not given; the anchor is a ligament of the knee (its
bundles' centroid).  Being anatomical directions of the model's (right) knee, they serve a left
knee's file too (its points are mirrored into the model).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import Field

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.schema import Flag, Number, Point, Table
from kneenlp.model.ligament import Bundle, Ligament
from kneenlp.model.parameters import Parameter


@dataclass(frozen=True)
class Placement:
    """Where and how stiff a placed bundle is by default: the ``anchor`` ligament (every ligament
    whose name starts so: ``PCL`` is PCLal and PCLpm of a knee that splits it), the offsets of
    its femoral and tibial attachments from the anchor's (mm: anterior, proximal, lateral), the
    stiffness's log-normal prior (median N per unit strain, sd of its log) and the reference
    strain's normal prior (mean and sd, fractions)."""

    name: str
    description: str
    anchor: str
    femur_offset: tuple[float, float, float]
    tibia_offset: tuple[float, float, float]
    stiffness: tuple[float, float]
    ref_strain: tuple[float, float]
    lin_strain: float = 0.03  # OpenSim's transition strain 0.06, halved


class PlacedTable(Table):
    """A placed bundle's table: a candidate or part of the base model, and its offsets (mm)."""

    candidate: Flag = Field(False, description="neutral candidate (true) or part of the base model (false)")
    femur_offset: Point | None = None
    tibia_offset: Point | None = None
    stiffness: Number | None = Field(None, description="stiffness (N per unit strain)")
    ref_strain: Number | None = Field(None, description="reference strain (%)")


@dataclass(frozen=True)
class Placed:
    """A declared placed bundle (SI): candidate or not, offsets (m), stiffness, reference strain."""

    candidate: bool
    femur_offset: np.ndarray
    tibia_offset: np.ndarray
    stiffness: float
    ref_strain: float


def reader(placement: Placement):
    """The ``read`` of a :class:`~kneenlp.model.structures.StructureTable` of ``placement``."""

    def read(table: PlacedTable, source: str) -> Placed:
        stiffness = placement.stiffness[0] if table.stiffness is None else table.stiffness
        if stiffness < 0:
            raise InputError("must be >= 0 (N per unit strain)", source=source, field=f"{placement.name}.stiffness")
        return Placed(table.candidate,
                      np.asarray(table.femur_offset or placement.femur_offset, float) * 1e-3,
                      np.asarray(table.tibia_offset or placement.tibia_offset, float) * 1e-3,
                      float(stiffness),
                      placement.ref_strain[0] if table.ref_strain is None else table.ref_strain / 100)

    return read


class PlacedBundle(Ligament):
    """A placed bundle: a one-bundle ligament whose default priors are its placement's."""

    def __init__(self, placement: Placement, bundle: Bundle, placed: Placed, reference):
        defaults = {"k": placed.stiffness, "ref_strain": placed.ref_strain, "lin_strain": placement.lin_strain}
        super().__init__(placement.name, [bundle], candidate=placed.candidate, defaults=defaults,
                         description=placement.description, reference=reference)
        self.placement = placement

    def parameters(self) -> list[Parameter]:
        own = self.placement
        priors = {"k": ("lognormal", own.stiffness[1]), "ref_strain": ("normal", own.ref_strain[1])}
        return [dataclasses.replace(p, prior=priors.get(p.name.rsplit(".", 1)[1], p.prior))
                for p in super().parameters()]


def declared(placement: Placement):
    """The ``declared`` of a :class:`~kneenlp.model.structures.StructureTable` of ``placement``: the
    bundle at the anchor's attachments (the centroid of its bundles) plus the offsets."""

    def build(knee: Any, placed: Placed) -> list[PlacedBundle]:
        bundles = [b for name, lig in knee.ligaments.items() if name.startswith(placement.anchor) for b in lig.bundles]
        if not bundles:
            raise unknown_name("ligament", placement.anchor, list(knee.ligaments)).with_context(
                source=knee.source, field=f"{placement.name} (placed from the {placement.anchor}'s attachments)")
        femur = np.mean([b.femur for b in bundles], axis=0) + placed.femur_offset
        tibia = np.mean([b.tibia for b in bundles], axis=0) + placed.tibia_offset
        return [PlacedBundle(placement, Bundle(femur, tibia), placed, knee.reference_transform)]

    return build


def describe(placement: Placement):
    """The ``describe`` of a :class:`~kneenlp.model.structures.StructureTable` of ``placement``."""

    def line(placed: Placed) -> str:
        role = "a neutral candidate" if placed.candidate else (
            f"part of the base model, {placed.stiffness:g} N per unit strain, reference strain "
            f"{100 * placed.ref_strain:g} %")
        return (f"{placement.name}: {placement.description}, placed from the {placement.anchor}'s attachments "
                f"({role})")

    return line
