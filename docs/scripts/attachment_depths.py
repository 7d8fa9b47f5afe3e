"""The attachment depths of docs/inputs.md: how far inside a mesh of each shipped knee its
ligaments' attachments lie (mm), the measurement behind the 2.5 mm limit of the attachment check.

    python docs/scripts/attachment_depths.py [KNEE.toml ...]   # the shipped knees, and these

Prints, per knee, the deepest attachment inside a mesh (field, mesh, depth in mm), or that none
lies inside.
"""

from __future__ import annotations

import sys

from kneenlp.model.knee import knee_file
from kneenlp.model.knee_file import KneeFile, resolve_knee

SHIPPED = ("default", "s192803", "implant")


def deepest(knee: str) -> tuple[str, str, float] | None:
    """(field, mesh, depth in mm) of the deepest attachment inside a mesh of ``knee`` (a shipped
    knee's name or a knee file), or None when none lies inside."""
    kf = KneeFile(resolve_knee(knee_file(knee) if knee in SHIPPED else knee))
    geometry = kf.contact({k: kf.raw_point(v) for k, v in kf.spec.landmarks.items()})
    kf.ligaments()
    kf.candidates()
    inside = kf.attachment_depths(geometry | {"bones": kf.bones()})
    if not inside:
        return None
    fld, what, _, _, depth = max(inside, key=lambda row: row[-1])
    return fld, what, depth * 1e3


if __name__ == "__main__":
    for name in (*SHIPPED, *sys.argv[1:]):
        found = deepest(name)
        print(f"{name}: " + ("no attachment inside a mesh" if found is None else
                             f"deepest {found[2]:.2f} mm inside the {found[1]} ({found[0]})"))
