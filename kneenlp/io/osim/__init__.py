"""Self-contained reader for OpenSim / OpenSim JAM knee models (.osim) and a
calibrated-model writer: ``read`` (the file into an :class:`OsimModel`; ligament groups; the
knee's line elements), ``model`` (the in-memory model and OpenSim's ligament force), ``kinematics``
(rotations, transforms, the joints' functions) and ``write`` (calibrated and loadable copies).

Only numpy and the standard library are used (``xml.etree.ElementTree``); the
``opensim`` package is *not* needed (it cannot load OpenSim JAM classes such as
``Smith2018ContactMesh`` anyway).  It is used only as an external oracle in the
tests.

Units: everything is returned exactly as stored in the file, which for OpenSim
models is SI (lengths in m, angles in rad, forces in N).  ``OsimModel.length_units``
and ``force_units`` give what the file declares.

Conventions (all verified against the ``opensim`` 4.6 package, see test_osim.py):

* Homogeneous transforms are 4x4 numpy arrays ``X_AB`` that map coordinates of a
  point expressed in frame B to frame A: ``p_A = X_AB[:3,:3] @ p_B + X_AB[:3,3]``.
* ``PhysicalOffsetFrame.orientation`` (and wrap-object ``xyz_body_rotation``,
  contact-mesh ``orientation``) are body-fixed X-Y-Z Euler angles in rad:
  ``R = Rx(a) @ Ry(b) @ Rz(c)``; ``translation`` is expressed in the parent frame.
* ``CustomJoint`` ``SpatialTransform``: ``X_FM = [R1 R2 R3 | sum_i t_i*axis_i]`` where
  ``R_k`` is a rotation by ``f_k(q)`` about ``axis_k`` (body-fixed sequence
  rotation1, rotation2, rotation3) and the three translations are along their
  axes expressed in the joint's parent frame F.
* A joint places its child frame M relative to its parent frame F:
  ``X_G,childbody = X_G,F @ X_FM(q) @ inv(X_childbody,M)``.

Public API (see docstrings): :func:`read_osim`, :class:`OsimModel`
(``body_transforms``, ``transform``, ``point_in_body``, ``frame_in_body``),
:func:`ligament_groups`, :func:`knee_line_elements`, :func:`blankevoort_force`,
:func:`write_calibrated`, :func:`write_opensim_loadable_copy`, :class:`OsimError`.
"""

from kneenlp.io.osim.kinematics import OsimError, rot_body_xyz
from kneenlp.io.osim.lines import LineElement, knee_line_elements, ligament_groups
from kneenlp.io.osim.model import (
    BLANKEVOORT_DEFAULTS,
    JAM_ONLY_CLASSES,
    BodyInfo,
    ContactMesh,
    Coordinate,
    Joint,
    Ligament,
    MeshGeometry,
    OffsetFrame,
    OsimModel,
    PathPoint,
    TransformAxis,
    WrapObject,
    blankevoort_force,
)
from kneenlp.io.osim.read import read_osim
from kneenlp.io.osim.write import write_calibrated, write_opensim_loadable_copy

__all__ = [
    "BLANKEVOORT_DEFAULTS",
    "JAM_ONLY_CLASSES",
    "BodyInfo",
    "ContactMesh",
    "Coordinate",
    "Joint",
    "Ligament",
    "LineElement",
    "MeshGeometry",
    "OffsetFrame",
    "OsimError",
    "OsimModel",
    "PathPoint",
    "TransformAxis",
    "WrapObject",
    "blankevoort_force",
    "knee_line_elements",
    "ligament_groups",
    "read_osim",
    "rot_body_xyz",
    "write_calibrated",
    "write_opensim_loadable_copy",
]
