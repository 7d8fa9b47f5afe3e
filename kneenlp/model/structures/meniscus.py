"""The menisci as springs: ``[menisci] stiffness`` (N/mm per compartment) in a knee file.

:class:`Meniscus` holds each femoral condyle's centre to its rest position over the plateau by a
spring in the tibial transverse plane (X, Z of the tibial frame): the menisci's resistance to
condylar translation.  A knee file that declares ``[menisci]`` carries it in its base model with
that stiffness (the Lenhart knee, whose segmented cartilage has no menisci: 5 N/mm); every other
knee carries it as a candidate (``meniscus.k`` neutral 0) that model adequacy may free.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
from pydantic import Field

from kneenlp.base.errors import InputError
from kneenlp.base.schema import Number, Table
from kneenlp.model.elements import ForceElement, Pose
from kneenlp.model.parameters import KINDS, UNIT_FACTORS, Parameter
from kneenlp.model.structures import KneeGeometry, StructureTable


class MenisciTable(Table):
    """``[menisci]``: the meniscus springs' stiffness (N/mm per compartment)."""

    stiffness: Number = Field(description="stiffness (N/mm per compartment)")


class Meniscus(ForceElement):
    """Springs (N/m) between each condyle centre and its reference position over the plateau,
    acting in the tibial transverse plane (X, Z of the tibial frame).  ``meniscus.k`` in N/mm;
    ``stiffness`` None: a candidate (neutral 0)."""

    name = "meniscus"
    description = "menisci: resistance to condylar translation over the plateau"

    def __init__(self, centres: list[np.ndarray], stiffness: float | None = None,
                 rest: list[np.ndarray] | None = None):
        self.centres = [np.asarray(c, float) for c in centres]  # femoral frame, m
        #: where each centre sits over the plateau with the springs relaxed (tibial frame, m): at
        #: the knee's reference pose (the centres themselves where that pose is the identity)
        self.rest = [np.asarray(c, float) for c in (rest if rest is not None else centres)]
        self.stiffness = stiffness  # N/m, None: a candidate
        self.candidate = stiffness is None

    def parameters(self) -> list[Parameter]:
        if self.candidate:
            return [Parameter("meniscus.k", "spring", "meniscal spring stiffness per compartment", 0.0, 0.0)]
        return [Parameter("meniscus.k", "spring", "meniscal spring stiffness per compartment", self.stiffness)]

    def wrench(self, pose: Pose, values: dict) -> tuple[ca.SX, ca.SX]:
        k = values["meniscus.k"]
        force, moment = ca.SX.zeros(3), ca.SX.zeros(3)
        mask = ca.DM([1.0, 0.0, 1.0])
        for ref, rest in zip(self.centres, self.rest, strict=True):
            c = pose.to_tibial(ref)
            f_t = k * mask * (c - ca.DM(rest))  # on the tibia, tibial frame
            force += pose.R @ f_t
            moment += pose.R @ ca.cross(c, f_t)
        return force, moment


def read(table: MenisciTable, source: str) -> float:
    """The springs' stiffness (N/m per compartment) of a ``[menisci]`` table."""
    if table.stiffness < 0:
        raise InputError("must be >= 0", source=source, field="menisci.stiffness")
    return table.stiffness * UNIT_FACTORS["spring"]["N/mm"]


def declared(knee: KneeGeometry, stiffness: float) -> list[ForceElement]:
    return [Meniscus(knee.condyle_centres(), stiffness, knee.condyle_rest())]


def candidates(knee: KneeGeometry) -> list[ForceElement]:
    return [Meniscus(knee.condyle_centres(), rest=knee.condyle_rest())]


def describe(stiffness: float) -> str:
    return (f"menisci: transverse springs of {stiffness * KINDS['spring'].to_user:g} N/mm per compartment at the "
            "condyle centres (part of the base model)")


TABLE = StructureTable("menisci", MenisciTable, read, declared, candidates, describe)
