"""The modes the library and the command line accept: each a ``Literal`` type, its one list of names.

A function that takes a mode is typed with its ``Literal`` and checks the value at the boundary
with :func:`checked` (a user's value that is not one of them is the standard one-line "unknown X
'name'; known: ..." error); the command line's ``choices`` come from :func:`names`, so a mode is
listed once.  Imports nothing heavy: the parser reads it before any work.
"""

from __future__ import annotations

from typing import Literal, get_args

from kneenlp.base.errors import unknown_name

#: How the parameters are identified: one NLP over all poses and parameters, or an optimizer around
#: a per-trial rootfinder (the paper's Complex method).
Method = Literal["simultaneous", "nested"]
#: What a fit of measured data is: chosen by the data, a real experiment's calibration, or the
#: paper's scatter fit.
Strategy = Literal["auto", "calibration", "scatter"]
#: Optimal-design criteria: A, D, worst-case and robust.
Criterion = Literal["A", "D", "W", "R"]
#: Export formats of the one NLP.
ExportFormat = Literal["nl", "casadi", "c"]
#: How the .nl export writes common subexpressions.
NlCommon = Literal["defined", "lifted"]
#: A knee's side.
Side = Literal["left", "right"]
#: Bundle grouping of an OpenSim import.
Groups = Literal["fine", "coarse"]
#: Priors of a calibration.
PriorChoice = Literal["default", "none"]
#: Where a study's fits start.
StudyStart = Literal["scatter", "truth"]
#: How a forward solve reached a trial's equilibrium (Newton from its start, the load ramp from the
#: unloaded state, settling where Newton or the ramp could not go on), or that it did not.
SolveStrategy = Literal["newton", "ramp", "settle", "failed"]
#: The axes a trial's loads are given in (a protocol's or the data's ``load_axes``).
LoadAxes = Literal["femoral", "joint", "jcs"]
#: The shape of the exact contact's CasADi graph: vectorised (CasADi files) or a loop (C).
Layout = Literal["vector", "loop"]
#: How an exported NLP holds the contact: exact in the graph, or an expansion at the start poses (.nl).
ContactForm = Literal["exact", "expansion"]
#: Where the NLP's contact working sets come from: the data vector, the graph, every pose evaluated.
WorkingSetSource = Literal["data", "graph", "pose"]
#: The frame a staged element gives its wrench in.
WrenchFrame = Literal["tibial", "femoral"]
#: How a knee's frames are made from its geometry.
FrameMethod = Literal["cylinders", "landmarks"]


def names(mode: object) -> tuple[str, ...]:
    """The names of a ``Literal`` mode, in their order."""
    return get_args(mode)


def checked(kind: str, value: str, mode: object, *, field: str | None = None, source: str | None = None) -> str:
    """``value`` if it is one of ``mode``'s names, else the one-line error naming ``kind`` (and ``field``)."""
    if value not in names(mode):
        raise unknown_name(kind, value, names(mode), source=source, field=field)
    return value
