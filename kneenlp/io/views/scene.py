"""What the pictures of a simulated knee show, extracted from a simulation result (SI, femoral
or tibial frame): each compartment's contact map (pressure, Pa; centre of pressure, m), the
ligament lines (N), the surfaces at a trial's pose and the :class:`Scene` of the 3-D view."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from kneenlp.base.errors import unknown_name
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.protocol import Protocol, Trial
from kneenlp.model.articular import Compartment
from kneenlp.model.knee import Knee
from kneenlp.simulation import SimulationResult
from kneenlp.solvers.forward import TrialSolution

MM, MPA = 1e3, 1e-6  # SI -> display units
#: Padding (m) around the femoral surface's touchable box when cropping it for pictures.
FEMUR_PAD = 0.010


# ---------------------------------------------------------------------------------------- data
@dataclass
class ContactMap:
    """The contact of one compartment at one trial's pose (SI).

    ``mesh`` is the tibial cartilage (tibial frame, m; its vertices are the contact sample points),
    ``pressure`` the pressure at each vertex (Pa), ``areas`` the area lumped to each vertex (m^2),
    ``force`` the contact force on the tibia (N, femoral frame) and ``cop`` the centre of pressure
    (tibial frame, m; NaN without contact)."""

    name: str
    mesh: trimesh.Trimesh
    pressure: np.ndarray
    areas: np.ndarray
    force: np.ndarray
    cop: np.ndarray

    @property
    def load(self) -> float:
        """Magnitude of the contact force (N), as the ``contact_<name>_N`` output."""
        return float(np.linalg.norm(self.force))

    @property
    def integrated(self) -> float:
        """Pressure integrated over the cartilage, sum of pressure x area (N; not projected, so it
        exceeds :attr:`load` by the spread of the surface normals, about 1 %)."""
        return float(np.sum(self.pressure * self.areas))


@dataclass
class LigamentLine:
    """One ligament bundle at a pose: attachments in the femoral frame (m) and the ligament's force (N)."""

    ligament: str
    femur: np.ndarray
    tibia: np.ndarray
    force: float
    candidate: bool = False


def trial_ids(result: SimulationResult) -> list[str]:
    """Ids of the result's trials, in protocol order."""
    return [s.trial.id for s in result.solutions]


def solution(result: SimulationResult, trial: str | Trial | TrialSolution) -> TrialSolution:
    """The solution of one trial of ``result``, by id (or Trial); unknown ids raise the standard
    one-line :class:`~kneenlp.base.errors.InputError`."""
    if isinstance(trial, TrialSolution):
        return trial
    tid = trial.id if isinstance(trial, Trial) else str(trial)
    for s in result.solutions:
        if s.trial.id == tid:
            return s
    raise unknown_name("trial", tid, trial_ids(result))


def pose(result: SimulationResult, sol: TrialSolution) -> tuple[np.ndarray, np.ndarray]:
    """The tibial pose of a solution: ``R`` (tibial -> femoral rotation) and ``p`` (tibial origin in
    the femoral frame, m), so that ``x_femoral = R @ x_tibial + p``."""
    model = result.model or KneeModel.of(result.knee)
    theta = model.theta(result.parameters)
    R, p = model.pose(sol.q, sol.trial.flexion, theta)
    return np.asarray(R, float), np.asarray(p, float).ravel()


def contact_maps(result: SimulationResult, trial: str | Trial | TrialSolution) -> dict[str, ContactMap]:
    """Per-vertex contact pressure of every compartment at a trial's pose (:class:`ContactMap`, SI),
    from each contact element's ``pressure`` (mesh or sphere contact alike)."""
    sol = solution(result, trial)
    model = result.model or KneeModel.of(result.knee)
    modulus = float(model.theta(result.parameters)[model.index("contact.modulus")])
    R, p = pose(result, sol)
    elements = {e.compartment: e for e in model.staged if hasattr(e, "pressure") and hasattr(e, "compartment")}
    maps = {}
    for name, comp in result.knee.compartments.items():
        if name not in elements:
            continue
        c = elements[name].pressure(R, p, modulus)
        cop = R.T @ (c["cop"] - p) if np.all(np.isfinite(c["cop"])) else np.full(3, np.nan)
        maps[name] = ContactMap(name, comp.tibia_mesh, np.asarray(c["pressure"], float), comp.areas,
                                np.asarray(c["force"], float), cop)
    return maps


def ligament_lines(result: SimulationResult, trial: str | Trial | TrialSolution) -> list[LigamentLine]:
    """Every bundle of the knee's ligaments (and of candidate bundles that carry force) at a trial's
    pose, femoral frame (m), with the ligament's force from the trial's outputs (N)."""
    sol = solution(result, trial)
    R, p = pose(result, sol)
    lines = []
    ligaments = [(lig, False) for lig in result.knee.ligaments.values()]
    ligaments += [(lig, True) for lig in result.knee.candidates]
    for lig, candidate in ligaments:
        force = float(sol.outputs.get(f"{lig.name}_force_N", 0.0))
        if candidate and force <= 0:
            continue  # a switched-off candidate is not part of the model
        for b in lig.bundles:
            lines.append(LigamentLine(lig.name, np.asarray(b.femur, float), R @ np.asarray(b.tibia, float) + p,
                                      force, candidate))
    return lines


def default_view_trials(protocol: Protocol) -> list[str]:
    """Trials worth a picture: every unloaded trial, plus one loaded trial per load direction (the
    largest magnitude) at the protocol's first (smallest) flexion, or at the direction's smallest
    flexion if it is not tested there."""
    trials = list(protocol.trials)
    chosen = [t.id for t in trials if t.direction == "none"]
    if not trials:
        return chosen
    first = min(t.flexion_deg for t in trials)
    for direction in dict.fromkeys(t.direction for t in trials if t.direction != "none"):
        same = [t for t in trials if t.direction == direction]
        lowest = min(t.flexion_deg for t in same)
        at = [t for t in same if t.flexion_deg == (first if any(u.flexion_deg == first for u in same) else lowest)]
        chosen.append(max(at, key=lambda t: t.magnitude).id)
    return chosen


# ---------------------------------------------------------------------------------------- geometry
def femur_surface(knee: Knee, pad: float = FEMUR_PAD) -> tuple[trimesh.Trimesh, str] | None:
    """The femoral articular surface for pictures (femoral frame, m) and a phrase saying what it is.

    The knee's femoral mesh moved outward by ``knee.femur.offset`` along its vertex normals (when
    the mesh is the subchondral bone), cropped to the touchable box padded by ``pad`` (m).  None
    for a knee without a femoral mesh (explicit spheres only)."""
    if knee.femur is None:
        return None
    mesh = knee.femur.mesh
    vertices = np.asarray(mesh.vertices, float)
    offset = float(knee.femur.offset)
    if offset:
        vertices = vertices + offset * np.asarray(mesh.vertex_normals, float)
    lo, hi = np.asarray(knee.femur.box, float) + np.array([[-pad], [pad]])
    inside = np.all((vertices >= lo) & (vertices <= hi), axis=1)
    faces = np.asarray(mesh.faces)[inside[mesh.faces].all(axis=1)]
    out = trimesh.Trimesh(vertices, faces, process=False)
    out.remove_unreferenced_vertices()
    what = (f"femoral articular surface (bone mesh moved {offset * MM:g} mm outward along its normals)"
            if offset else "femoral articular surface")
    return out, what


def sphere_cap(centre: np.ndarray, radius: float, toward: np.ndarray, half_angle_deg: float = 75.0,
               subdivisions: int = 4) -> trimesh.Trimesh:
    """Tessellated cap of an explicit condyle sphere (femoral frame, m): the part within
    ``half_angle_deg`` of the direction ``toward`` (e.g. the tibial cartilage), as
    :func:`kneenlp.model.anatomy.condyle_mesh` tessellates the synthetic condyles."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=float(radius))
    axis = np.asarray(toward, float)
    axis = axis / (np.linalg.norm(axis) or 1.0)
    keep = sphere.vertices @ axis >= radius * np.cos(np.deg2rad(half_angle_deg))
    cap = trimesh.Trimesh(sphere.vertices, sphere.faces[keep[sphere.faces].all(axis=1)], process=False)
    cap.remove_unreferenced_vertices()
    cap.apply_translation(np.asarray(centre, float))
    return cap


def condyle_caps(knee: Knee, R: np.ndarray, p: np.ndarray) -> dict[str, trimesh.Trimesh]:
    """A cap of every explicit condyle sphere, facing the compartment's tibial cartilage at the pose
    ``(R, p)`` (femoral frame, m)."""
    caps = {}
    for name, c in knee.compartments.items():
        if c.sphere:
            toward = (np.asarray(c.points).mean(axis=0) @ R.T + p) - c.centre
            caps[name] = sphere_cap(c.centre, c.sphere_radius, toward)
    return caps


def posed_tibia(comp: Compartment, R: np.ndarray, p: np.ndarray) -> trimesh.Trimesh:
    """A compartment's tibial cartilage moved to the pose: ``x_femoral = R @ x_tibial + p`` (m)."""
    v = np.asarray(comp.tibia_mesh.vertices, float) @ R.T + p
    return trimesh.Trimesh(v, np.asarray(comp.tibia_mesh.faces), process=False)


def decimate(vertices: np.ndarray, faces: np.ndarray, target_faces: int,
             values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertex-clustering decimation to roughly ``target_faces`` faces (for pictures only).

    Vertices are merged per cubic cell (same unit as ``vertices``) whose size follows from the
    surface area and the budget; per-vertex ``values`` are averaged over each cell.  Meshes already
    within the budget are returned unchanged."""
    vertices, faces = np.asarray(vertices, float), np.asarray(faces, int)
    if len(faces) <= target_faces:
        return vertices, faces, values
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    cell = np.sqrt(2.0 * area / target_faces)
    keys = np.floor((vertices - vertices.min(axis=0)) / cell).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    count = np.bincount(inverse)
    merged = np.stack([np.bincount(inverse, vertices[:, k]) for k in range(3)], axis=1) / count[:, None]
    new_values = None if values is None else np.bincount(inverse, np.asarray(values, float)) / count
    f = inverse[faces]
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    return merged, f[np.sort(first)], new_values


# ---------------------------------------------------------------------------------------- 3-D view
@dataclass
class Scene:
    """Everything the 3-D view draws, femoral frame, SI: surfaces, pressures, ligaments."""

    title: str
    femur: trimesh.Trimesh | None
    femur_note: str
    caps: dict[str, trimesh.Trimesh]
    tibiae: dict[str, trimesh.Trimesh]
    contact: dict[str, ContactMap]
    cops: dict[str, np.ndarray]  # femoral frame, m
    ligaments: list[LigamentLine]


def build_scene(result: SimulationResult, trial: str | Trial | TrialSolution) -> Scene:
    """Collect the geometry of the knee at a trial's pose (femoral frame, m)."""
    sol = solution(result, trial)
    knee = result.knee
    R, p = pose(result, sol)
    surface = femur_surface(knee)
    femur, note = surface if surface is not None else (None, "")
    caps = condyle_caps(knee, R, p)
    if caps:
        note = (note + "; " if note else "") + "explicit condyle spheres (caps)"
    contact = contact_maps(result, sol)
    tibiae = {name: posed_tibia(c, R, p) for name, c in knee.compartments.items()}
    cops = {n: R @ m.cop + p for n, m in contact.items() if np.all(np.isfinite(m.cop))}
    flag = "" if sol.converged else " (NOT CONVERGED)"
    title = f"{knee.name} knee, {sol.trial.id}{flag}: {sol.trial.describe()}"
    return Scene(title, femur, note, caps, tibiae, contact, cops, ligament_lines(result, sol))
