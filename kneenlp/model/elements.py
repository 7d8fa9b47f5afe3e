"""The force-element interface: every part of the knee model is one element (OpenSim's Force).

An element owns its parameters (with metadata, :class:`~kneenlp.model.parameters.Parameter`),
contributes a wrench on the tibia and names its outputs for tables.  :class:`KneeModel` sums the
elements; nothing else in kneenlp knows what kinds of elements exist.

Conventions of every method (SI units, CasADi SX expressions):

* the wrench is ``(force, moment)``, both 3-vectors in the femoral frame, acting *on the tibia*;
  the moment is about the tibial origin ``pose.p``;
* ``values`` maps every model parameter name to its symbol;
* outputs are scalars, reported per trial (e.g. a ligament's strain and force).

Two optional hooks let an element change what is *not* a force: :meth:`ForceElement.flexion_offset`
(the true flexion differs from the prescribed one) and :meth:`ForceElement.measurement_bias` (a
bias of the measured coordinates, e.g. a registration offset).

Elements whose force needs an expensive computation over many surface points (contact) split it
in two stages, :class:`StagedElement`: a cheap SX ``probe`` of the pose and parameters, and an MX
``surface`` function of the probe whose graph stays a few vector operations however many points
there are (expanding it to SX would inline every point of every trial).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import casadi as ca

from kneenlp.model.parameters import Parameter


@dataclass(frozen=True)
class Pose:
    """The tibia's pose as symbols: rotation ``R`` (tibial -> femoral frame), tibial origin ``p``
    in the femoral frame (m), the five free coordinates ``q`` (rad, m) and the flexion (rad)."""

    R: ca.SX
    p: ca.SX
    q: ca.SX
    flexion: ca.SX

    def to_femoral(self, point_tibial) -> ca.SX:
        """A point fixed in the tibia (tibial frame, m) in the femoral frame."""
        return self.p + self.R @ ca.DM(point_tibial)

    def to_tibial(self, point_femoral) -> ca.SX:
        """A point fixed in the femur (femoral frame, m) in the tibial frame."""
        return self.R.T @ (ca.DM(point_femoral) - self.p)


@dataclass(frozen=True)
class Output:
    """A reported quantity of an element: ``column`` in tables, SI value times ``to_user``."""

    name: str
    column: str
    unit: str
    to_user: float = 1.0


class ForceElement:
    """Base class: no parameters, no wrench, no outputs.

    ``candidate`` marks an element that is neutral in the knee's own parameter set (it contributes
    nothing until its ``frees`` parameters move from their neutral values): model adequacy tests
    whether adding it explains the data.
    """

    name: str = "element"
    description: str = ""
    candidate: bool = False

    def parameters(self) -> list[Parameter]:
        """This element's parameters (names are ``<element>.<parameter>``)."""
        return []

    def frees(self) -> list[str]:
        """Parameters identified when this element is added as an effect (default: all)."""
        return [p.name for p in self.parameters()]

    def wrench(self, pose: Pose, values: dict[str, ca.SX]) -> tuple[ca.SX, ca.SX]:
        """Force (N) and moment about the tibial origin (N m) on the tibia, femoral frame."""
        return ca.SX.zeros(3), ca.SX.zeros(3)

    def outputs(self) -> list[Output]:
        """Names and units of :meth:`output_values`."""
        return []

    def output_values(self, pose: Pose, values: dict[str, ca.SX]) -> list[ca.SX]:
        """Values (SI) of :meth:`outputs`, in order."""
        return []

    def flexion_offset(self, values: dict[str, ca.SX]) -> ca.SX | float:
        """True minus prescribed flexion (rad)."""
        return 0.0

    def measurement_bias(self, values: dict[str, ca.SX]) -> ca.SX | None:
        """Added to the model's five coordinates before comparison with measurements (rad, m)."""
        return None


class StagedElement(ForceElement, ABC):
    """An element whose force comes from an expensive surface computation (see module docstring).

    Subclasses give :meth:`probe` (SX column from the pose and parameters) and :meth:`surface`
    (a CasADi Function ``probe -> (force, moment)`` in the *tibial* frame, moment about the tibial
    origin), and optionally :meth:`report` (MX outputs computed only for result tables).
    """

    @abstractmethod
    def probe(self, pose: Pose, values: dict[str, ca.SX]) -> ca.SX:
        """Everything :meth:`surface` needs, as one SX column (e.g. a sphere centre, tibial frame)."""

    @abstractmethod
    def surface(self) -> ca.Function:
        """``probe -> (force, moment)`` on the tibia, tibial frame, moment about the tibial origin."""

    def report(self, probe: ca.MX, force: ca.MX) -> list[ca.MX]:
        """Values of :meth:`outputs` from the probe and the surface's force (tibial frame)."""
        return []
