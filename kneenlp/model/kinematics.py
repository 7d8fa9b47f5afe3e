"""Tibial pose from Grood & Suntay joint coordinates (see :mod:`kneenlp.conventions`).

All functions take CasADi symbols or numbers in SI units (rad, m) and return CasADi
expressions, so the same code serves the symbolic model and numerical evaluation.
"""

from __future__ import annotations

import casadi as ca


def rot_x(a):
    """Rotation matrix about X by angle ``a`` (rad)."""
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(1, 0, 0), ca.horzcat(0, c, -s), ca.horzcat(0, s, c))


def rot_y(a):
    """Rotation matrix about Y by angle ``a`` (rad)."""
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(c, 0, s), ca.horzcat(0, 1, 0), ca.horzcat(-s, 0, c))


def rot_z(a):
    """Rotation matrix about Z by angle ``a`` (rad)."""
    c, s = ca.cos(a), ca.sin(a)
    return ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))


def tibial_pose(flexion, q):
    """Pose of the tibial frame in the femoral frame.

    Parameters
    ----------
    flexion : knee flexion angle (rad), positive = flexed.
    q : the five free coordinates ``[varus, internal, lateral, anterior, proximal]`` (rad, m).

    Returns
    -------
    R : 3x3 rotation, tibial -> femoral frame.
    p : 3-vector, tibial origin in the femoral frame (m).
    axes : ``(e1, e2, e3)`` the Grood & Suntay axes (flexion, floating, tibial long axis).
    """
    rz = rot_z(-flexion)  # right knee, Z lateral: flexion is a negative rotation about Z
    R = rz @ rot_x(q[0]) @ rot_y(q[1])
    e1 = ca.DM([0.0, 0.0, 1.0])
    e2 = rz[:, 0]  # floating axis: unit vector, perpendicular to e1 and e3
    e3 = R[:, 1]
    p = q[2] * e1 + q[3] * e2 + q[4] * e3
    return R, p, (e1, e2, e3)


def generalized_forces(q, p, axes, force, moment):
    """Virtual-work generalised forces of a wrench on the tibia for the five free coordinates.

    ``force`` (N) and ``moment`` (N m, about the tibial origin ``p``) are in the femoral frame.
    Returns ``[M_varus, M_internal, F_lateral, F_anterior, F_proximal]`` (N m, N m, N, N, N):
    the rotation entries are moments about the floating and tibial axes, the translation entries
    include the small terms from the non-orthogonality of the Grood & Suntay axes.
    """
    _, e2, e3 = axes
    jac_p = ca.jacobian(p, q)  # 3x5 translational Jacobian
    jac_w = ca.horzcat(e2, e3, ca.DM.zeros(3, 3))  # angular-velocity Jacobian
    return jac_p.T @ force + jac_w.T @ moment
