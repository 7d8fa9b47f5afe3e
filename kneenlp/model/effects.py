"""Candidate physical effects of the knee: elements and parameter groups neutral in the base model.

An *effect* is something the model adequacy check can add (:mod:`kneenlp.adequacy`):

* a candidate force element (:class:`~kneenlp.model.elements.ForceElement` with
  ``candidate = True``): at its neutral parameter values it contributes exactly nothing, so the
  base fit is the extended fit with those parameters fixed.  Built in: bundles named in the knee
  file's ``[candidates.<name>]`` (e.g. ``posterior_capsule``, ``ALL``: :class:`Ligament` elements
  with stiffness 0) and the structures a knee file does not declare (:mod:`kneenlp.model.structures`:
  the menisci); the experiment's candidates (flexion offset,
  registration, load point) are :mod:`kneenlp.experiment.parts`'s;
* a parameter group of the base model (:func:`parameter_group`): ``lin_strain`` (the linear
  strain limits) and ``contact_modulus``;
* a geometry candidate (:func:`attachment_effects`): the position of one ligament's (or bundle
  group's) femoral or tibial attachments, ``<LIG>_femoral_attachment`` and
  ``<LIG>_tibial_attachment``, three shifts in mm each (anterior, proximal, lateral);
* a bundle group of a multi-bundle knee whose parameters a fit keeps fixed
  (:func:`bundle_group_effects`, ``<GROUP>_bundles``: stiffness scale and strain offset).

Extension point: subclass :class:`~kneenlp.model.elements.ForceElement` (set ``candidate = True``,
give :meth:`parameters` with a ``neutral`` value and :meth:`wrench`), and pass it as
``KneeModel(knee, extra_elements=[...])``; ``docs/architecture.md`` has a worked example.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Effect:
    """What adequacy can add: a name, a description and the parameters it frees."""

    name: str
    description: str
    parameters: tuple[str, ...]

    def free_names(self) -> list[str]:
        return list(self.parameters)

    def parameter_named(self, key: str) -> str | None:
        """The parameter ``key`` names: its full name, or a unique ending after a dot or an
        underscore (``k`` of ``posterior_capsule.k``, ``modulus`` of ``contact.modulus``,
        ``anterior`` of ``ACL.femur_anterior``) or beginning before a dot (``ACL`` of ``ACL.lin_strain``);
        ``None`` if none or several match."""
        if key in self.parameters:
            return key
        hits = [n for n in self.parameters if n.endswith(f".{key}") or n.endswith(f"_{key}")]
        hits = hits or [n for n in self.parameters if n.startswith(f"{key}.")]
        return hits[0] if len(hits) == 1 else None


def parameter_group(name: str, names: list[str], description: str) -> Effect:
    """An effect that frees existing base-model parameters (e.g. the linear strain limits)."""
    return Effect(name, description, tuple(names))


def builtin_groups(ligaments: list[str]) -> list[Effect]:
    """Effects that free base-model parameters: the linear strain limits of the (single-law)
    ``ligaments`` and the contact modulus."""
    groups = [parameter_group("lin_strain", [f"{lig}.lin_strain" for lig in ligaments],
                              "the linear strain limits of the ligaments differ from 3 %")] if ligaments else []
    return [*groups, parameter_group("contact_modulus", ["contact.modulus"], "the cartilage pressure modulus differs")]


def bundle_group_effects(groups: list[str]) -> list[Effect]:
    """One candidate per bundle group of a multi-bundle knee: the group's stiffness scale and
    reference-strain offset (``<group>.k_scale``, ``<group>.ref_strain_offset``).  A candidate
    only where a fit keeps them at the model's values (e.g. a group left out of ``--free``)."""
    return [parameter_group(f"{g}_bundles", [f"{g}.k_scale", f"{g}.ref_strain_offset"],
                            f"the {g} bundles are stiffer or slacker than the model's") for g in groups]


def attachment_effects(ligaments: list[str]) -> list[Effect]:
    """One geometry candidate per ligament (or bundle group) and side: its attachments moved by
    a vector (``<lig>.femur_anterior`` ..., mm; :mod:`kneenlp.model.ligament`)."""
    from kneenlp.model.ligament import SHIFT_AXES

    out = []
    for lig in ligaments:
        for side, word in (("femur", "femoral"), ("tibia", "tibial")):
            out.append(Effect(f"{lig}_{word}_attachment", f"the {lig} {word} attachment is elsewhere",
                              tuple(f"{lig}.{side}_{axis}" for axis in SHIFT_AXES)))
    return out
