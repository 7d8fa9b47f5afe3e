"""Menisci that deform: ``[meniscal_rim]`` in a knee file, beside or instead of the springs of
``[menisci]`` (:mod:`.meniscus`).

Each compartment's meniscus is a rim of ``nodes`` points on a circle of ``radius`` about the
condyle's rest position over the plateau (in the tibial transverse plane X-Z, ``depth`` below the
condyle centre), carried by the tibia.  A node moves along its outward radial direction ``n_i``
by ``u_i`` (m) and is

* held by the horn and coronary attachments: a radial spring ``k_n`` per node;
* held by its neighbours through the hoop: springs along the rim's chords, stiffness
  ``ratio * k_n``, each stretched by ``sin(pi / N)`` times the radial moves of its two ends;
* pushed by the condyle where the condyle moves towards it: a contact spring ``k_c`` switched on
  by a smooth step (width :data:`SWITCH`) of the condyle centre's transverse move towards the node,
  ``d_i = n_i . (c - c_rest)`` (tibial frame).

The switch depends on the condyle's move, not on ``u``, so the nodes' balance is linear,
``(k_n (I + ratio s^2 A'A) + k_c W) u = k_c W d`` (``A`` the chords' incidence, ``s = sin(pi/N)``,
``W`` the switches): one symbolic solve of ``N`` unknowns a compartment inside the residual, so no
unknown joins the NLP and its derivatives stay exact.  The condyle's contact forces
``f_i = k_c w_i (d_i - u_i)`` act on the tibia at the nodes along ``n_i`` (the massless meniscus
passes them on through its attachments and the plateau) and on the femur opposite.  Against a
transverse move ``delta`` of the condyle, a rim without hoop and with a stiff contact pushes back
with ``k_n N / 4 delta``; ``meniscal_rim.k`` is that stiffness (N/mm per compartment, so
``k_n = 4 k / N``), the springs' ``meniscus.k`` of the same size, and the hoop spreads the push
over the rim (a hoop-stiff rim moves as a ring: about twice that).

Defaults: ``k`` the Lenhart knee's springs (5 N/mm), log-normal prior sd 0.7 of its log; the hoop
``ratio`` 300: a circumferential tensile modulus of 100-300 MPa (Fithian, Kelly and Mow 1990, Clin
Orthop 252:19) on a 20-40 mm^2 section over a chord of about 10 mm gives 200-1200 N/mm a chord,
against 1.7 N/mm a node; the contact 100 N/mm a node (stiff beside the attachments); 12 nodes on a
radius of 18 mm, 20 mm below the condyle centre (a meniscus's inner rim, a condyle's radius of
curvature).  With ``candidate = true`` it is neutral (``k`` = 0: no force at all), for
``diagnose``.  The rim is planar: the wedge's share of the compressive load is the cartilage
contact's, as in the springs.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
from pydantic import Field

from kneenlp.base.errors import InputError
from kneenlp.base.schema import Flag, Number, Table
from kneenlp.model.elements import ForceElement, Output, Pose
from kneenlp.model.parameters import UNIT_FACTORS, Parameter
from kneenlp.model.structures import KneeGeometry, StructureTable

#: Width (m) of the smooth step that switches a node's contact on as the condyle moves towards it.
SWITCH = 1e-4
#: Radial stiffness (N/m per compartment) below which the balance is solved at this one and the
#: force scaled down to zero (a neutral candidate's k = 0 leaves the nodes' balance singular).
K_FLOOR = 1.0
#: Default prior width of ``meniscal_rim.k`` (sd of its log).
PRIOR_SD = 0.7


class MeniscalRimTable(Table):
    """``[meniscal_rim]``: the rim's stiffness (N/mm per compartment) and shape."""

    candidate: Flag = Field(False, description="neutral candidate (true) or part of the base model (false)")
    stiffness: Number = Field(5.0, description="radial stiffness against a transverse move of the condyle "
                                               "(N/mm per compartment)")
    hoop_ratio: Number = Field(300.0, description="a chord's hoop stiffness over a node's radial stiffness")
    contact: Number = Field(100.0, description="contact stiffness between condyle and rim (N/mm per node)")
    nodes: int = Field(12, description="nodes on each rim")
    radius: Number = Field(18.0, description="the rim's radius (mm)")
    depth: Number = Field(20.0, description="the rim below the condyle centre (mm)")


class MeniscalRim(ForceElement):
    """The deforming rims of every compartment (module docstring); SI inside."""

    name = "meniscal_rim"
    description = "menisci as rims with radial attachments and hoop stiffness"

    def __init__(self, rest: list[np.ndarray], rim: MeniscalRimTable, centres: list[np.ndarray],
                 names: list[str] | None = None):
        self.centres = [np.asarray(c, float) for c in centres]  # femoral frame, m
        self.rest = [np.asarray(c, float) for c in rest]  # tibial frame, m
        self.names = names or [f"c{i}" for i in range(len(self.rest))]
        self.candidate = rim.candidate
        self.stiffness = rim.stiffness * UNIT_FACTORS["spring"]["N/mm"]
        self.hoop_ratio, self.nodes = float(rim.hoop_ratio), int(rim.nodes)
        self.contact = rim.contact * UNIT_FACTORS["spring"]["N/mm"]
        angles = 2 * np.pi * np.arange(self.nodes) / self.nodes
        #: outward radial directions of the nodes (tibial frame, N x 3: anterior first, then lateral)
        self.directions = np.stack([np.cos(angles), np.zeros_like(angles), np.sin(angles)], axis=1)
        self.radius, self.depth = rim.radius * 1e-3, rim.depth * 1e-3
        chords = np.eye(self.nodes) + np.roll(np.eye(self.nodes), 1, axis=1)
        s = np.sin(np.pi / self.nodes)
        #: the rim's own stiffness per unit k_n: attachments plus hoop
        self.structure = np.eye(self.nodes) + self.hoop_ratio * s**2 * chords.T @ chords

    def parameters(self) -> list[Parameter]:
        value = 0.0 if self.candidate else self.stiffness
        return [Parameter("meniscal_rim.k", "spring", "meniscal rim radial stiffness per compartment", value,
                          0.0 if self.candidate else None, prior=("lognormal", PRIOR_SD))]

    def node_points(self, rest: np.ndarray) -> np.ndarray:
        """The rim's nodes of the compartment resting at ``rest`` (tibial frame, m, N x 3)."""
        return rest + self.radius * self.directions - np.array([0.0, self.depth, 0.0])

    def node_forces(self, c: ca.SX, rest: np.ndarray, k: ca.SX) -> ca.SX:
        """The condyle's contact forces on the nodes (N, along their outward directions) with its
        centre at ``c`` (tibial frame, m) and the rim's stiffness ``k`` (N/m per compartment)."""
        k_eff = ca.fmax(k, K_FLOOR)
        d = ca.mtimes(ca.DM(self.directions), c - ca.DM(rest))
        w = 0.5 * (1 + ca.tanh(d / SWITCH))
        k_n = 4 * k_eff / self.nodes
        system = k_n * ca.DM(self.structure) + self.contact * ca.diag(w)
        u = ca.solve(system, self.contact * w * d)
        return (k / k_eff) * self.contact * w * (d - u)

    def wrench(self, pose: Pose, values: dict) -> tuple[ca.SX, ca.SX]:
        k = values["meniscal_rim.k"]
        force, moment = ca.SX.zeros(3), ca.SX.zeros(3)
        for centre, rest in zip(self.centres, self.rest, strict=True):
            f = self.node_forces(pose.to_tibial(centre), rest, k)
            for i, at in enumerate(self.node_points(rest)):
                f_t = f[i] * ca.DM(self.directions[i])  # on the tibia, tibial frame
                force += pose.R @ f_t
                moment += pose.R @ ca.cross(ca.DM(at), f_t)
        return force, moment

    def outputs(self) -> list[Output]:
        return [Output("force", f"meniscal_rim_{n}_N", "N") for n in self.names]

    def output_values(self, pose: Pose, values: dict) -> list[ca.SX]:
        k = values["meniscal_rim.k"]
        out = []
        for centre, rest in zip(self.centres, self.rest, strict=True):
            f = self.node_forces(pose.to_tibial(centre), rest, k)
            total = ca.mtimes(ca.DM(self.directions).T, f)
            out.append(ca.norm_2(total))
        return out


def read(table: MeniscalRimTable, source: str) -> MeniscalRimTable:
    """The rim's table, checked."""
    for key in ("stiffness", "hoop_ratio", "contact", "radius", "depth"):
        if not getattr(table, key) >= 0:
            raise InputError("must be >= 0", source=source, field=f"meniscal_rim.{key}")
    if not 4 <= table.nodes <= 64:
        raise InputError(f"must be between 4 and 64, got {table.nodes}", source=source, field="meniscal_rim.nodes")
    if table.contact <= 0 or table.radius <= 0:
        raise InputError("the contact stiffness and the radius must be > 0", source=source, field="meniscal_rim")
    return table


def declared(knee: KneeGeometry, table: MeniscalRimTable) -> list[ForceElement]:
    return [MeniscalRim(knee.condyle_rest(), table, knee.condyle_centres(), list(knee.compartments))]


def describe(table: MeniscalRimTable) -> str:
    what = "a neutral candidate" if table.candidate else f"{table.stiffness:g} N/mm per compartment"
    return (f"meniscal_rim: {table.nodes} nodes on a {table.radius:g} mm rim per compartment, hoop ratio "
            f"{table.hoop_ratio:g}, {what}")


TABLE = StructureTable("meniscal_rim", MeniscalRimTable, read, declared, lambda knee: [], describe)
