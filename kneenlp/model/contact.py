"""Elastic-foundation contact between a femoral condyle and a tibial cartilage surface.

Each compartment (medial, lateral) pairs a femoral condyle, represented by the sphere fitted to
its cartilage surface (centre ``c``, radius ``R``), with the tibial cartilage surface, represented
by the centroids ``x_i`` and areas ``A_i`` of its mesh faces.  At each tibial point the penetration
is measured along the sphere's normal, ``d_i = R - |x_i - c|``; the pressure is
``p_i = K g(d_i)`` with the pressure modulus ``K`` (10 GN/m^3 in the paper) and the contact gate
``g`` (:func:`kneenlp.model.laws.gate`), a C2 polynomial smoothing of ``max(d, 0)`` over ``0 < d <
delta`` that is exactly zero without penetration and exactly ``d`` beyond ``delta`` (the paper's
linear law there; :mod:`kneenlp.geometry.ramp`); another pressure law of
:mod:`kneenlp.model.laws` may replace it.
``delta`` = 0.01 mm by default, far below the penetrations that carry load (0.1-1 mm).  The force on the tibia is
``sum_i p_i A_i (x_i - c) / |x_i - c|`` and its moment about the tibial origin follows from the
same sums:  with ``s_i = p_i A_i / |x_i - c|``, ``S0 = sum s_i`` and ``S1 = sum s_i x_i``,
force ``F = S1 - c S0`` and moment ``M = c x S1``.

The computation over all points is a handful of dense vector operations (squared distances from
``|x|^2 - 2 x.c + |c|^2``), so that derivatives and generated code stay small whatever the number
of points (the lesson of ``shared/notes/formulation-facts.md``; measured 3-7x faster than mapping
a per-point SX function).  Everything is in the tibial frame
and SI units.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from kneenlp.model.elements import Output, Pose, StagedElement
from kneenlp.model.laws import NUMPY, ElasticFoundation, PressureLaw
from kneenlp.model.parameters import Parameter

if TYPE_CHECKING:
    from kneenlp.model.articular import Compartment

#: The cartilage pressure modulus, shared by every contact element.
MODULUS = Parameter("contact.modulus", "modulus", "elastic-foundation pressure modulus")


def sphere_wrench(sphere: tuple, modulus, samples: tuple, delta: float, law: PressureLaw | None = None):
    """Force and moment (about the tibial origin) on the tibia of a sphere ``sphere = (c, radius)``
    (centre ``c``, tibial frame, radius in m) with the pressure ``modulus`` pressed into ``samples
    = (x, areas)``: sample points ``x`` (3 x N) with ``areas`` (1 x N), tibial frame; the points may
    be constants or symbols; ``delta`` the gate width (m).  A few vector operations whatever ``N``
    is: with ``s_i = p_i A_i / |x_i - c|``, ``S0 = sum s_i`` and ``S1 = sum s_i x_i``,
    force ``F = S1 - c S0`` and moment ``M = c x S1``."""
    c, radius = sphere
    x, areas = samples
    sq = ca.sum1(x * x)  # 1 x N
    dist = ca.sqrt(sq - 2 * (c.T @ x) + ca.dot(c, c))
    s = (law or ElasticFoundation()).pressure(radius - dist, modulus, delta) * areas / dist
    s1 = x @ s.T
    return s1 - c * ca.sum2(s), ca.cross(c, s1)


def compartment_function(name: str, points: np.ndarray, areas: np.ndarray, delta: float) -> ca.Function:
    """Contact wrench of one compartment with every point, ``(c, K, R) -> (force, moment)`` in the
    tibial frame (:func:`sphere_wrench` with the points as constants).

    ``points`` (N, 3) tibial cartilage samples (tibial frame, m), ``areas`` (N,) m^2, ``delta``
    gate width (m).  Inputs: sphere centre ``c`` in the tibial frame (m), modulus ``K`` (N/m^3),
    radius ``R`` (m); outputs: force on the tibia (N), moment about the tibial origin (N m).
    """
    points = np.asarray(points, dtype=float)
    c, modulus, radius = ca.MX.sym("c", 3), ca.MX.sym("K"), ca.MX.sym("R")
    force, moment = sphere_wrench((c, radius), modulus, (ca.DM(points.T), ca.DM(np.asarray(areas, float).ravel()).T),
                                  delta)
    return ca.Function(f"contact_{name}", [c, modulus, radius], [force, moment], ["c", "K", "R"],
                       ["force", "moment"])


def sphere_plane_force(modulus: float, radius: float, depth: float) -> float:
    """Closed-form normal force (N) of a sphere pressed ``depth`` (m) into a flat foundation.

    With penetration measured along the sphere's normal (as in :func:`compartment_function`),
    ``F = pi K d^2 (R - d)``.  (Measured along the plane normal instead it is the cap volume times
    ``K``, ``pi K d^2 (R - d/3)``; both tend to ``pi K R d^2`` for ``d << R``.)
    """
    return float(np.pi * modulus * depth**2 * (radius - depth))


class SphereContact(StagedElement):
    """Elastic-foundation contact of one compartment: a femoral sphere (centre in the femoral
    frame, radius, m) against tibial cartilage samples (tibial frame, m; areas m^2): those of
    ``compartment``, with its pressure law; ``gate`` its width (m).

    The sphere is an explicit analytic choice of the knee file, never an approximation of a mesh.
    Parameter: ``contact.modulus`` (shared by every compartment).  Outputs: the contact force
    magnitude (N) and the largest penetration (mm).
    """

    def __init__(self, compartment: Compartment, gate: float, working_set_size: int = 0):
        self.name, self.compartment = f"contact_{compartment.name}", compartment.name
        self.law = compartment.law or ElasticFoundation()
        self.centre, self.radius = np.asarray(compartment.centre, float), float(compartment.sphere_radius)
        self.points, self.areas = np.asarray(compartment.points, float), np.asarray(compartment.areas, float)
        self.gate = float(gate)
        self.working_set_size = int(working_set_size)
        self.description = f"{compartment.name} compartment: sphere vs tibial cartilage"

    def parameters(self) -> list[Parameter]:
        return [MODULUS]

    def probe(self, pose: Pose, values: dict) -> ca.SX:
        return ca.vertcat(pose.to_tibial(self.centre), values[MODULUS.name])

    def surface_wrench(self, probe, data):
        return sphere_wrench((probe[:3], self.radius), probe[3], (data[:3, :], data[3, :]), self.gate, self.law)

    def clearance(self, R, p, values):
        centre = np.asarray(R).T @ (self.centre - np.asarray(p).ravel())
        return np.linalg.norm(self.points - centre, axis=1) - self.radius

    def pressure(self, R: np.ndarray, p: np.ndarray, modulus: float) -> dict[str, np.ndarray]:
        """The contact at a pose (numeric, every point), as :meth:`MeshContact.pressure`: per-point
        penetration (m) and pressure (Pa), force on the tibia (N) and moment about the tibial origin
        (N m) in the femoral frame, centre of pressure (femoral frame, m; NaN without contact)."""
        R, p = np.asarray(R, float), np.asarray(p, float).ravel()
        X = self.points @ R.T + p
        diff = X - self.centre
        dist = np.linalg.norm(diff, axis=1)
        pen = self.radius - dist
        pres = self.law.pressure(pen, modulus, self.gate, NUMPY)
        f = diff / dist[:, None] * (pres * self.areas)[:, None]
        w = pres * self.areas
        cop = (X * w[:, None]).sum(axis=0) / w.sum() if w.sum() > 0 else np.full(3, np.nan)
        return {"penetration": pen, "pressure": pres, "force": f.sum(axis=0),
                "moment": np.cross(X - p, f).sum(axis=0), "cop": cop}

    def outputs(self) -> list[Output]:
        return [Output("force", f"contact_{self.compartment}_N", "N"),
                Output("penetration", f"penetration_{self.compartment}_mm", "mm", 1e3)]

    def report(self, probe: ca.MX, data, force: ca.MX) -> list[ca.MX]:
        diff = data[:3, :] - ca.repmat(probe[:3], 1, data.shape[1])
        return [ca.norm_2(force), self.radius - ca.sqrt(ca.mmin(ca.sum1(diff * diff)))]
