"""Tibial pose from Grood & Suntay joint coordinates (see :mod:`kneenlp.base.conventions`).

All functions take CasADi symbols or numbers in SI units (rad, m) and return CasADi
expressions, so the same code serves the symbolic model and numerical evaluation.
"""

from __future__ import annotations

import casadi as ca
import numpy as np


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


def joint_coordinates(R, p) -> tuple[float, np.ndarray]:
    """Inverse of :func:`tibial_pose`: flexion (rad) and the five free coordinates (rad, m) of the
    tibial frame with rotation ``R`` (tibial -> femoral) and origin ``p`` (femoral frame, m).

    ``e3 = R[:, 1] = (cos v sin f, cos v cos f, sin v)`` gives flexion ``f`` and varus ``v``;
    ``Ry(i) = (Rz(-f) Rx(v))^T R`` gives the internal rotation; the translations solve
    ``p = lateral e1 + anterior e2 + proximal e3``."""
    R, p = np.asarray(R, dtype=float), np.asarray(p, dtype=float).ravel()
    e3 = R[:, 1]
    varus = float(np.arcsin(np.clip(e3[2], -1.0, 1.0)))
    flexion = float(np.arctan2(e3[0], e3[1]))
    base = np.asarray(rot_z(-flexion) @ rot_x(varus))
    ry = base.T @ R
    internal = float(np.arctan2(ry[0, 2], ry[0, 0]))
    e1 = np.array([0.0, 0.0, 1.0])
    e2 = base[:, 0]
    lateral, anterior, proximal = np.linalg.solve(np.column_stack([e1, e2, e3]), p)
    return flexion, np.array([varus, internal, lateral, anterior, proximal])


def reference_transform(flexion: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (tibial -> femoral) and tibial origin (femoral frame, m) of a pose (rad, m)."""
    R, p, _ = tibial_pose(flexion, np.asarray(q, float))
    return np.asarray(R, float), np.asarray(p, float).ravel()
