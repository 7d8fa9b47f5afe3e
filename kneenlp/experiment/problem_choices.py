"""What an identification problem is asked to be beside its model and data: the free parameters
(:func:`free_names`, :func:`check_free`), their priors (:func:`resolve_priors`) and the other keyword
arguments of :meth:`~kneenlp.experiment.problem.IdentificationProblem.from_data`, checked in one place
(:class:`ProblemChoices`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from kneenlp.base.errors import InputError
from kneenlp.model.params import declared_free, default_free
from kneenlp.model.priors import Prior

if TYPE_CHECKING:
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.experiment.noise import NoiseModel


@dataclass(frozen=True)
class ProblemChoices:
    """The keyword arguments of :meth:`~kneenlp.experiment.problem.IdentificationProblem.from_data`, as
    given: the ``noise`` model (or its spec, e.g. ``"uniform:0.5"``), a fit ``weighted`` by 1/variance,
    ``fixed`` values (SI), the candidate effects ``with_effects`` freed too, the ``priors``
    (:func:`resolve_priors`), the ``prior_weight`` (mm^2 or deg^2; None: from the noise), the free
    parameters' ``bounds`` (SI) and ``ties``."""

    noise: str | NoiseModel | None = None
    weighted: bool = False
    fixed: Mapping[str, float] | None = None
    with_effects: Sequence[str] = ()
    priors: str | Mapping[str, Prior | None] | None = None
    prior_weight: float | None = None
    bounds: Mapping[str, tuple[float, float]] | None = None
    ties: Mapping[str, str] | None = None



def free_names(model: KneeModel, free: Sequence[str] | None = None, with_effects: Sequence[str] = ()) -> list[str]:
    """``free`` (default: :func:`declared_free` over :func:`default_free`) and the parameters of the
    candidate effects ``with_effects``, each once."""
    out = list(free or declared_free(model, default_free(model)))
    for name in with_effects:
        out += [n for n in model.effect(name).free_names() if n not in out]
    return out


def check_free(model: KneeModel, free: Sequence[str]) -> list[str]:
    """The free parameter names, validated (known, not repeated, not empty)."""
    for name in free:
        model.index(name)
    if len(set(free)) != len(free):
        raise InputError(f"free parameters repeated: {', '.join(free)}", field="free")
    if not free:
        raise InputError("no free parameters", field="free")
    return list(free)


def resolve_priors(model: KneeModel, free: Sequence[str], priors: str | Mapping[str, Prior | None] | None,
                   fixed: Mapping[str, float] | None = None) -> dict[str, Prior]:
    """The priors of the ``free`` parameters: none for ``None`` or ``"none"`` (the data-only fit);
    for ``"default"`` each parameter's prior from the knee's parameter file, else its shipped
    default (:meth:`~kneenlp.model.parameters.Parameter.default_prior`) centred on its value in the
    knee's parameter set (or ``fixed``); a mapping gives its own by name over those defaults
    (``None`` removes one).  A prior on a parameter that is not free is an error naming it."""
    if priors is None or (isinstance(priors, str) and priors == "none"):
        return {}
    if isinstance(priors, str) and priors != "default":
        raise InputError(f"unknown priors {priors!r}; known: default, none", field="priors")
    given = {} if isinstance(priors, str) else dict(priors)
    for name in given:
        model.index(name)
        if name not in free:
            raise InputError("has a prior but is not free: free it or drop its prior", field=f"priors.{name}")
    theta = model.theta(dict(fixed or {}))
    declared = model.knee.parameters.priors
    out = {}
    for name in free:
        prior = given[name] if name in given else declared.get(name)
        if name not in given and prior is None:
            prior = model.parameter(name).default_prior(float(theta[model.index(name)]))
        if prior is not None:
            out[name] = prior  # checked against the parameter by the problem
    return out
