"""A ligament path over a bone's own surface (kneenlp.model.bone_wrap): the knee file's table, its bad
input, the jumps it names, and (slow) a real knee's equilibrium with it."""

from __future__ import annotations

import numpy as np
import pytest

from kneenlp.base.errors import InputError
from kneenlp.model.bone_wrap import BoneWrap
from tests.test_paths import _knee_with_wrap
from tests.test_taut_path import Cylinder

BONE = '\n[ligaments.MCL.wrap]\nshape = "bone"\nbody = "tibia"\n'


def test_a_path_over_a_bone_needs_the_bones_mesh(tmp_path):
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap\.body: a path over the tibia's surface needs its mesh"):
        _knee_with_wrap(tmp_path, BONE)


def test_a_bone_path_takes_no_obstacle_keys(tmp_path):
    with pytest.raises(InputError, match=r"ligaments\.MCL\.wrap\.centre.*centre belongs to a cylinder, not a bone"):
        _knee_with_wrap(tmp_path, BONE + "centre = [0.0, 0.0, 0.0]\n")


def test_a_path_over_a_bone_names_where_it_jumps():
    """An attachment deeper in the bone than attachments lie, and a straight line through the bone's
    middle (where the side the path goes round flips), are named; a smooth wrap is not."""
    path = BoneWrap(Cylinder(), "femur")
    rotation, origin = np.eye(3), np.zeros(3)
    S, E = np.array([-0.03, 0.004, 0.0]), np.array([0.025, 0.002, 0.01])
    assert path.jump(E, S, rotation, origin) == ""
    through = np.array([0.025, 0.0005, 0.01]), np.array([-0.03, 0.0, 0.0])  # 0.3 mm from the axis
    assert "near its middle" in path.jump(*through, rotation, origin)
    assert "tibial attachment lies inside" in path.jump(E, np.array([0.005, 0.0, 0.0]), rotation, origin)
    assert path.jump(E, np.array([0.0099, 0.0, 0.0]), rotation, origin) == ""  # on the surface: an attachment
