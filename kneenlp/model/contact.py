"""Elastic-foundation contact between a femoral condyle and a tibial cartilage surface.

Each compartment (medial, lateral) pairs a femoral condyle, represented by the sphere fitted to
its cartilage surface (centre ``c``, radius ``R``), with the tibial cartilage surface, represented
by the centroids ``x_i`` and areas ``A_i`` of its mesh faces.  At each tibial point the penetration
is measured along the sphere's normal, ``d_i = R - |x_i - c|``; the pressure is
``p_i = K g(d_i)`` with the pressure modulus ``K`` (10 GN/m^3 in the paper) and the contact gate
``g`` (:func:`smooth_gate`), a C2 polynomial smoothing of ``max(d, 0)`` over ``0 < d < delta``
that is exactly zero without penetration and exactly ``d - delta/2`` beyond ``delta``.
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

import casadi as ca
import numpy as np

from kneenlp.model.elements import Output, Pose, StagedElement
from kneenlp.model.parameters import Parameter

#: The cartilage pressure modulus, shared by every contact element.
MODULUS = Parameter("contact.modulus", "modulus", "elastic-foundation pressure modulus")


def smooth_gate(d, delta):
    """C2-smooth ``max(d, 0)``: zero for ``d <= 0``, ``d - delta/2`` for ``d >= delta``.

    In between ``g = d^3/delta^2 - d^4/(2 delta^3)``; value, slope and curvature are continuous
    at both ends, and points that do not penetrate contribute exactly zero.
    """
    t = ca.fmin(ca.fmax(d, 0), delta)
    t2 = t * t
    return t2 * t * (1 / delta**2) - t2 * t2 * (1 / (2 * delta**3)) + (ca.fmax(d, delta) - delta)


def compartment_function(name: str, points: np.ndarray, areas: np.ndarray, delta: float) -> ca.Function:
    """Contact wrench of one compartment, ``(c, K, R) -> (force, moment)`` in the tibial frame.

    Parameters
    ----------
    points : (N, 3) tibial cartilage sample points, tibial frame, m.
    areas : (N,) area of each sample (m^2).
    delta : gate width (m).

    The returned function's inputs are the condyle sphere centre ``c`` in the tibial frame (m),
    the pressure modulus ``K`` (N/m^3) and the sphere radius ``R`` (m); outputs are the force on
    the tibia (N) and its moment about the tibial origin (N m).  The points enter as constant
    vectors, so the graph has a few dozen vector operations whatever ``N`` is.
    """
    points = np.asarray(points, dtype=float)
    areas = np.asarray(areas, dtype=float).ravel()
    x = ca.DM(points.T)  # 3 x N
    c = ca.MX.sym("c", 3)
    modulus = ca.MX.sym("K")
    radius = ca.MX.sym("R")
    dist2 = ca.DM(np.sum(points**2, axis=1)).T - 2 * (c.T @ x) + ca.dot(c, c)  # 1 x N
    dist = ca.sqrt(dist2)
    s = modulus * ca.DM(areas).T * smooth_gate(radius - dist, delta) / dist
    s0 = ca.sum2(s)
    s1 = x @ s.T
    force = s1 - c * s0
    moment = ca.cross(c, s1)
    return ca.Function(
        f"contact_{name}", [c, modulus, radius], [force, moment], ["c", "K", "R"], ["force", "moment"]
    )


def sphere_plane_force(modulus: float, radius: float, depth: float) -> float:
    """Closed-form normal force (N) of a sphere pressed ``depth`` (m) into a flat foundation.

    With penetration measured along the sphere's normal (as in :func:`compartment_function`),
    ``F = pi K d^2 (R - d)``.  (Measured along the plane normal instead it is the cap volume times
    ``K``, ``pi K d^2 (R - d/3)``; both tend to ``pi K R d^2`` for ``d << R``.)
    """
    return float(np.pi * modulus * depth**2 * (radius - depth))


class SphereContact(StagedElement):
    """Elastic-foundation contact of one compartment: a femoral sphere (centre in the femoral
    frame, radius, m) against tibial cartilage samples (tibial frame, m; areas m^2).

    The sphere is an explicit analytic choice of the knee file, never an approximation of a mesh.
    Parameter: ``contact.modulus`` (shared by every compartment).  Outputs: the contact force
    magnitude (N) and the largest penetration (mm).
    """

    def __init__(self, compartment: str, centre: np.ndarray, radius: float, points: np.ndarray,
                 areas: np.ndarray, gate: float):
        self.name, self.compartment = f"contact_{compartment}", compartment
        self.centre, self.radius = np.asarray(centre, float), float(radius)
        self.points, self.areas, self.gate = np.asarray(points, float), np.asarray(areas, float), float(gate)
        self.description = f"{compartment} compartment: sphere vs tibial cartilage"

    def parameters(self) -> list[Parameter]:
        return [MODULUS]

    def probe(self, pose: Pose, values: dict) -> ca.SX:
        return ca.vertcat(pose.to_tibial(self.centre), values[MODULUS.name])

    def surface(self) -> ca.Function:
        fn = compartment_function(self.compartment, self.points, self.areas, self.gate)
        probe = ca.MX.sym("probe", 4)
        force, moment = fn(probe[:3], probe[3], self.radius)
        return ca.Function(f"surface_{self.compartment}", [probe], [force, moment], ["probe"], ["force", "moment"])

    def outputs(self) -> list[Output]:
        return [Output("force", f"contact_{self.compartment}_N", "N"),
                Output("penetration", f"penetration_{self.compartment}_mm", "mm", 1e3)]

    def report(self, probe: ca.MX, force: ca.MX) -> list[ca.MX]:
        pts = ca.DM(self.points.T)
        diff = pts - ca.repmat(probe[:3], 1, pts.shape[1])
        return [ca.norm_2(force), self.radius - ca.sqrt(ca.mmin(ca.sum1(diff * diff)))]
