"""Articular surfaces of the implant example knee (``Knee.named("implant")``), built with trimesh.

A synthetic total knee arthroplasty (right knee) in the ISB femoral frame (X anterior, Y proximal,
Z lateral, mm; origin on the flexion axis midway between the condyles), in the reference pose
(0 deg flexion, all five coordinates zero):

* femoral component: per condyle (medial at ``z = -21``, lateral at ``z = +21``) a surface swept
  in the sagittal plane along a J-curve, a distal arc of radius ``R_d`` joined tangentially to a
  posterior arc of radius ``R_p`` (the classic multi-radius design), with a convex coronal
  section of radius ``R_c``.  The posterior arc is centred on the flexion axis (the origin); the
  distal arc is placed so that the lowest point at 0 deg lies at ``y = lowest_y``, which fixes the
  angle of the junction: ``cos(theta_t) = (R_d + lowest_y) / (R_d - R_p)``.  Each piece is a torus
  about an axis parallel to Z through its arc centre (tube radius ``R_c``).  The surface spans
  sagittal normal directions from ``anterior_deg`` in front of distal to ``posterior_deg`` behind
  it (contact from hyperextension to deep flexion), outward normals;
* tibial inlay: the articular top surface only, one dish per condyle,
  ``y = y0 + sag(x - x0, R_s) + sag(z - z0, R_t)`` with ``sag(u, R) = R - sqrt(R^2 - u^2)``
  (circular profiles of radius ``R_s`` sagittally and ``R_t`` coronally, both larger than the
  femoral radii: moderately conforming), cut to a rounded rectangle (superellipse) around the
  dish centre.  The dish centre lies under the femoral lowest point at 0 deg (``x0``, which is
  ``(R_d - R_p) sin(theta_t)`` anterior of the flexion axis) and ``y0`` is set so that the
  component penetrates the inlay by ``penetration`` there in the reference pose.

Near-conforming surfaces move the contact far: an offset ``e`` between the femoral arc centre
and the dish centre puts the contact ``e R_s / (R_s - R)`` from the dish bottom.  With the
synthetic knee's ligaments (neutral internal rotation of about 7 deg at 0 deg flexion, varus
coupled with about 20 deg internal rotation at 30 deg) the contact patches of Set 3 reach
+-22.3 mm antero-posteriorly and 12.4 mm medio-laterally from the dish centres, hence the
inlay's extent of +-25 mm by +-15 mm and the condyles' half width of 17 mm (a tibial point never
lies beyond the femoral surface's edge, where the distance field is not meaningful).

Run ``python -m kneenlp.model.implant [DIR]`` to (re)write ``knee.toml`` and ``meshes/*.stl`` of the
implant knee (default ``kneenlp/resources/knees/implant``).  Landmarks, ligament attachments and
candidate elements are copied from the synthetic knee's file.
"""

from __future__ import annotations

import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from kneenlp.base.atomic import export_mesh_atomic, write_text_atomic

#: Medio-lateral positions of the medial and lateral condyle (mm, femoral frame).
CONDYLE_Z = {"medial": -21.0, "lateral": 21.0}
#: The knee whose landmarks, ligaments and candidates the implant knee reuses.
SYNTHETIC_TOML = Path(__file__).resolve().parents[1] / "resources" / "knees" / "synthetic" / "knee.toml"
#: Where the shipped implant knee lives (``knee.toml`` and ``meshes/``).
IMPLANT_DIR = Path(__file__).resolve().parents[1] / "resources" / "knees" / "implant"


@dataclass(frozen=True)
class FemoralComponent:
    """Dimensions of the femoral component (mm, deg; femoral frame)."""

    distal_radius: float = 44.0  # sagittal radius of the distal arc
    posterior_radius: float = 20.0  # sagittal radius of the posterior arc, centred on the flexion axis
    coronal_radius: float = 25.0  # medio-lateral convex radius of each condyle
    lowest_y: float = -21.0  # proximal coordinate of the lowest point at 0 deg flexion
    anterior_deg: float = 35.0  # the surface starts this far anterior of distal ...
    posterior_deg: float = 120.0  # ... and ends this far posterior (sagittal normal direction)
    half_width: float = 17.0  # medio-lateral half width of each condyle
    spacing: float = 1.0  # target edge length

    @property
    def junction_deg(self) -> float:
        """Angle from distal (towards posterior) where the distal arc meets the posterior arc."""
        r_d, r_p = self.distal_radius, self.posterior_radius
        return float(np.degrees(np.arccos((r_d + self.lowest_y) / (r_d - r_p))))

    @property
    def distal_centre(self) -> np.ndarray:
        """Centre of the distal arc (x, y), mm; the posterior arc is centred at the origin."""
        return -(self.distal_radius - self.posterior_radius) * _normal(np.radians(self.junction_deg))

    @property
    def lowest_x(self) -> float:
        """Antero-posterior position of the lowest point at 0 deg flexion (mm)."""
        return float(self.distal_centre[0])


@dataclass(frozen=True)
class Inlay:
    """Dimensions of the tibial inlay (mm; tibial frame = femoral frame in the reference pose)."""

    sagittal_radius: float = 80.0
    coronal_radius: float = 40.0
    half_ap: float = 25.0  # antero-posterior half extent of each dish
    half_ml: float = 15.0  # medio-lateral half extent of each dish
    corner: float = 4.0  # superellipse exponent of the outline (2: ellipse, large: rectangle)
    penetration: float = 0.1  # of the femoral component at its lowest point in the reference pose
    spacing: float = 0.9  # vertex spacing


def _normal(theta: np.ndarray | float) -> np.ndarray:
    """Outward sagittal normal (x, y) at ``theta`` (rad) from distal (-Y) towards posterior (-X)."""
    theta = np.asarray(theta, dtype=float)
    return np.stack([-np.sin(theta), -np.cos(theta)], axis=-1)


def _grid_faces(n_u: int, n_v: int, flip: bool) -> np.ndarray:
    """Two triangles per cell of an ``n_u`` x ``n_v`` vertex grid (row-major indices)."""
    idx = np.arange(n_u * n_v).reshape(n_u, n_v)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.vstack([np.column_stack([a, b, d]), np.column_stack([b, c, d])])
    return faces[:, ::-1] if flip else faces


def sagittal_profile(design: FemoralComponent) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The J-curve sampled at about ``spacing`` of arc length, anterior to posterior: normal angle
    ``theta`` (rad, from distal towards posterior), arc centre (x, y) and radius (mm) per sample;
    the junction of the two arcs is a sample."""
    t0, tj, t1 = np.radians([-design.anterior_deg, design.junction_deg, design.posterior_deg])
    arcs = [(t0, tj, design.distal_radius, design.distal_centre), (tj, t1, design.posterior_radius, np.zeros(2))]
    thetas, centres, radii = [], [], []
    for k, (a, b, radius, centre) in enumerate(arcs):
        n = max(2, int(np.ceil(radius * (b - a) / design.spacing)))
        th = np.linspace(a, b, n + 1)[(1 if k else 0):]
        thetas.append(th)
        centres.append(np.broadcast_to(centre, (len(th), 2)))
        radii.append(np.full(len(th), radius))
    return np.concatenate(thetas), np.vstack(centres), np.concatenate(radii)


def condyle_surface(design: FemoralComponent, z: float) -> trimesh.Trimesh:
    """Articular surface of one femoral condyle centred at medio-lateral position ``z`` (mm):
    the J-curve swept with a coronal circle of radius ``coronal_radius``; outward normals."""
    theta, centre, radius = sagittal_profile(design)
    rc = design.coronal_radius
    phi_max = np.arcsin(design.half_width / rc)
    n_phi = max(2, int(np.ceil(2 * phi_max * rc / design.spacing)))
    phi = np.linspace(-phi_max, phi_max, n_phi + 1)
    n = _normal(theta)  # (S, 2)
    spine = centre + (radius - rc)[:, None] * n  # centre of the coronal circle, sagittal plane
    xy = spine[:, None, :] + rc * np.cos(phi)[None, :, None] * n[:, None, :]
    zz = np.broadcast_to(z + rc * np.sin(phi)[None, :], xy.shape[:2])
    vertices = np.column_stack([xy[..., 0].ravel(), xy[..., 1].ravel(), zz.ravel()])
    mesh = trimesh.Trimesh(vertices, _grid_faces(len(theta), len(phi), flip=False), process=False)
    outward = np.column_stack([n[:, None, 0] * np.cos(phi), n[:, None, 1] * np.cos(phi),
                               np.broadcast_to(np.sin(phi), (len(theta), len(phi)))])
    if np.mean(np.einsum("ij,ij->i", mesh.vertex_normals, outward.reshape(-1, 3))) < 0:
        mesh.invert()
    return mesh


def femoral_component(design: FemoralComponent = FemoralComponent()) -> trimesh.Trimesh:
    """Both condyles of the femoral component in one mesh (mm, femoral frame)."""
    return trimesh.util.concatenate([condyle_surface(design, z) for z in CONDYLE_Z.values()])


def dish_surface(inlay: Inlay, femur: FemoralComponent, z: float) -> trimesh.Trimesh:
    """One dish of the tibial inlay under the condyle at ``z`` (mm, tibial frame), normals +Y."""
    x0, y0 = femur.lowest_x, femur.lowest_y + inlay.penetration

    def sag(u: np.ndarray, r: float) -> np.ndarray:
        return r - np.sqrt(r**2 - u**2)

    n_x = int(np.ceil(2 * inlay.half_ap / inlay.spacing))
    n_z = int(np.ceil(2 * inlay.half_ml / inlay.spacing))
    gx, gz = np.meshgrid(np.linspace(-inlay.half_ap, inlay.half_ap, n_x + 1),
                         np.linspace(-inlay.half_ml, inlay.half_ml, n_z + 1), indexing="ij")
    gy = y0 + sag(gx, inlay.sagittal_radius) + sag(gz, inlay.coronal_radius)
    vertices = np.column_stack([(gx + x0).ravel(), gy.ravel(), (gz + z).ravel()])
    faces = _grid_faces(*gx.shape, flip=True)  # +Y normals
    inside = (np.abs(gx / inlay.half_ap) ** inlay.corner + np.abs(gz / inlay.half_ml) ** inlay.corner) <= 1.0 + 1e-9
    mesh = trimesh.Trimesh(vertices, faces[inside.ravel()[faces].all(axis=1)], process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


def inlay_surface(inlay: Inlay = Inlay(), femur: FemoralComponent = FemoralComponent()) -> trimesh.Trimesh:
    """Both dishes of the tibial inlay in one mesh (two connected components; mm, tibial frame)."""
    return trimesh.util.concatenate([dish_surface(inlay, femur, z) for z in CONDYLE_Z.values()])


def _toml_value(value: object) -> str:
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(float(value)) if isinstance(value, float) else str(value)


def _toml_tables(doc: dict, prefix: str) -> list[str]:
    """``[prefix.name]`` tables of simple keys (values: strings, numbers, lists)."""
    lines = []
    for name, table in doc.items():
        lines += ["", f"[{prefix}.{name}]", *(f"{k} = {_toml_value(v)}" for k, v in table.items())]
    return lines


def knee_toml(femur: FemoralComponent = FemoralComponent(), inlay: Inlay = Inlay(),
              synthetic: Path = SYNTHETIC_TOML) -> str:
    """The implant knee's TOML: these surfaces plus the synthetic knee's landmarks, ligaments and
    candidates (mm, femoral frame)."""
    with open(synthetic, "rb") as fh:
        syn = tomllib.load(fh)
    description = (
        f"Synthetic right total knee arthroplasty generated by `python -m kneenlp.model.implant`: a multi-radius "
        f"femoral component (sagittal J-curve: distal radius {femur.distal_radius:g} mm joined tangentially at "
        f"{femur.junction_deg:.1f} deg to a posterior radius {femur.posterior_radius:g} mm centred on the flexion "
        f"axis; coronal radius {femur.coronal_radius:g} mm per condyle, condyles at z = +-21 mm) against a dished "
        f"polyethylene inlay (sagittal radius {inlay.sagittal_radius:g} mm, coronal radius "
        f"{inlay.coronal_radius:g} mm; dishes +-{inlay.half_ap:g} x +-{inlay.half_ml:g} mm). Landmarks and ligament "
        "attachments of the synthetic knee; in a real TKA the ACL is resected, but all four ligaments are kept so "
        "that the paper's identification applies")
    lines = [
        '# kneenlp knee description: the implant example knee (a right knee), Knee.named("implant").',
        "# Generated by `python -m kneenlp.model.implant` (kneenlp/model/implant.py); do not edit by hand.",
        "# Millimetres in the ISB femoral frame (X anterior, Y proximal, Z lateral), origin on the flexion",
        "# axis midway between the condyles; tibial points in the tibial frame (= femoral frame at 0 deg",
        "# flexion, all coordinates zero).  Landmarks, ligaments and candidates: the synthetic knee's.",
        "",
        'name = "implant"',
        f"description = {_toml_value(description)}",
        'side = "right"',
        'units = "mm"',
        'coordinates = "femoral"',
        'parameters = "../../parameters/table1.toml"',
        "",
        "[landmarks]   # hip centre and epicondyles: femoral frame; the others: tibial frame",
        *(f"{k} = {_toml_value(v)}" for k, v in syn["landmarks"].items()),
        "",
        "# The component surface is the articular surface (no femur_offset); the inlay holds both",
        "# dishes (two connected components, split by the loader).",
        "[contact]",
        'femur = "meshes/femur_component.stl"',
        'tibia = "meshes/inlay.stl"',
        "gate = 0.01          # mm, width of the smooth contact gate",
        "grid_spacing = 0.5   # mm, femoral distance-field grid",
        *_toml_tables(syn["ligaments"], "ligaments"),
        *_toml_tables(syn.get("candidates", {}), "candidates"),
    ]
    return "\n".join(lines) + "\n"


def write_implant_knee(directory: Path, femur: FemoralComponent = FemoralComponent(),
                       inlay: Inlay = Inlay()) -> list[Path]:
    """Write ``knee.toml``, ``meshes/femur_component.stl`` and ``meshes/inlay.stl`` (mm) into
    ``directory``; returns the written paths."""
    meshes = directory / "meshes"
    meshes.mkdir(parents=True, exist_ok=True)
    written = [meshes / "femur_component.stl", meshes / "inlay.stl", directory / "knee.toml"]
    export_mesh_atomic(femoral_component(femur), written[0])
    export_mesh_atomic(inlay_surface(inlay, femur), written[1])
    write_text_atomic(written[2], knee_toml(femur, inlay))
    return written


if __name__ == "__main__":  # pragma: no cover - maintenance script
    for p in write_implant_knee(Path(sys.argv[1]) if len(sys.argv) > 1 else IMPLANT_DIR):
        print(p)
