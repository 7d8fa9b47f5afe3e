"""Brute-force reference of the elastic-foundation contact on the femoral mesh itself.

:func:`reference_contact` evaluates the same pressure law as the model (pressure = modulus x
penetration through the C2 gate, force along the femoral surface normal, on the same tibial sample
points and areas) but with *exact* point-to-mesh signed distances to the femoral mesh
(:class:`kneenlp.geometry.distance.MeshDistance`: trimesh's point-triangle distances with a
certified candidate search), instead of the distance field the model uses.  It is slow (seconds)
and has no derivatives: it is the oracle of the field's accuracy (tests/test_real_knee.py) and a
tool to check a user's own knee::

    from kneenlp.testing.reference import compare_contact
    compare_contact(knee, q, theta, flexion)   # per compartment: model vs exact force, moment, CoP

Frames and units: tibial points in the tibial frame, pose ``(R, p)`` maps them to the femoral
frame; force on the tibia (N) and moment about the tibial origin (N m) in the femoral frame, centre
of pressure in the femoral frame (m).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.protocol import Loading
from kneenlp.geometry.distance import MeshDistance
from kneenlp.geometry.rim import OpenEdges
from kneenlp.model.laws import NUMPY, ElasticFoundation


@dataclass(frozen=True)
class ContactState:
    """The contact of one compartment at one pose (SI, femoral frame)."""

    force: np.ndarray
    moment: np.ndarray
    cop: np.ndarray  # NaN without contact
    penetration: np.ndarray  # per tibial point, m
    pressure: np.ndarray  # per tibial point, Pa

    @property
    def load(self) -> float:
        return float(np.linalg.norm(self.force))


@dataclass(frozen=True)
class ExactSurface:
    """The femoral surface by exact distances: ``offset`` (m) outside the mesh of ``distance``.
    ``rim``: the mesh's open edges (:class:`~kneenlp.geometry.rim.OpenEdges` of the mesh itself,
    offset 0; None: none); a point whose nearest mesh point lies on one presses nothing (the surface
    ends where the mesh ends: a sharp edge, where the model's weight falls to 0 within a grid
    spacing)."""

    distance: MeshDistance
    offset: float = 0.0
    rim: OpenEdges | None = None

    @classmethod
    def of(cls, femur, distance: MeshDistance | None = None) -> ExactSurface:
        """The surface of a knee's ``femur`` (:class:`~kneenlp.model.articular.FemoralSurface`)."""
        return cls(distance or MeshDistance(femur.mesh), femur.offset, OpenEdges(femur.mesh))


def reference_contact(surface: ExactSurface, contact, pose: tuple[np.ndarray, np.ndarray],
                      modulus: float) -> ContactState:
    """Contact of the tibial points of ``contact`` (a contact element: its ``points``, tibial frame,
    m, ``areas``, m^2, ``gate``, m, and pressure ``law``) against ``surface`` at ``pose = (R, p)``,
    modulus in N/m^3."""
    distance, offset, rim = surface.distance, surface.offset, surface.rim
    R, p = pose
    p = np.asarray(p, float).ravel()
    X = np.asarray(contact.points, float) @ np.asarray(R, float).T + p
    # the others are certainly clear of the surface, or inside the mesh deeper than any contact (5 mm)
    near = distance.lower_bound(X) < max(offset + 1e-4, 5e-3)
    d, normal = np.full(len(X), np.inf), np.zeros((len(X), 3))
    if np.any(near):
        d[near], closest, normal[near] = distance(X[near])
        if rim is not None and not rim.closed:  # beyond the edge: the distance is to the edge line, no contact
            beyond = np.flatnonzero(near)[rim.distance(closest) <= 1e-9 * distance.unit]
            d[beyond] = np.inf
    pen = offset - d
    pres = (contact.law or ElasticFoundation()).pressure(pen, modulus, contact.gate, NUMPY)
    w = pres * np.asarray(contact.areas, float)
    f = normal * w[:, None]
    cop = (X * w[:, None]).sum(axis=0) / w.sum() if w.sum() > 0 else np.full(3, np.nan)
    return ContactState(f.sum(axis=0), np.cross(X - p, f).sum(axis=0), cop, pen, pres)


def compare_contact(knee, q: np.ndarray, theta: np.ndarray, flexion: float,
                    distance: MeshDistance | None = None) -> dict[str, dict[str, float]]:
    """The model's contact (its femoral distance field) against :func:`reference_contact` at one
    pose ``q`` (SI) of ``knee`` (mesh compartments only), per compartment: both loads (N), the
    force and moment errors relative to the reference magnitudes, and the centre-of-pressure
    distance (mm)."""
    model = KneeModel.of(knee)
    R, p = (np.asarray(v) for v in model.pose(q, flexion, theta))
    modulus = float(theta[model.index("contact.modulus")])
    surface = ExactSurface.of(knee.femur, distance)
    out = {}
    for e in model.staged:
        if not hasattr(e, "field"):
            continue
        ref = reference_contact(surface, e, (R, p), modulus)
        got = e.pressure(R, p, modulus)
        out[e.compartment] = {
            "load_N": float(np.linalg.norm(got["force"])), "reference_load_N": ref.load,
            "force_error": float(np.linalg.norm(got["force"] - ref.force) / max(ref.load, 1e-12)),
            "moment_error": float(np.linalg.norm(got["moment"] - ref.moment)
                                  / max(np.linalg.norm(ref.moment), 1e-12)),
            "cop_error_mm": float(np.linalg.norm(got["cop"] - ref.cop) * 1e3) if ref.load > 0 else 0.0,
        }
    return out


def cropped_knee_file(name: str, cut: float, directory: Path) -> Path:
    """A copy of the shipped knee ``name``'s file in ``directory`` whose femoral mesh is cropped: the
    faces whose centre lies more than ``cut`` (m) posterior of the femoral origin (femoral frame)
    removed, every other mesh path made absolute.  A cropped surface to check the rim against the
    brute force (a real knee's cartilage is often segmented only where it was imaged)."""
    import re

    import trimesh

    from kneenlp.model.knee import Knee
    from kneenlp.model.knee_file import knee_file

    src = knee_file(name)
    text = re.sub(r'(\w+) = "(\.\./[^"]+)"',
                  lambda m: f'{m.group(1)} = "{(src.parent / m.group(2)).resolve().as_posix()}"', src.read_text())
    raw = re.search(r'femur = "([^"]+)"', text).group(1)
    mesh = trimesh.load(raw)
    centres = np.asarray(Knee.named(name).femur.mesh.triangles_center)  # the file's faces, femoral frame
    trimesh.Trimesh(mesh.vertices, mesh.faces[centres[:, 0] >= -cut], process=True).export(directory / "femur.stl")
    out = directory / "knee.toml"
    out.write_text(text.replace(raw, (directory / "femur.stl").as_posix()))
    return out


def reference_equilibrium(model: KneeModel, solution, theta: np.ndarray, tol: float = 1e-6,
                          max_iter: int = 30) -> tuple[np.ndarray, float]:
    """The equilibrium of the ``solution``'s trial with the brute-force contact
    (:func:`reference_contact` for every mesh compartment, the model's other forces as they are)
    near the model's own equilibrium (its pose ``q``, SI; a
    :class:`~kneenlp.solvers.forward.TrialSolution`): chord Newton with the model's Jacobian at
    ``q``.  Returns the pose (SI) and the largest residual (N, N m)."""
    if not all(hasattr(e, "field") for e in model.staged):
        raise ValueError("the brute-force equilibrium needs mesh contact in every staged element")
    surface = ExactSurface.of(model.knee.femur)
    modulus = float(theta[model.index("contact.modulus")])
    trial, q = solution.trial, np.asarray(solution.q, float).copy()
    jac = model.trial_derivatives(q[None], theta, Loading.of([trial]), 1)[1][0]
    res = np.inf
    for _ in range(max_iter):
        R, p = (np.asarray(v) for v in model.pose(q, trial.flexion, theta))
        states = [reference_contact(surface, e, (R, p.ravel()), modulus) for e in model.staged]
        r = model.residual_given(q, theta, trial.load, trial.flexion, [(s.force, s.moment) for s in states])
        res = float(np.max(np.abs(r)))
        if res <= tol:
            break
        q -= np.linalg.solve(jac, r)
    return q, res


def rescaled_knee(knee, rng: np.random.Generator, sd: float = 0.3):
    """``knee`` (a :class:`~kneenlp.model.knee.Knee` whose ligaments' bundles carry their own
    stiffness and whose groups have a ``k_scale``) parametrised another way: each group's bundle
    stiffnesses times a log-normal factor (``sd``) and its ``k_scale`` divided by it.  Every force
    is the same function of the pose (to rounding); only the parameter values differ, so any
    difference in what a solver returns is the solver's path, not the knee."""
    import copy
    import dataclasses

    from kneenlp.experiment.kneemodel import KneeModel

    model = KneeModel.of(knee)
    theta = model.theta()
    ligaments, values = {}, {}
    for name, ligament in knee.ligaments.items():
        if f"{name}.k_scale" not in model.parameter_names or ligament.bundles[0].stiffness is None:
            continue
        factor = float(np.exp(rng.normal(0.0, sd)))
        moved = copy.copy(ligament)
        moved.bundles = [dataclasses.replace(b, stiffness=b.stiffness * factor) for b in ligament.bundles]
        ligaments[name] = moved
        values[f"{name}.k_scale"] = float(theta[model.index(f"{name}.k_scale")]) / factor
    out = dataclasses.replace(knee, ligaments={**knee.ligaments, **ligaments})
    return out.with_parameters(out.parameters.with_values(values))
