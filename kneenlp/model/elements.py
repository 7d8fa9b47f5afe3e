"""The force-element interface: every part of the knee model is one element (OpenSim's Force).

An element owns its parameters (with metadata, :class:`~kneenlp.model.parameters.Parameter`),
contributes a wrench on the tibia and names its outputs for tables.  :class:`KneeModel` sums the
elements; nothing else in kneenlp knows what kinds of elements exist.

Conventions of every method (SI units, CasADi SX expressions):

* the wrench is ``(force, moment)``, both 3-vectors in the femoral frame, acting *on the tibia*;
  the moment is about the tibial origin ``pose.p``;
* ``values`` maps every model parameter name to its symbol;
* outputs are scalars, reported per trial (e.g. a ligament's strain and force).

A force element only adds a force.  What changes the kinematics or the observation instead (the
experiment's frames, its registration, where it applies its load, its flexion) is the experiment's,
not the knee's: :mod:`kneenlp.experiment.parts`.  Both are :class:`Part` s: a name, a
description, parameters with metadata and whether model adequacy may add it (``candidate``).

Elements whose force needs an expensive computation over many surface points (contact) split it
in two stages, :class:`StagedElement`: a cheap SX ``probe`` of the pose and parameters, and an MX
``surface`` function of the probe whose graph stays a few vector operations however many points
there are (expanding it to SX would inline every point of every trial).
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from itertools import pairwise

import casadi as ca
import numpy as np

from kneenlp.base.modes import Layout, WrenchFrame
from kneenlp.model.parameters import Parameter


@dataclass(frozen=True)
class Pose:
    """The tibia's pose as symbols: rotation ``R`` (the model's tibial frame -> femoral frame),
    tibial origin ``p`` in the femoral frame (m), the five free coordinates ``q`` (rad, m) and the
    flexion (rad).  ``q`` and the flexion are the Grood-Suntay coordinates of the experiment's
    tibial axes, which are the model's unless the experiment turns them
    (:class:`kneenlp.experiment.parts.TibialAxes`)."""

    R: ca.SX
    p: ca.SX
    q: ca.SX
    flexion: ca.SX
    #: the elements' pose data by key (:class:`PoseData`; symbols the model fills at each pose)
    data: Mapping[str, ca.SX] = field(default_factory=dict)

    def to_femoral(self, point_tibial) -> ca.SX:
        """A point fixed in the tibia (tibial frame, m) in the femoral frame."""
        return self.p + self.R @ ca.DM(point_tibial)

    def to_tibial(self, point_femoral) -> ca.SX:
        """A point fixed in the femur (femoral frame, m) in the tibial frame."""
        return self.R.T @ (ca.DM(point_femoral) - self.p)


@dataclass(frozen=True)
class PoseData:
    """Numbers an element's expression needs that are computed outside CasADi at each pose (a path's
    taut string over a bone): ``size`` of them, the symbol ``pose.data[key]`` in the element's
    expressions, and ``take(R, p, values)``: their values at T poses (rotations T x 3 x 3, tibial
    origins T x 3, m; ``values``: every parameter's, SI) as a T x ``size`` array.  The model takes
    them at every pose a solver evaluates, with zero derivative
    (:mod:`kneenlp.experiment.functions`); ``what`` names them in messages."""

    key: str
    size: int
    take: Callable[[np.ndarray, np.ndarray, dict[str, float]], np.ndarray]
    what: str


@dataclass(frozen=True)
class Output:
    """A reported quantity of an element: ``column`` in tables, SI value times ``to_user``."""

    name: str
    column: str
    unit: str
    to_user: float = 1.0


class Part:
    """A named part of the model with parameters: a force element of the knee
    (:class:`ForceElement`) or a part of the experiment's description
    (:class:`kneenlp.experiment.parts.ExperimentPart`).

    ``candidate`` marks a part that is neutral in the knee's own parameter set (it contributes
    nothing until its ``frees`` parameters move from their neutral values): model adequacy tests
    whether adding it explains the data.
    """

    name: str = "part"
    description: str = ""
    candidate: bool = False

    def parameters(self) -> list[Parameter]:
        """This part's parameters (names are ``<part>.<parameter>``)."""
        return []

    def frees(self) -> list[str]:
        """Parameters identified when this part is added as an effect (default: all)."""
        return [p.name for p in self.parameters()]


class ForceElement(Part):
    """A force on the tibia (OpenSim's Force).  Base class: no parameters, no wrench, no outputs."""

    name: str = "element"

    def wrench(self, pose: Pose, values: dict[str, ca.SX]) -> tuple[ca.SX, ca.SX]:
        """Force (N) and moment about the tibial origin (N m) on the tibia, femoral frame."""
        return ca.SX.zeros(3), ca.SX.zeros(3)

    def outputs(self) -> list[Output]:
        """Names and units of :meth:`output_values`."""
        return []

    def output_values(self, pose: Pose, values: dict[str, ca.SX]) -> list[ca.SX]:
        """Values (SI) of :meth:`outputs`, in order."""
        return []

    def pose_data(self) -> list[PoseData]:
        """What :meth:`wrench` reads from ``pose.data`` (none by default)."""
        return []


def share_out(run: Callable[[int, int], None], n: int, threads: int, min_share: int = 1) -> None:
    """Call ``run(first, last)`` on ``threads`` contiguous shares of ``range(n)`` at once (compiled
    loops that release the GIL), each share at least ``min_share`` long (a thread costs ~0.1 ms to
    start and join: a share smaller than that much work is done by the caller): the calling thread
    takes the first share, one new thread each of the others (no pool is kept between calls); an
    exception in any share is raised here."""
    shares = max(1, min(int(threads), n // max(1, int(min_share))))
    if shares == 1:
        run(0, n)
        return
    bounds = np.linspace(0, n, shares + 1).round().astype(int)
    errors: list[BaseException] = []

    def guarded(first: int, last: int) -> None:
        try:
            run(first, last)
        except BaseException as exc:
            errors.append(exc)

    workers = [threading.Thread(target=guarded, args=(int(a), int(b))) for a, b in pairwise(bounds[1:])]
    for w in workers:
        w.start()
    try:
        run(int(bounds[0]), int(bounds[1]))
    finally:
        for w in workers:
            w.join()
    if errors:
        raise errors[0]


class StagedElement(ForceElement, ABC):
    """An element whose force comes from an expensive surface computation over tibial sample
    points (see module docstring).

    Subclasses give :meth:`probe` (SX column from the pose and parameters), :meth:`surface_wrench`
    (MX expressions of the probe and a matrix of per-point data) and :meth:`clearance` (numeric
    gap of every sample point at a pose), and optionally :meth:`select`, :meth:`pack` and
    :meth:`report`.

    Working sets: with ``n_working = n > 0`` only ``n`` slots of per-point data (``ws_width``
    numbers each, :meth:`pack`) enter the residual, as an input of the model's functions, so one
    compiled function serves every working set.  The data are taken at a pose (the points that can
    touch there and, for a mesh, the local expansion of the surface at each point); the solvers
    retake them at every solution and solve again until the solution is consistent with the data
    it was solved with (:meth:`KneeModel.working_set`).  ``n_working = 0`` (only for elements
    whose :meth:`constant_data` exists) uses every point as a constant.
    """

    points: np.ndarray  # (N, 3) tibial sample points, tibial frame, m
    areas: np.ndarray  # (N,) area of each sample, m^2
    working_set_size: int = 0
    #: numbers per working-set slot (rows of the matrix :meth:`surface_wrench` receives)
    ws_width: int = 4
    #: frame of :meth:`surface_wrench`'s force and moment: "tibial" or "femoral"
    wrench_frame: WrenchFrame = "tibial"

    @property
    def n_working(self) -> int:
        """Slots per working set (0: no working set, every point always counts)."""
        n = int(self.working_set_size)
        return n if 0 < n < len(self.points) else 0

    @abstractmethod
    def probe(self, pose: Pose, values: dict[str, ca.SX]) -> ca.SX:
        """Everything :meth:`surface_wrench` needs of the pose and parameters, one SX column."""

    @abstractmethod
    def surface_wrench(self, probe: ca.MX, data: ca.MX | ca.DM) -> tuple[ca.MX, ca.MX]:
        """Force and moment (about the tibial origin) on the tibia, in :attr:`wrench_frame`, from
        the per-point ``data`` (``ws_width`` x n; rows as :meth:`pack` writes them)."""

    @abstractmethod
    def clearance(self, R: np.ndarray, p: np.ndarray, values: dict[str, float]) -> np.ndarray:
        """Gap (m) of every sample point from the femoral surface at pose ``(R, p)``: negative
        where the point penetrates.  Numeric; used to choose and check working sets."""

    def clearance_near(self, R: np.ndarray, p: np.ndarray, values: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """``(indices, gaps)`` of the points that may be near the surface (default: every point);
        the others are certainly clear of it."""
        return np.arange(len(self.points)), self.clearance(R, p, values)

    def constant_data(self) -> np.ndarray:
        """Per-point data of every point (``ws_width`` x N) for ``n_working = 0``."""
        return np.vstack([np.asarray(self.points, float).T, np.asarray(self.areas, float)[None, :]])

    def select(self, R: np.ndarray, p: np.ndarray, values: dict[str, float]) -> np.ndarray:
        """The working set at a pose: indices of the ``n_working`` points of smallest clearance."""
        gap = self.clearance(R, p, values)
        return np.sort(np.argpartition(gap, self.n_working - 1)[: self.n_working])

    def pack(self, indices: np.ndarray, R: np.ndarray, p: np.ndarray, values: dict[str, float]) -> np.ndarray:
        """The working-set input (``ws_width * n_working`` numbers, :meth:`unpack`'s layout) for
        the sample points ``indices`` at pose ``(R, p)``."""
        pts = np.asarray(self.points, float)[indices]
        return np.column_stack([pts, np.asarray(self.areas, float)[indices]]).ravel()

    def working_data(self, R: np.ndarray, p: np.ndarray, values: dict[str, float]) -> np.ndarray:
        """The working-set input at pose ``(R, p)``: :meth:`pack` of :meth:`select`."""
        return self.pack(self.select(R, p, values), R, p, values)

    def working_data_batch(self, R: np.ndarray, p: np.ndarray, values: dict[str, float], threads: int = 1,
                           order: int = 2) -> np.ndarray:
        """:meth:`working_data` at the poses ``R`` (T x 3 x 3), ``p`` (T x 3), one row each.  ``order``:
        the residual's derivatives the data must serve (0: its value only, 1: first derivatives,
        2: second; an element may skip what is not asked for)."""
        R, p = np.asarray(R, float).reshape(-1, 3, 3), np.asarray(p, float).reshape(-1, 3)
        return np.array([self.working_data(R[t], p[t], values) for t in range(len(R))]).reshape(len(R), -1)

    def unpack(self, ws: ca.MX, n: int) -> ca.MX:
        """The ``ws_width`` x n matrix :meth:`surface_wrench` receives, from the packed input."""
        return ca.reshape(ws, self.ws_width, n)

    def surface(self, probe_size: int, with_report: bool = False) -> ca.Function:
        """``(probe, ws) -> (force, moment)`` and, ``with_report``, the values of :meth:`outputs`
        too; ``ws`` packs the working set (``ws_width`` x n_working, column-major) or is empty
        (every point, as constants)."""
        n = self.n_working
        probe = ca.MX.sym("probe", probe_size)
        ws = ca.MX.sym("ws", self.ws_width * n)
        data = self.unpack(ws, n) if n else ca.DM(self.constant_data())
        force, moment = self.surface_wrench(probe, data)
        outs = [force, moment, *(self.report(probe, data, force) if with_report else [])]
        return ca.Function(f"surface_{self.name}", [probe, ws], outs)

    def exact_wrench(self, probe: ca.MX, layout: Layout = "vector") -> tuple[ca.MX, ca.MX]:
        """Force and moment (:attr:`wrench_frame`) from the probe alone, every point counted: what
        the working sets stand for, as one self-contained graph (export); ``layout`` is the graph's
        shape where an element has a choice (:data:`kneenlp.geometry.graph_field.LAYOUTS`).
        Default: the surface wrench of every point as constants (:meth:`constant_data`)."""
        return self.surface_wrench(probe, ca.DM(self.constant_data()))

    def report(self, probe: ca.MX, data: ca.MX | ca.DM, force: ca.MX) -> list[ca.MX]:
        """Values of :meth:`outputs` from the probe, the per-point data and the surface's force."""
        return []
