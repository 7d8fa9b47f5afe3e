"""A knee: geometry (cartilage meshes, ligament attachments, frames) plus a default parameter set.

A knee is described by a TOML file (see ``kneenlp/resources/knees/default/knee.toml``) that names its
cartilage meshes (STL/PLY/OBJ, read with trimesh), ligament attachments, landmarks and contact
settings, in millimetres, either already in the ISB femoral frame (``coordinates = "femoral"``,
the default) or in scanner coordinates (``coordinates = "scan"``): then the ISB femoral frame is
built from the landmarks ``hip_center``, ``medial_epicondyle`` and ``lateral_epicondyle`` (Wu et al.
2002) and its origin put midway between the fitted condyle centres, on the flexion axis.
:meth:`Knee.load` validates the file and converts everything to SI.  A left knee
(``side = "left"``) is mirrored into a right knee (Z -> -Z), which keeps the anatomical meaning of
every coordinate.

Each femoral condyle enters the contact model through the sphere fitted to its cartilage mesh
(least squares, ``trimesh.nsphere.fit_nsphere``); the RMS distance of the mesh from that sphere is
kept in :attr:`Compartment.fit_rms` and a knee whose fit is worse than 1 mm is rejected, since the
contact law would then misrepresent it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh

from kneenlp.errors import InputError
from kneenlp.io.resources import resource
from kneenlp.model.contact import SphereContact
from kneenlp.model.elements import ForceElement
from kneenlp.model.ligament import Bundle, Ligament
from kneenlp.model.parameters import ParameterSet, number, read_toml

MAX_SPHERE_FIT_RMS = 1e-3  # m


def default_knee_file() -> Path:
    """The knee TOML of the embedded default knee (inside the installed package)."""
    return resource("knees", "default", "knee.toml")


@dataclass(frozen=True)
class Compartment:
    """One tibiofemoral compartment: condyle sphere and tibial cartilage samples (SI)."""

    name: str
    femur_mesh: trimesh.Trimesh  # femoral frame, m
    tibia_mesh: trimesh.Trimesh  # tibial frame, m
    sphere_center: np.ndarray  # femoral frame, m
    sphere_radius: float  # m
    fit_rms: float  # m

    @cached_property
    def points(self) -> np.ndarray:
        """Tibial cartilage sample points: mesh vertices (N x 3, m, tibial frame)."""
        return np.asarray(self.tibia_mesh.vertices, dtype=float)

    @cached_property
    def areas(self) -> np.ndarray:
        """Area lumped to each sample point: a third of each adjacent face (m^2)."""
        m = self.tibia_mesh
        a = np.zeros(len(m.vertices))
        np.add.at(a, m.faces.ravel(), np.repeat(m.area_faces / 3.0, 3))
        return a


@dataclass
class Knee:
    """Geometry of a (right) knee and its default mechanical parameters."""

    name: str
    ligaments: dict[str, Ligament]
    compartments: dict[str, Compartment]
    tuberosity: np.ndarray  # tibial frame, m
    parameters: ParameterSet
    gate: float = 1e-5  # m
    working_set: int = 0  # contact sample points per compartment and trial (0: all)
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    source: str | None = None
    description: str = ""
    candidates: list[Ligament] = field(default_factory=list)  # [candidates.*]: bundles with stiffness 0

    @classmethod
    def default(cls) -> Knee:
        """The embedded default knee with the paper's Table 1 properties."""
        return cls.load(default_knee_file())

    @classmethod
    def load(cls, path: str | Path, parameters: str | Path | ParameterSet | None = None) -> Knee:
        """Read and validate a knee description TOML; see module docstring for the format."""
        path = Path(path)
        src = str(path)
        doc = read_toml(path)
        side = doc.get("side", "right")
        if side not in ("right", "left"):
            raise InputError(f"must be 'right' or 'left', got {side!r}", source=src, field="side")
        units = doc.get("units", "mm")
        if units not in ("mm", "m"):
            raise InputError(f"must be 'mm' or 'm', got {units!r}", source=src, field="units")
        scale = 1e-3 if units == "mm" else 1.0
        mirror = np.array([1.0, 1.0, -1.0 if side == "left" else 1.0])
        coordinates = doc.get("coordinates", "femoral")
        if coordinates not in ("femoral", "scan"):
            raise InputError(f"must be 'femoral' or 'scan', got {coordinates!r}", source=src, field="coordinates")
        transform = _Transform(scale, mirror)

        def raw_point(value: object, fld: str) -> np.ndarray:
            if not isinstance(value, list) or len(value) != 3:
                raise InputError(f"expected [x, y, z] in {units}, got {value!r}", source=src, field=fld)
            return np.array([number(v, src, fld) for v in value])

        def point(value: object, fld: str) -> np.ndarray:
            return transform(raw_point(value, fld))

        raw_landmarks = {k: raw_point(v, f"landmarks.{k}") for k, v in doc.get("landmarks", {}).items()}
        if coordinates == "scan":
            transform.from_landmarks(raw_landmarks, side, src)
            for cname, cdoc in doc.get("contact", {}).items():  # origin: midpoint of the condyle centres
                if isinstance(cdoc, dict) and "femur" in cdoc:
                    fem = read_mesh(path.parent / str(cdoc["femur"]), transform, field=f"contact.{cname}.femur",
                                    knee_file=src)
                    transform.centres.append(fit_sphere(fem.vertices)[0])
            transform.shift = np.mean(transform.centres, axis=0) if transform.centres else np.zeros(3)
        landmarks = {k: transform(v) for k, v in raw_landmarks.items()}
        if "tibial_tuberosity" not in landmarks:
            raise InputError("missing (anterior/posterior loads act there)", source=src,
                             field="landmarks.tibial_tuberosity")

        ligs_doc = doc.get("ligaments")
        if not isinstance(ligs_doc, dict) or not ligs_doc:
            raise InputError("missing table [ligaments.<NAME>]", source=src, field="ligaments")
        ligaments = {}
        for name, lig in ligs_doc.items():
            for key in ("femur", "tibia"):
                if key not in lig:
                    raise InputError("missing attachment", source=src, field=f"ligaments.{name}.{key}")
            ligaments[name] = Ligament(name, [Bundle(point(lig["femur"], f"ligaments.{name}.femur"),
                                                     point(lig["tibia"], f"ligaments.{name}.tibia"))])
            if ligaments[name].reference_length < 1e-3:
                raise InputError("attachments closer than 1 mm", source=src, field=f"ligaments.{name}")

        contact = doc.get("contact", {})
        gate = number(contact.get("gate", 0.01), src, "contact.gate") * scale
        if gate <= 0:
            raise InputError("must be > 0", source=src, field="contact.gate")
        working_set = contact.get("working_set", 0)
        if isinstance(working_set, bool) or not isinstance(working_set, int) or working_set < 0:
            raise InputError(f"must be an integer >= 0 (0: every point), got {working_set!r}", source=src,
                             field="contact.working_set")
        compartments = {}
        for cname, cdoc in contact.items():
            if cname in ("gate", "working_set"):
                continue
            if not isinstance(cdoc, dict):
                raise InputError("must be a table with 'femur' and 'tibia' meshes", source=src,
                                 field=f"contact.{cname}")
            meshes = {}
            for key in ("femur", "tibia"):
                if key not in cdoc:
                    raise InputError("missing mesh file", source=src, field=f"contact.{cname}.{key}")
                meshes[key] = read_mesh(path.parent / str(cdoc[key]), transform,
                                        field=f"contact.{cname}.{key}", knee_file=src)
            center, radius, rms = fit_sphere(meshes["femur"].vertices)
            if rms > MAX_SPHERE_FIT_RMS:
                raise InputError(f"femoral cartilage deviates {rms * 1e3:.2f} mm RMS from a sphere "
                                 "(limit 1 mm); the contact model needs a condyle-like surface",
                                 source=src, field=f"contact.{cname}.femur")
            compartments[cname] = Compartment(cname, meshes["femur"], meshes["tibia"], center,
                                              radius, rms)
        if not compartments:
            raise InputError("no compartments ([contact.medial], [contact.lateral])", source=src,
                             field="contact")

        candidates = []
        for cname, cdoc in doc.get("candidates", {}).items():
            fld = f"candidates.{cname}"
            if cdoc.get("kind") != "bundle":
                raise InputError(f"unknown candidate kind {cdoc.get('kind')!r}; known: bundle", source=src,
                                 field=f"{fld}.kind")
            fem, tib = cdoc.get("femur"), cdoc.get("tibia")
            if not isinstance(fem, list) or not isinstance(tib, list) or len(fem) != len(tib) or not fem:
                raise InputError("femur and tibia must be equally long lists of [x, y, z]", source=src, field=fld)
            fem = [point(v, f"{fld}.femur") for v in fem]
            tib = [point(v, f"{fld}.tibia") for v in tib]
            ref = number(cdoc.get("ref_strain", 0.0), src, f"{fld}.ref_strain") / 100.0
            candidates.append(Ligament(cname, [Bundle(f, t) for f, t in zip(fem, tib, strict=True)], candidate=True,
                                       defaults={"ref_strain": ref}, description=str(cdoc.get("description", ""))))
        if isinstance(parameters, ParameterSet):
            params = parameters
        elif parameters is not None:
            params = ParameterSet.load(parameters)
        elif "parameters" in doc:
            params = ParameterSet.load(path.parent / str(doc["parameters"]))
        else:
            raise InputError("no parameter set: give 'parameters = FILE' or pass one", source=src,
                             field="parameters")
        extra = sorted({n.split(".")[0] for n in params.names()} - set(ligaments) - {"contact"})
        if extra:
            raise InputError(f"unknown ligament {extra[0]!r}; known: {', '.join(ligaments)}",
                             source=params.source or src, field="ligaments")
        missing = [f"{n}.{k}" for n in ligaments for k in ("k", "ref_strain", "lin_strain")
                   if f"{n}.{k}" not in params]
        if missing:
            raise InputError(f"parameter set {params.source or params.name} lacks {', '.join(missing)}",
                             source=src, field="parameters")
        return cls(name=str(doc.get("name", path.stem)), ligaments=ligaments,
                   compartments=compartments, tuberosity=landmarks["tibial_tuberosity"],
                   parameters=params, gate=gate, working_set=working_set, landmarks=landmarks, source=src,
                   description=str(doc.get("description", "")), candidates=candidates)

    @property
    def ligament_names(self) -> list[str]:
        return list(self.ligaments)

    @cached_property
    def model(self):
        """The CasADi model of this knee (:class:`~kneenlp.model.kneemodel.KneeModel`), built once."""
        from kneenlp.model.kneemodel import KneeModel  # the model is built from the knee

        return KneeModel(self)

    def elements(self) -> list[ForceElement]:
        """The knee's force elements: its ligaments, one contact element per compartment and the
        candidate bundles of its file (neutral: stiffness 0)."""
        contact = [SphereContact(c.name, c.sphere_center, c.sphere_radius, c.points, c.areas, self.gate,
                                 self.working_set) for c in self.compartments.values()]
        return [*self.ligaments.values(), *contact, *self.candidates]

    def condyle_centres(self) -> list[np.ndarray]:
        """Centre of each femoral condyle (femoral frame, m): where the meniscus springs act."""
        return [c.sphere_center for c in self.compartments.values()]

    def with_parameters(self, parameters: ParameterSet | str | Path) -> Knee:
        """The same geometry with another parameter set."""
        params = parameters if isinstance(parameters, ParameterSet) else ParameterSet.load(parameters)
        return dataclasses.replace(self, parameters=params)


class _Transform:
    """File coordinates -> the model's femoral frame (m): scale, optional rigid transform from
    scanner coordinates built from ISB landmarks, mirror of a left knee, origin shift."""

    def __init__(self, scale: float, mirror: np.ndarray):
        self.scale, self.mirror = scale, mirror
        self.rotation, self.origin, self.shift = np.eye(3), np.zeros(3), np.zeros(3)
        self.centres: list[np.ndarray] = []

    def from_landmarks(self, lm: dict[str, np.ndarray], side: str, src: str) -> None:
        """ISB femoral frame (Wu et al. 2002): Y from the epicondyle midpoint to the hip centre,
        Z along the epicondylar axis orthogonalised to Y, pointing right, X = Y x Z."""
        need = ("hip_center", "medial_epicondyle", "lateral_epicondyle")
        missing = [n for n in need if n not in lm]
        if missing:
            raise InputError(f"coordinates = 'scan' needs landmarks {', '.join(missing)}", source=src,
                             field="landmarks")
        mid = (lm["medial_epicondyle"] + lm["lateral_epicondyle"]) / 2
        y = lm["hip_center"] - mid
        z = lm["lateral_epicondyle"] - lm["medial_epicondyle"]
        if side == "left":
            z = -z  # ISB Z points right; the mirror below turns the lateral side to +Z
        y = y / np.linalg.norm(y)
        z = z - (z @ y) * y
        if np.linalg.norm(z) < 1e-9:
            raise InputError("epicondyles on the hip-knee line: frame undefined", source=src, field="landmarks")
        z = z / np.linalg.norm(z)
        self.rotation = np.vstack([np.cross(y, z), y, z])
        self.origin = mid * self.scale

    def __call__(self, p: np.ndarray) -> np.ndarray:
        pts = np.atleast_2d(np.asarray(p, float))
        out = (self.rotation @ (pts.T * self.scale - self.origin[:, None])).T * self.mirror - self.shift
        return out[0] if np.ndim(p) == 1 else out


def read_mesh(path: Path, transform: _Transform, *, field: str, knee_file: str) -> trimesh.Trimesh:
    """Load a cartilage mesh with trimesh, validate it and convert it to the femoral frame (m)."""
    if not path.is_file():
        raise InputError(f"mesh file not found: {path}", source=knee_file, field=field)
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many exception types for broken files
        raise InputError(f"cannot read mesh {path.name} ({type(exc).__name__}: {exc})",
                         source=knee_file, field=field) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"mesh {path.name} has no triangles", source=knee_file, field=field)
    if not np.all(np.isfinite(mesh.vertices)):
        raise InputError(f"mesh {path.name} has non-finite vertices", source=knee_file, field=field)
    mesh = mesh.copy()
    mesh.vertices = transform(mesh.vertices)
    if transform.mirror[2] < 0:
        mesh.invert()  # keep the face orientation after mirroring
    return mesh


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere through ``points``: (centre, radius, RMS radial deviation)."""
    center, radius, _ = trimesh.nsphere.fit_nsphere(np.asarray(points, dtype=float))
    dev = np.linalg.norm(points - center, axis=1) - radius
    return np.asarray(center, dtype=float), float(radius), float(np.sqrt(np.mean(dev**2)))
