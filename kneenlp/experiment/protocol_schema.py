"""The protocol file declared as a schema: its keys, their types and which are required
(:mod:`kneenlp.experiment.protocol` builds the trials from it and checks the loads and angles)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from kneenlp.base.conventions import ALL_LOAD_COMPONENTS, DIRECTIONS, LOAD_AXES
from kneenlp.base.schema import Name, Number, Numbers, Table, one_of

#: A load component of a combined load (``anterior_force``, ``internal_moment``, ...).
LoadComponent = Annotated[str, one_of("load component", ALL_LOAD_COMPONENTS)]


class Exclusion(Table):
    """One trial of a case left out: ``{magnitude = M, flexion = F}`` (N or N m; deg)."""

    magnitude: Number | None = Field(None, description="magnitude (N or N m)")
    flexion: Number = Field(description="flexion (deg)")


class Case(Table):
    """One ``[[cases]]`` entry: a ``direction`` with ``magnitude`` values (N for forces, N m for
    moments, positive) at ``flexion`` angles (deg), less the trials in ``exclude``; or a combined
    load ``loads`` (signed components, N and N m) at ``flexion`` angles, with an optional ``name``."""

    direction: Annotated[str, one_of("load direction", DIRECTIONS)] | None = None
    magnitude: Numbers | None = Field(None, description="magnitude")
    flexion: Numbers = Field(description="flexion angles (deg)")
    exclude: list[Exclusion] | None = None
    loads: dict[LoadComponent, Number] | None = None
    name: Name | None = None


class ProtocolFile(Table):
    """A protocol file: its name, title and description, the load axes and the cases."""

    name: str | None = None
    title: str = ""
    description: str = ""
    load_axes: Annotated[str, one_of("load_axes", LOAD_AXES)] = "femoral"
    cases: list[Case] = Field(min_length=1, description="[[cases]]")
