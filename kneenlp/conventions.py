"""Coordinates, signs and units: every convention of kneenlp in one place.

Frames (right knee)
-------------------
* Femoral frame = global frame (the femur is fixed), ISB orientation (Wu et al. 2002):
  ``X`` anterior, ``Y`` proximal (superior), ``Z`` lateral (to the right for a right knee).
  Its origin is the knee centre: the midpoint of the line joining the medial and lateral femoral
  condyle (sphere) centres, which is the flexion axis.
* Tibial frame: same orientation and origin as the femoral frame in the *reference pose*
  (the pose of the scan: 0 deg flexion, all coordinates zero).  Tibial points (attachments,
  cartilage, tuberosity) are given in this frame.

Joint coordinates (Grood & Suntay 1983)
---------------------------------------
The tibial orientation is the intrinsic rotation sequence ``R = Rz(-flexion) Rx(varus) Ry(internal)``:
flexion about the femoral medio-lateral axis ``e1 = Z_f``, varus/valgus about the floating axis
``e2 = e3 x e1 / |e3 x e1|`` and internal/external rotation about the tibial long axis ``e3 = Y_t``.
The tibial origin is at ``p = lateral * e1 + anterior * e2 + proximal * e3`` (femoral frame).

==========================  =====  ===========================================================
coordinate                  unit   positive sense
==========================  =====  ===========================================================
``flexion``                 deg    knee flexion (prescribed, not free)
``varus_rotation``          deg    varus (tibia adducted); valgus is negative
``internal_rotation``       deg    internal rotation of the tibia; external is negative
``lateral_translation``     mm     tibia moves laterally along ``e1``; medial is negative
``anterior_translation``    mm     tibia moves anteriorly along ``e2``; posterior is negative
``proximal_translation``    mm     tibia moves proximally along ``e3`` (compression)
==========================  =====  ===========================================================

Loads (fixed in the femoral frame)
----------------------------------
==========================  =====  ===========================================================
load component              unit   positive sense
==========================  =====  ===========================================================
``anterior_force``          N      force along ``+X_f`` at the tibial tuberosity (posterior < 0)
``varus_moment``            N m    pure moment about ``+X_f`` (varus); valgus is negative
``internal_moment``         N m    pure moment about ``+Y_f`` (internal); external is negative
==========================  =====  ===========================================================

Units: SI inside (m, rad, N, N m, Pa); mm and degrees at every user boundary (files, tables,
plots, reports).  Ligament stiffness ``k`` is in N per unit strain; strains are fractions inside
and percent at the boundary; the contact pressure modulus is in N/m^3 inside and GN/m^3 outside.
"""

from __future__ import annotations

import numpy as np

#: The five free coordinates, in the order of the model's unknown vector ``q``.
COORDINATES: tuple[str, ...] = (
    "varus_rotation",
    "internal_rotation",
    "lateral_translation",
    "anterior_translation",
    "proximal_translation",
)
#: User-facing unit of each coordinate.
COORDINATE_UNITS: tuple[str, ...] = ("deg", "deg", "mm", "mm", "mm")
#: Factor from the internal SI unit (rad, m) to the user unit (deg, mm), per coordinate.
TO_USER: np.ndarray = np.array([180.0 / np.pi, 180.0 / np.pi, 1e3, 1e3, 1e3])

#: Load components accepted in protocols and data files, with units.
LOAD_COMPONENTS: tuple[str, ...] = ("anterior_force", "varus_moment", "internal_moment")
LOAD_UNITS: tuple[str, ...] = ("N", "Nm", "Nm")

#: Load directions of the paper's Table 2: (component, sign).
DIRECTIONS: dict[str, tuple[str | None, float]] = {
    "none": (None, 0.0),
    "anterior": ("anterior_force", 1.0),
    "posterior": ("anterior_force", -1.0),
    "varus": ("varus_moment", 1.0),
    "valgus": ("varus_moment", -1.0),
    "internal": ("internal_moment", 1.0),
    "external": ("internal_moment", -1.0),
}

#: Generalised-force (residual) names and units, in the order of ``COORDINATES``.
RESIDUAL_NAMES: tuple[str, ...] = (
    "moment_varus",
    "moment_internal",
    "force_lateral",
    "force_anterior",
    "force_proximal",
)
RESIDUAL_UNITS: tuple[str, ...] = ("N m", "N m", "N", "N", "N")


#: The physiological envelope of a knee pose in user units (deg, deg, mm, mm, mm): the largest
#: plausible |coordinate|.  The forward solver rejects equilibria outside it; the identification
#: NLP bounds its pose variables with it.
POSE_ENVELOPE_USER = np.array([30.0, 60.0, 25.0, 25.0, 25.0])


def coords_to_user(q: np.ndarray) -> np.ndarray:
    """Convert free coordinates from SI (rad, m) to user units (deg, mm); last axis has length 5."""
    return np.asarray(q, dtype=float) * TO_USER


def coords_from_user(q_user: np.ndarray) -> np.ndarray:
    """Convert free coordinates from user units (deg, mm) to SI (rad, m); last axis length 5."""
    return np.asarray(q_user, dtype=float) / TO_USER


def coordinate_columns() -> list[str]:
    """CSV column names of the coordinates, with their units (e.g. ``anterior_translation_mm``)."""
    return [f"{c}_{u}" for c, u in zip(COORDINATES, COORDINATE_UNITS, strict=True)]


def load_columns() -> list[str]:
    """CSV column names of the load components, with units (e.g. ``anterior_force_N``)."""
    return [f"{c}_{u}" for c, u in zip(LOAD_COMPONENTS, LOAD_UNITS, strict=True)]


#: Axes along which load components act: the femoral axes (the paper) or the joint axes.
LOAD_AXES: tuple[str, ...] = ("femoral", "joint")


def load_vector(anterior_force: float, varus_moment: float, internal_moment: float, *,
                flexion: float = 0.0, axes: str = "femoral") -> np.ndarray:
    """Internal 6-vector load ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m) in the femoral frame.

    The force acts at the tibial tuberosity, the moment is a pure moment on the tibia.  With
    ``axes="femoral"`` the components act along femoral X (anterior force, varus moment) and Y
    (internal moment); with ``axes="joint"`` along the floating axis ``e2 = (cos f, -sin f, 0)``
    and the unvarused tibial axis ``e3 = (sin f, cos f, 0)`` at flexion ``f`` (rad).
    """
    if axes == "femoral":
        e2, e3 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    elif axes == "joint":
        c, s = np.cos(flexion), np.sin(flexion)
        e2, e3 = np.array([c, -s, 0.0]), np.array([s, c, 0.0])
    else:
        raise ValueError(f"unknown load axes {axes!r}; known: {', '.join(LOAD_AXES)}")
    return np.concatenate([anterior_force * e2, varus_moment * e2 + internal_moment * e3])
