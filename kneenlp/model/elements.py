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
import numpy as np

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
    """An element whose force comes from an expensive surface computation over tibial sample
    points (see module docstring).

    Subclasses give :meth:`probe` (SX column from the pose and parameters), :meth:`surface_wrench`
    (MX expressions of the probe and the sample points) and :meth:`clearance` (numeric gap of
    every sample point at a pose), and optionally :meth:`report`.

    Working sets: with ``working_set_size = n`` (0 < n < number of points) only the ``n`` points
    nearest to contact at a trial's pose enter the residual (as an input of the model's functions,
    so one compiled function serves every working set); the solvers recompute them after each
    solve and re-solve when a point left out penetrates (:meth:`KneeModel.working_set`).
    """

    points: np.ndarray  # (N, 3) tibial sample points, tibial frame, m
    areas: np.ndarray  # (N,) area of each sample, m^2
    working_set_size: int = 0

    @property
    def n_working(self) -> int:
        """Points per working set (0: no working set, every point always counts)."""
        n = int(self.working_set_size)
        return n if 0 < n < len(self.points) else 0

    @abstractmethod
    def probe(self, pose: Pose, values: dict[str, ca.SX]) -> ca.SX:
        """Everything :meth:`surface_wrench` needs of the pose and parameters, one SX column."""

    @abstractmethod
    def surface_wrench(self, probe: ca.MX, x: ca.MX | ca.DM, areas: ca.MX | ca.DM) -> tuple[ca.MX, ca.MX]:
        """Force and moment (about the tibial origin) on the tibia, tibial frame, from the sample
        points ``x`` (3 x n, tibial frame, m) with ``areas`` (1 x n, m^2)."""

    @abstractmethod
    def clearance(self, R: np.ndarray, p: np.ndarray, values: dict[str, float]) -> np.ndarray:
        """Gap (m) of every sample point from the femoral surface at pose ``(R, p)``: negative
        where the point penetrates.  Numeric; used to choose and check working sets."""

    def surface(self, probe_size: int) -> ca.Function:
        """``(probe, ws) -> (force, moment)``; ``ws`` packs the working set's points and areas
        (4 x n_working, column-major) or is empty (then every point counts, as constants)."""
        n = self.n_working
        probe = ca.MX.sym("probe", probe_size)
        ws = ca.MX.sym("ws", 4 * n)
        if n:
            w = ca.reshape(ws, 4, n)
            x, a = w[:3, :], w[3, :]
        else:
            x, a = ca.DM(np.asarray(self.points, float).T), ca.DM(np.asarray(self.areas, float)).T
        force, moment = self.surface_wrench(probe, x, a)
        return ca.Function(f"surface_{self.name}", [probe, ws], [force, moment], ["probe", "ws"],
                           ["force", "moment"])

    def pack(self, indices: np.ndarray) -> np.ndarray:
        """The working-set input for the sample points ``indices``."""
        pts = np.asarray(self.points, float)[indices]
        return np.column_stack([pts, np.asarray(self.areas, float)[indices]]).ravel()

    def report(self, probe: ca.MX, force: ca.MX) -> list[ca.MX]:
        """Values of :meth:`outputs` from the probe and the surface's force (tibial frame)."""
        return []
