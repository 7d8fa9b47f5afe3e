"""The articular contact: one force element per compartment of the knee file's ``[contact]``.

The knee file's reader reads the table (:mod:`kneenlp.model.knee_contact_file`: the meshes, the
femoral distance field, the fitted spheres need the whole file); this module makes the elements of
the compartments it built: :class:`~kneenlp.model.contact.SphereContact` for a compartment with an
explicit sphere, :class:`~kneenlp.model.mesh_contact.MeshContact` against the femoral distance field
otherwise.  Every knee carries them (``schema`` and ``read`` None).
"""

from __future__ import annotations

from kneenlp.model.contact import SphereContact
from kneenlp.model.elements import ForceElement
from kneenlp.model.mesh_contact import MeshContact
from kneenlp.model.structures import KneeGeometry, StructureTable


def declared(knee: KneeGeometry, _value: None) -> list[ForceElement]:
    """The contact element of each compartment, in the knee file's order."""
    return [SphereContact(c, knee.gate, knee.working_set) if c.sphere else
            MeshContact(c, knee.femur.field, knee.gate, knee.femur) for c in knee.compartments.values()]


TABLE = StructureTable("contact", None, None, declared, lambda knee: [], None)
