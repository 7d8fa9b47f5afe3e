"""OpenSim knee models in: an .osim file becomes a kneenlp knee (TOML + meshes).

``kneenlp import-osim MODEL.osim --out KNEE_DIR`` (:func:`import_osim`) reads the femur and tibia
bodies of the knee joint, every femur-tibia Blankevoort1991Ligament bundle (stiffness, slack
length, transition strain, the path points on the two bodies and the surface the path wraps,
:mod:`kneenlp.io.import_wraps`; path points on other bodies are reported and skipped), the tibiofemoral
contact meshes (Smith2018ContactMesh, found next to the model or in ``--geometry DIR``), and
writes a knee whose multi-bundle ligaments are the model's bundle groups (``ACLam``, ``ACLpl``,
... by default; ``groups="coarse"`` merges them into ``ACL``, ``PCL``, ``MCL``, ...).  Each group
is identified by a stiffness scale and a reference-strain offset shared by its bundles
(:mod:`kneenlp.model.ligament`).

Coordinates stay the model's (metres, the femur body's frame for femoral points and meshes, the
tibia body's for tibial ones: they coincide at the model's default pose, the reference pose);
kneenlp builds its femoral frame from cylinder fits to the condyles and the hip centre when the
knee is loaded (``coordinates = "scan"``, ``frame = "cylinders"``).  A femoral cartilage mesh the
model names but the geometry folder lacks can be replaced by another surface (``femur_mesh``, e.g.
the subchondral bone) with ``femur_offset`` (its distance inside the articular surface, m).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

from kneenlp.base.atomic import write_text_atomic
from kneenlp.base.errors import InputError
from kneenlp.base.keywords import keyword_options
from kneenlp.base.modes import Groups, checked
from kneenlp.io.import_wraps import wrap_table
from kneenlp.io.osim import LineElement, OsimError, OsimModel, knee_line_elements, ligament_groups, read_osim
from kneenlp.model.knee_file import PLAUSIBLE_MM
from kneenlp.model.laws import BlankevoortLaw
from kneenlp.model.parameters import imported_parameter_set


@dataclass
class ImportReport:
    """What :func:`import_osim` did: the knee file, the groups and the skipped parts."""

    knee_file: Path
    groups: dict[str, list[str]]
    skipped: list[str] = field(default_factory=list)

    @property
    def n_bundles(self) -> int:
        return sum(len(v) for v in self.groups.values())

    def text(self) -> str:
        lines = [f"wrote {self.knee_file}: {self.n_bundles} bundles in {len(self.groups)} groups ("
                 + ", ".join(f"{g} {len(b)}" for g, b in self.groups.items()) + ")"]
        lines += [f"skipped: {s}" for s in self.skipped]
        return "\n".join(lines)


def _find_mesh(name: str, folders: list[Path], source: str) -> Path:
    for folder in folders:
        for candidate in (folder / name, folder / "Geometry" / name):
            if candidate.is_file():
                return candidate
    raise InputError(f"mesh {name!r} not found in {', '.join(str(f) for f in folders)} (give --geometry DIR, or "
                     "--femur-mesh for a femoral surface the model's folder lacks)", source=source,
                     field="Smith2018ContactMesh")


@dataclass(frozen=True)
class OsimImport:
    """The keyword options of :func:`import_osim` (its docstring), checked in one place (:meth:`of`)."""

    geometry: str | Path | None = None
    groups: Groups = "fine"
    femur_body: str = "femur_distal_r"
    tibia_body: str = "tibia_proximal_r"
    femur_mesh: str | Path | None = None
    femur_offset: float = 0.0
    tuberosity: tuple[float, float, float] | None = None



@dataclass(frozen=True)
class _MeshCopy:
    """Where :func:`_copy_contact_mesh` looks for a mesh file (``folders``), the model its errors
    name (``source``), the knee's directory it copies into (``out``) and the notes it adds to
    (``skipped``)."""

    folders: list[Path]
    source: str
    out: Path
    skipped: list[str]


def import_osim(osim: str | Path, out: str | Path, **options) -> ImportReport:
    """Write a kneenlp knee from an OpenSim model (see module docstring); lengths in metres.
    Keyword options (:class:`OsimImport`): ``geometry`` (a folder of the model's mesh files),
    ``groups`` ("fine"), ``femur_body`` ("femur_distal_r"), ``tibia_body`` ("tibia_proximal_r"),
    ``femur_mesh`` (the femoral contact mesh's file in place of the model's), ``femur_offset`` (m,
    the cartilage on it, 0), ``tuberosity``: the tibial tuberosity in the tibia body's frame (m),
    for a model without patellar-tendon bundles (:func:`_tuberosity`)."""
    opts = keyword_options(OsimImport, "import_osim", options)
    groups, femur_body, tibia_body = opts.groups, opts.femur_body, opts.tibia_body
    femur_offset = opts.femur_offset
    osim = Path(osim)
    _check_femur_offset(femur_offset)
    model = _read_model(osim, groups, (femur_body, tibia_body))
    keep, skipped = _kept_bundles(model, femur_body, tibia_body)
    wraps = _wraps(model, keep, {"femur": femur_body, "tibia": tibia_body}, skipped)
    grouped = ligament_groups(list(keep))[groups]
    out = Path(out)
    (out / "meshes").mkdir(parents=True, exist_ok=True)
    copying = _MeshCopy(([Path(opts.geometry)] if opts.geometry else []) + [osim.parent], str(osim), out, skipped)
    meshes = {role: _copy_contact_mesh(model, role, body, opts.femur_mesh if role == "femur" else None, copying)
              for role, body in (("femur", femur_body), ("tibia", tibia_body))}
    landmarks, where = _landmarks(model, femur_body, tibia_body, opts.tuberosity, out / meshes["tibia"])
    skipped.append(f"tibial tuberosity {where}")
    doc: dict = {
        "name": osim.stem, "side": "right", "units": "m", "coordinates": "scan", "frame": "cylinders",
        "description": f"imported from {osim.name} by kneenlp import-osim ({groups} bundle groups)",
        "parameters": "parameters.toml",
        "landmarks": landmarks,
        "contact": {"femur": meshes["femur"], "tibia": meshes["tibia"], "gate": 1e-5, "grid_spacing": 5e-4,
                    **({"femur_offset": float(femur_offset)} if femur_offset else {})},
        "ligaments": {group: _ligament_table(keep, names, wraps) for group, names in grouped.items()},
    }
    header = (f"# kneenlp knee imported from {osim.name} (kneenlp import-osim; {groups} bundle groups).\n"
              f"# Coordinates: metres in the model's {femur_body} frame ({tibia_body} for tibial points).\n"
              "# Bundles: stiffness in N per unit strain (OpenSim linear_stiffness), slack_length in m (of the\n"
              "# path, wrapped where OpenSim wraps it: wrap tables, the surface in its body's frame),\n"
              "# transition_strain as OpenSim's (the paper's linear strain limit is half of it); the law is\n"
              "# OpenSim's Blankevoort1991Ligament (law = \"blankevoort\", kneenlp.model.laws).\n")
    knee_file = write_text_atomic(out / "knee.toml", header + tomli_w.dumps(doc))
    write_text_atomic(out / "parameters.toml",
                      imported_parameter_set("OpenSim", "their own stiffness and slack length"))
    return ImportReport(knee_file, grouped, skipped)


def _check_femur_offset(femur_offset: float) -> None:
    """The cartilage thickness on the bone of ``--femur-mesh`` (m) is 0 or within the plausible range."""
    lo, hi = PLAUSIBLE_MM["femur_offset"]
    if not (femur_offset == 0 or max(lo, 0.1) <= femur_offset * 1e3 <= hi):
        raise InputError(f"{femur_offset * 1e3:g} mm: the cartilage thickness on the bone of --femur-mesh is 0 or "
                         f"0.1-{hi:g} mm (a negative offset puts the surface inside the bone; below 0.1 mm: given in "
                         "m?)", field="--femur-offset")


def _read_model(osim: Path, groups: Groups, bodies: tuple[str, str]) -> OsimModel:
    """The OpenSim model at ``osim``, checked to have the knee's femur and tibia ``bodies``; ``groups``
    is the bundle grouping asked for (``fine`` or ``coarse``)."""
    try:
        model = read_osim(osim)
    except OsimError as exc:
        raise InputError(str(exc)) from None
    checked("grouping", groups, Groups, field="--groups")
    for body in bodies:
        if body not in model.bodies:
            raise InputError(f"no body {body!r}; bodies: {', '.join(model.bodies)}", source=str(osim),
                             field="BodySet")
    return model


def _kept_bundles(model: OsimModel, femur_body: str, tibia_body: str) -> tuple[dict[str, LineElement], list[str]]:
    """The femur-tibia bundles kneenlp represents (load bearing, on the two bodies) by name, and
    the notes on what the import leaves out: the reader's, bundles with points on other bodies."""
    lines = knee_line_elements(model, femur_body, tibia_body)
    skipped = [s for s in model.skipped if "PathWrap" not in s]
    keep = {}
    for name, e in lines.items():
        if e.ignored_points:
            skipped.append(f"{name}: path points {', '.join(e.ignored_points)} on other bodies "
                           "(the bundle is left out)")
        elif e.linear_stiffness > 0:
            keep[name] = e
    return keep, skipped


def _wraps(model: OsimModel, keep: dict[str, LineElement], bodies: dict[str, str], skipped: list[str]) -> dict:
    """Each wrapping bundle's ``wrap`` table (:func:`kneenlp.io.import_wraps.wrap_table`); what
    stays straight is added to ``skipped``, and the wrapped bundles are summed up there."""
    tables = {}
    for name, line in keep.items():
        table, note = wrap_table(model, line, bodies)
        if note:
            skipped.append(note)
        if table is not None:
            tables[name] = table
    by_surface: dict[str, list[str]] = {}
    for name in tables:
        by_surface.setdefault(keep[name].wraps[0], []).append(name)
    if by_surface:
        skipped.append("wrapping surfaces imported: " + "; ".join(
            f"{surface} ({model.wrap_objects[surface].type[4:].lower()}): {', '.join(_ranges(names))}"
            for surface, names in by_surface.items()))
    return tables


def _copy_contact_mesh(model: OsimModel, role: str, body: str, given: str | Path | None, copying: _MeshCopy) -> str:
    """Copy the tibiofemoral contact mesh of ``body`` (or the ``given`` file) into ``out/meshes``
    and return its path relative to ``out``; a mesh placed with an offset in its body is noted in
    ``skipped`` (``copying``: those two, the folders searched and the source named)."""
    folders, source, out, skipped = copying.folders, copying.source, copying.out, copying.skipped
    found = [c for c in model.contact_meshes.values() if c.body == body]
    if given is not None:
        path = Path(given)
        if not path.is_file():
            raise InputError(f"mesh file not found: {path}", field="--femur-mesh")
    elif not found:
        raise InputError(f"no Smith2018ContactMesh on body {body!r}", source=source, field="ContactGeometrySet")
    else:
        if len(found) > 1 or np.any(found[0].X_body_mesh(model) != np.eye(4)):
            skipped.append(f"{role}: contact mesh {found[0].name!r} used as placed in its body (offsets ignored)")
        path = _find_mesh(found[0].mesh_file, folders, source)
    shutil.copyfile(path, out / "meshes" / path.name)
    return f"meshes/{path.name}"


def _ligament_table(keep: dict[str, LineElement], names: list[str], wraps: dict[str, dict]) -> dict:
    """The knee-file table of one bundle group: OpenSim's law and each bundle's attachments (m),
    stiffness (N per unit strain), slack length (m), transition strain and wrapping surface."""
    return {"law": BlankevoortLaw.name, "bundles": [
        {"name": n, "femur": [float(v) for v in keep[n].femoral_point],
         "tibia": [float(v) for v in keep[n].tibial_point], "stiffness": float(keep[n].linear_stiffness),
         "slack_length": float(keep[n].slack_length), "transition_strain": float(keep[n].transition_strain),
         **({"wrap": wraps[n]} if n in wraps else {})}
        for n in names]}


def _landmarks(model, femur_body: str, tibia_body: str, tuberosity, tibial_mesh: Path) -> tuple[dict, str]:
    """(landmarks, where the tuberosity came from): the hip centre (origin of the femur body the
    knee's femur is welded to, when it is the child of a hip joint) and the tibial tuberosity
    (:func:`_tuberosity`)."""
    out = {}
    for body in sorted(model.welded_bodies(femur_body) - {femur_body}):
        out["hip_center"] = [float(v) for v in model.transform(femur_body, body)[:3, 3]]
        break
    out["tibial_tuberosity"], where = _tuberosity(model, tibia_body, tuberosity, tibial_mesh)
    return out, where


#: Where the tuberosity is placed from the tibial articular surface when nothing else says
#: (OpenSim body axes: X anterior, Y proximal): 30 mm distal of its centroid, 10 mm anterior of its
#: anterior rim; an estimate of an adult tibia (the tuberosity a few centimetres below the joint
#: line, in front of the plateau), said in the import report.  Only the paper's femoral-axis
#: drawer force acts there (a robot's joint loads act at the tibial origin).
TUBEROSITY_DISTAL = 0.030
TUBEROSITY_ANTERIOR = 0.010


def _tuberosity(model, tibia_body: str, given, tibial_mesh: Path) -> tuple[list[float], str]:
    """The tibial tuberosity (tibia body frame, m) and where it came from: ``given`` (the user's
    ``--tuberosity``), else the centroid of the patellar-tendon insertions (bundles ``PT...``),
    else estimated from the tibial contact mesh (:data:`TUBEROSITY_DISTAL`)."""
    if given is not None:
        return [float(v) for v in given], "as given (--tuberosity)"
    tibia = model.welded_bodies(tibia_body)
    tendon = [lig.points[-1] for name, lig in model.ligaments.items()
              if name.upper().startswith("PT") and lig.points and lig.points[-1].body in tibia]
    if tendon:
        point = np.mean([model.point_in_body(p, tibia_body) for p in tendon], axis=0)
        return [float(v) for v in point], f"from the patellar-tendon insertions ({len(tendon)} bundles)"
    import trimesh

    vertices = np.asarray(trimesh.load(tibial_mesh, force="mesh", process=False).vertices, float)
    centre = vertices.mean(axis=0)
    point = [vertices[:, 0].max() + TUBEROSITY_ANTERIOR, centre[1] - TUBEROSITY_DISTAL, centre[2]]
    return ([float(v) for v in point],
            f"estimated from the tibial mesh (no patellar-tendon bundle): {TUBEROSITY_DISTAL * 1e3:.0f} mm distal of "
            f"its centroid, {TUBEROSITY_ANTERIOR * 1e3:.0f} mm anterior of its rim; give --tuberosity X,Y,Z (mm, "
            f"{tibia_body} frame) to place it")


def _ranges(names: list[str]) -> list[str]:
    """``["MCLd1", ..., "MCLd5"]`` -> ``["MCLd1-5"]`` (bundle names grouped for a message)."""
    fine = ligament_groups(names)["fine"]
    return [f"{g}{b[0][len(g):]}-{b[-1][len(g):]}" if len(b) > 1 else b[0] for g, b in fine.items()]
