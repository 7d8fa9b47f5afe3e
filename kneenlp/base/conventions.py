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

Loads
-----
==========================  =====  ===========================================================
load component              unit   positive sense
==========================  =====  ===========================================================
``anterior_force``          N      pushes the tibia anteriorly (posterior < 0)
``varus_moment``            N m    turns the tibia into varus; valgus is negative
``internal_moment``         N m    turns the tibia internally; external is negative
``lateral_force``           N      pushes the tibia laterally (optional, default 0)
``proximal_force``          N      pushes the tibia proximally into the femur: compression (optional)
``flexion_moment``          N m    flexes the knee (optional; reported only: the prescribed
                                   flexion carries it)
==========================  =====  ===========================================================

Where and along which axes they act (``load_axes``, :func:`load_vector`):

* ``"femoral"`` (the paper): forces at the tibial tuberosity along the femoral axes (anterior
  ``+X_f``, proximal ``+Y_f``, lateral ``+Z_f``), pure moments about ``+X_f`` (varus) and ``+Y_f``
  (internal), fixed in the femoral frame;
* ``"joint"``: as ``"femoral"`` but along the Grood & Suntay axes at the prescribed flexion
  (floating axis ``e2``, unvarused tibial axis ``e3``, ``e1 = Z_f``), as a clinical laxity device
  applies them;
* ``"jcs"``: the generalised forces of the Grood & Suntay joint coordinate system, each conjugate
  to its coordinate (moments about ``e2`` and ``e3``, forces along ``e1``, ``e2``, ``e3`` acting at
  the tibial origin), as a robotic knee simulator controls and reports them.  They enter the
  equilibrium as they are, whatever the pose.

Units: SI inside (m, rad, N, N m, Pa); mm and degrees at every user boundary (files, tables,
plots, reports).  Ligament stiffness ``k`` is in N per unit strain; strains are fractions inside
and percent at the boundary; the contact pressure modulus is in N/m^3 inside and GN/m^3 outside.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from kneenlp.base.modes import LoadAxes, names

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

#: Load components every protocol and data file has (the paper's), with units.
LOAD_COMPONENTS: tuple[str, ...] = ("anterior_force", "varus_moment", "internal_moment")
LOAD_UNITS: tuple[str, ...] = ("N", "Nm", "Nm")
#: Further load components a real experiment records (optional, default 0), with units.
EXTRA_LOAD_COMPONENTS: tuple[str, ...] = ("lateral_force", "proximal_force", "flexion_moment")
EXTRA_LOAD_UNITS: tuple[str, ...] = ("N", "N", "Nm")
#: Every load component and its unit.
ALL_LOAD_COMPONENTS: tuple[str, ...] = LOAD_COMPONENTS + EXTRA_LOAD_COMPONENTS
ALL_LOAD_UNITS: tuple[str, ...] = LOAD_UNITS + EXTRA_LOAD_UNITS
#: Size of the internal load vector (:func:`load_vector`): a force (3), a pure moment (3), both in
#: the femoral frame, generalised forces of the five free coordinates (5), where the force acts: a
#: tibial point (3, tibial frame, m) plus the knee's tuberosity times a weight (1), the coordinates
#: the apparatus holds: a mask (5, 1 = held) and the values they are held at (5, SI), and a
#: compressive preload acting elsewhere: its force (3, femoral frame) and its tibial point (3 + 1),
#: and the coordinate the trial's dominant load drives, with its sign (5: +-1 there, else 0; the
#: observation's, e.g. an apparatus' dead band, :class:`~kneenlp.experiment.parts.NeutralZone`).
LOAD_SIZE = 37
#: Slices of the load vector: the loads a ramp scales, the held mask, the held values, the preload
#: and its point (as the force's: a tibial point and the tuberosity's weight), the loaded direction.
LOADS, HELD, HELD_AT, PRELOAD, PRELOAD_AT = slice(0, 11), slice(15, 20), slice(20, 25), slice(25, 28), slice(28, 32)
LOADED = slice(32, 37)

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
#: A pose is an equilibrium when no residual component exceeds this (N or N m): the forward
#: solver's, the simulation's and every identification's one tolerance (the nested Complex method
#: penalises only above the paper's looser 1e-3, :data:`kneenlp.solvers.nested.CONSTRAINT_TOL`).
EQUILIBRIUM_TOL = 1e-6


#: The physiological envelope of a knee pose in user units (deg, deg, mm, mm, mm): the largest
#: plausible |coordinate|.  The forward solver rejects equilibria outside it; the identification
#: NLP bounds its pose variables with it.
POSE_ENVELOPE_USER = np.array([30.0, 60.0, 25.0, 25.0, 25.0])


def coords_to_user(q):
    """Free coordinates from SI (rad, m) to user units (deg, mm): a NumPy array whose last axis has
    length 5, or a CasADi matrix of 5 rows (one column a pose).  Every conversion of poses and
    measured data goes through this function or :func:`coords_from_user`."""
    if isinstance(q, ca.SX | ca.MX | ca.DM):
        return q * ca.DM(TO_USER)
    return np.asarray(q, dtype=float) * TO_USER


def coords_from_user(q_user):
    """Free coordinates from user units (deg, mm) to SI (rad, m): a NumPy array whose last axis
    has length 5, or a CasADi matrix of 5 rows (one column a pose)."""
    if isinstance(q_user, ca.SX | ca.MX | ca.DM):
        return q_user / ca.DM(TO_USER)
    return np.asarray(q_user, dtype=float) / TO_USER


def pose_envelope_user(reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds (5, mm and deg) of a plausible pose: :data:`POSE_ENVELOPE_USER` about
    the knee's ``reference`` pose (5, SI)."""
    centre = coords_to_user(reference)
    return centre - POSE_ENVELOPE_USER, centre + POSE_ENVELOPE_USER


def coordinate_columns() -> list[str]:
    """CSV column names of the coordinates, with their units (e.g. ``anterior_translation_mm``)."""
    return [f"{c}_{u}" for c, u in zip(COORDINATES, COORDINATE_UNITS, strict=True)]


def load_columns(extra: bool = False) -> list[str]:
    """CSV column names of the load components, with units (e.g. ``anterior_force_N``); with
    ``extra`` those of the optional components too."""
    comps, units = (ALL_LOAD_COMPONENTS, ALL_LOAD_UNITS) if extra else (LOAD_COMPONENTS, LOAD_UNITS)
    return [f"{c}_{u}" for c, u in zip(comps, units, strict=True)]


#: Axes along which load components act (see the module docstring).
LOAD_AXES: tuple[str, ...] = names(LoadAxes)


def scaled_load(load: np.ndarray, factor: float) -> np.ndarray:
    """``factor`` times the force, moment and generalised forces of a load vector (:func:`load_vector`;
    a ramp's fraction of the trial's load), acting at the same point."""
    out = np.array(load, float)
    out[LOADS] *= factor
    out[PRELOAD] *= factor
    return out


def load_vector(loads: dict[str, float], *, flexion: float = 0.0, axes: LoadAxes = "femoral",
                point: np.ndarray | None = None, held: tuple[tuple[int, float], ...] = (),
                preload_point: tuple[float, float, float, float] | None = None,
                loaded: tuple[int, float] | None = None) -> np.ndarray:
    """Internal load vector (:data:`LOAD_SIZE`) of signed load components (N, N m; absent = 0).

    ``[F (3), M (3), Q (5), a (3), w (1)]``: a force ``F`` and a pure moment ``M``, both in the
    femoral frame, generalised forces ``Q`` added to the equilibrium residual as they are (order of
    :data:`COORDINATES`), and the tibial point ``F`` acts at, ``a + w t`` (tibial frame, m; ``t`` the
    knee's tuberosity): ``point`` (``a``, ``w = 0``) or by default the tuberosity (``a = 0``,
    ``w = 1``), then the ``held`` coordinates (index in :data:`COORDINATES`, value in rad or m: the
    mask and the values), and, given a ``preload_point`` (``a, w`` as the force's point), the
    proximal force as a preload of its own acting there (not for ``jcs`` loads), and ``loaded``: the
    coordinate (index in :data:`COORDINATES`) the dominant load drives and its sign.  ``axes``
    (module docstring): ``"femoral"`` along femoral X, Y, Z; ``"joint"`` along the floating axis
    ``e2 = (cos f, -sin f, 0)``, the unvarused tibial axis ``e3 = (sin f, cos f, 0)`` at flexion
    ``f`` (rad) and ``e1 = Z``; ``"jcs"`` all in ``Q``.  The flexion moment is never applied (the
    prescribed flexion carries it).
    """
    get = {c: float(loads.get(c, 0.0)) for c in ALL_LOAD_COMPONENTS}
    unknown = set(loads) - set(ALL_LOAD_COMPONENTS)
    if unknown:
        raise ValueError(f"unknown load component {sorted(unknown)[0]!r}; known: {', '.join(ALL_LOAD_COMPONENTS)}")
    out = np.zeros(LOAD_SIZE)
    out[11:15] = (0.0, 0.0, 0.0, 1.0) if point is None else (*np.asarray(point, float).reshape(3), 0.0)
    for i, value in held:
        out[HELD.start + i], out[HELD_AT.start + i] = 1.0, value
    if loaded is not None:
        out[LOADED.start + loaded[0]] = np.sign(loaded[1])
    if axes == "jcs":
        out[6:11] = [get["varus_moment"], get["internal_moment"], get["lateral_force"], get["anterior_force"],
                   get["proximal_force"]]
        return out
    if axes == "femoral":
        e2, e3 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    elif axes == "joint":
        c, s = np.cos(flexion), np.sin(flexion)
        e2, e3 = np.array([c, -s, 0.0]), np.array([s, c, 0.0])
    else:
        raise ValueError(f"unknown load axes {axes!r}; known: {', '.join(LOAD_AXES)}")
    e1 = np.array([0.0, 0.0, 1.0])
    preload = get["proximal_force"] * e3
    out[0:3] = get["anterior_force"] * e2 + get["lateral_force"] * e1
    if preload_point is None:
        out[0:3] += preload
    else:
        out[PRELOAD], out[PRELOAD_AT] = preload, preload_point
    out[3:6] = get["varus_moment"] * e2 + get["internal_moment"] * e3
    return out

#: The predictive band's level (two-sided) and its half-width in standard deviations (normal):
#: ``predict`` with a calibration's posterior, its figure.
BAND_LEVEL = 0.95
BAND_Z = 1.959963984540054
