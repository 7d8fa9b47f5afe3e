"""Reading an .osim file (XML, standard library only) into an :class:`~kneenlp.io.osim.model.OsimModel`,
its ligament groups by name, and the knee's ligaments as line elements in kneenlp's convention
(femoral and tibial attachment points, m).  Conventions: :mod:`kneenlp.io.osim`."""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET

import numpy as np

from kneenlp.io.osim.kinematics import (
    OsimError,
    _apply,
    _Constant,
    _Function,
    _Linear,
    _Multiplier,
    _PiecewiseLinear,
    _SimmSpline,
    _Unsupported,
)
from kneenlp.io.osim.model import (
    _LIGAMENT_TAG,
    _SUPPORTED_JOINTS,
    BLANKEVOORT_DEFAULTS,
    BodyInfo,
    ContactMesh,
    Coordinate,
    Joint,
    Ligament,
    MeshGeometry,
    OffsetFrame,
    OsimModel,
    PathPoint,
    TransformAxis,
    WrapObject,
)

_SKIPPED_POINT_TAGS = ("ConditionalPathPoint", "MovingPathPoint")
_WRAP_TAGS = ("WrapEllipsoid", "WrapCylinder", "WrapSphere", "WrapTorus", "WrapCylinderObst",
              "WrapDoubleCylinderObst", "WrapSphereObst")


# --------------------------------------------------------------------------------------
# parsing
# --------------------------------------------------------------------------------------
class _Ctx:
    def __init__(self, path: str):
        self.path = path

    def err(self, what: str) -> OsimError:
        return OsimError(f"{self.path}: {what}")

    def text(self, el: ET.Element, tag: str, owner: str, required: bool = True) -> str | None:
        sub = el.find(tag)
        if sub is None or sub.text is None or not sub.text.strip():
            if required:
                raise self.err(f"{owner}: missing <{tag}>")
            return None
        return sub.text.strip()

    def floats(self, el: ET.Element, tag: str, owner: str, n: int | None = None,
               required: bool = True) -> np.ndarray | None:
        t = self.text(el, tag, owner, required)
        if t is None:
            return None
        try:
            v = np.array([float(s) for s in t.split()], float)
        except ValueError:
            raise self.err(f"{owner} <{tag}>: cannot parse '{t}' as numbers") from None
        if (n is not None and v.size != n) or not np.all(np.isfinite(v)):
            raise self.err(f"{owner} <{tag}>: expected {n or 'finite'} finite numbers, got '{t}'")
        return v

    def float1(self, el: ET.Element, tag: str, owner: str, required: bool = True) -> float | None:
        v = self.floats(el, tag, owner, 1, required)
        return None if v is None else float(v[0])

    def boolean(self, el: ET.Element, tag: str, owner: str, default: bool) -> bool:
        t = self.text(el, tag, owner, required=False)
        if t is None:
            return default
        if t.lower() not in ("true", "false"):
            raise self.err(f"{owner} <{tag}>: expected true/false, got '{t}'")
        return t.lower() == "true"


def _resolve(owner_path: str, ref: str) -> str:
    """Resolve an OpenSim socket path ``ref`` relative to the component at ``owner_path``."""
    ref = ref.strip()
    parts = [] if ref.startswith("/") else [p for p in owner_path.split("/") if p]
    for seg in ref.split("/"):
        if seg in ("", "."):
            continue
        if seg == "..":
            if parts:
                parts.pop()
        else:
            parts.append(seg)
    return "/" + "/".join(parts)


def _parse_function(ctx: _Ctx, el: ET.Element, owner: str) -> tuple[_Function, str]:
    tag = el.tag
    where = f"{owner} <{tag}>"
    if tag == "Constant":
        return _Constant(ctx.float1(el, "value", where)), tag
    if tag == "LinearFunction":
        c = ctx.floats(el, "coefficients", where, 2)
        return _Linear(float(c[0]), float(c[1])), tag
    if tag in ("SimmSpline", "PiecewiseLinearFunction"):
        x = ctx.floats(el, "x", where)
        y = ctx.floats(el, "y", where)
        if x.size != y.size or x.size < 1 or np.any(np.diff(x) <= 0):
            raise ctx.err(f"{where}: x must be strictly increasing and match y")
        if x.size == 1:
            return _Constant(float(y[0])), tag
        return (_SimmSpline(x, y) if tag == "SimmSpline" else _PiecewiseLinear(x, y)), tag
    if tag == "MultiplierFunction":
        holder = el.find("function")
        inner = list(holder) if holder is not None else []
        if len(inner) != 1:
            raise ctx.err(f"{where}: expected one function inside <function>")
        f, t = _parse_function(ctx, inner[0], owner)
        return _Multiplier(f, ctx.float1(el, "scale", where)), f"{tag}({t})"
    return _Unsupported(f"{ctx.path}: {where}: function type not supported by this reader"), tag


def _iter_components(el: ET.Element, path: str):
    """Yield (element, absolute_component_path) for every named XML element under ``el``.

    OpenSim component paths are formed from ``name`` attributes; unnamed containers such as
    ``<objects>``, ``<frames>``, ``<components>`` do not add a path segment."""
    for ch in el:
        name = ch.get("name")
        p = f"{path}/{name}" if name else path
        if name:
            yield ch, p
        yield from _iter_components(ch, p)


def read_osim(path: str | os.PathLike) -> OsimModel:
    """Parse an .osim file (OpenSim 4.x XML, incl. OpenSim JAM components) without OpenSim.

    The components are read in dependency order: bodies and offset frames, then the geometry
    placed on them (meshes, wrap objects), then the joints and coordinates, the ligaments and the
    contact meshes, each of which resolves frames read before.  Lengths stay the file's (m).

    Raises :class:`OsimError` with a one-line message naming the file and element for
    malformed XML, missing/unparseable required values, unresolvable frames or unknown
    path-point types inside a ligament."""
    path = os.fspath(path)
    ctx = _Ctx(path)
    model_el = _model_element(ctx)
    all_comps = list(_iter_components(model_el, ""))
    model = OsimModel(path, model_el.get("name", ""),
                      (model_el.findtext("length_units") or "").strip(),
                      (model_el.findtext("force_units") or "").strip(),
                      _read_bodies(ctx, model_el), _read_offset_frames(ctx, all_comps), {}, {}, {}, {}, {}, [])
    _read_geometry(ctx, model, all_comps)
    _read_joints(ctx, model, model_el)
    _read_ligaments(ctx, model, all_comps)
    _read_contact_meshes(ctx, model, all_comps)
    return model


def _model_element(ctx: _Ctx) -> ET.Element:
    """The ``<Model>`` element of the .osim document at ``ctx.path``."""
    try:
        root = ET.parse(ctx.path).getroot()
    except ET.ParseError as e:
        raise OsimError(f"{ctx.path}: malformed XML ({e})") from None
    except OSError as e:
        raise OsimError(f"{ctx.path}: cannot read file ({e.strerror})") from None
    if root.tag != "OpenSimDocument":
        raise ctx.err(f"root element <{root.tag}> is not <OpenSimDocument>")
    model_el = root.find("Model")
    if model_el is None:
        raise ctx.err("<OpenSimDocument> has no <Model> element")
    return model_el


def _read_bodies(ctx: _Ctx, model_el: ET.Element) -> dict[str, BodyInfo]:
    """The ground and the bodies of the ``BodySet`` by name (mass in kg, mass centre in m)."""
    bodies: dict[str, BodyInfo] = {"ground": BodyInfo("ground", "/ground", 0.0, np.zeros(3))}
    bodyset = model_el.find("BodySet/objects")
    for b in (bodyset if bodyset is not None else []):
        if b.tag != "Body":
            raise ctx.err(f"BodySet: unknown element <{b.tag}> '{b.get('name')}'")
        nm = b.get("name")
        if not nm:
            raise ctx.err("BodySet: <Body> without a name")
        where = f"Body '{nm}'"
        bodies[nm] = BodyInfo(nm, f"/bodyset/{nm}", ctx.float1(b, "mass", where),
                              ctx.floats(b, "mass_center", where, 3))
    return bodies


def _read_offset_frames(ctx: _Ctx, comps: list[tuple[ET.Element, str]]) -> dict[str, OffsetFrame]:
    """Every ``PhysicalOffsetFrame`` of the model, wherever it is declared, by component path
    (translation in m, orientation as body-fixed XYZ angles in rad)."""
    frames: dict[str, OffsetFrame] = {}
    for el, p in comps:
        if el.tag == "PhysicalOffsetFrame":
            where = f"PhysicalOffsetFrame '{p}'"
            par = ctx.text(el, "socket_parent", where)
            frames[p] = OffsetFrame(el.get("name"), p, _resolve(p, par),
                                    ctx.floats(el, "translation", where, 3),
                                    ctx.floats(el, "orientation", where, 3))
    return frames


def _read_geometry(ctx: _Ctx, model: OsimModel, comps: list[tuple[ET.Element, str]]) -> None:
    """Add the display meshes to their bodies and the wrap objects (dimensions in m) to ``model``."""
    for el, p in comps:
        if el.tag == "Mesh":
            where = f"Mesh '{p}'"
            sock = el.findtext("socket_frame") or ".."
            fr = _resolve(p, sock.strip())
            if fr == "/":
                # a geometry's path is <frame path>/<geometry name>: socket '..' names that frame
                fr = p.rsplit("/", 1)[0]
            body, _ = model.frame_in_body(fr)
            sf = ctx.floats(el, "scale_factors", where, 3, required=False)
            mg = MeshGeometry(el.get("name"), ctx.text(el, "mesh_file", where), fr, body,
                              np.ones(3) if sf is None else sf)
            model.bodies[body].meshes.append(mg)
        elif el.tag in _WRAP_TAGS:
            where = f"{el.tag} '{p}'"
            seg = p.split("/")
            body = "ground" if seg[1] == "ground" else seg[2]
            dims = {}
            for t in ("dimensions", "radius", "length", "inner_radius", "outer_radius"):
                v = ctx.floats(el, t, where, required=False)
                if v is not None and t in ("dimensions", "radius", "length") and not np.all(v > 0):
                    raise ctx.err(f"{where} <{t}>: a wrapping surface's size must be > 0 m, got "
                                  f"'{' '.join(f'{x:g}' for x in v)}'")
                if v is not None:
                    dims[t] = v
            rot = ctx.floats(el, "xyz_body_rotation", where, 3, required=False)
            tr = ctx.floats(el, "translation", where, 3, required=False)
            model.wrap_objects[el.get("name")] = WrapObject(
                el.get("name"), el.tag, body, np.zeros(3) if tr is None else tr,
                np.zeros(3) if rot is None else rot, dims, (el.findtext("quadrant") or "all").strip().lower())


def _read_joints(ctx: _Ctx, model: OsimModel, model_el: ET.Element) -> None:
    """Add the joints of the ``JointSet`` and their coordinates to ``model``; a joint type whose
    kinematics this reader does not evaluate is noted in ``model.skipped``."""
    jointset = model_el.find("JointSet/objects")
    for j in (jointset if jointset is not None else []):
        nm = j.get("name")
        jp = f"/jointset/{nm}"
        where = f"{j.tag} '{nm}'"
        pf = _resolve(jp, ctx.text(j, "socket_parent_frame", where))
        cf = _resolve(jp, ctx.text(j, "socket_child_frame", where))
        for fr in (pf, cf):
            try:
                model.frame_in_body(fr)
            except OsimError:
                raise ctx.err(f"{where}: frame '{fr}' not found") from None
        coords = _read_coordinates(ctx, j, where)
        for co in coords:
            model.coordinates[co.name] = co
        axes: list[TransformAxis] = []
        if j.tag == "CustomJoint":
            axes = _read_spatial_transform(ctx, j, where, model.skipped)
        elif j.tag not in _SUPPORTED_JOINTS:
            model.skipped.append(f"{ctx.path}: {where}: joint type not supported for kinematics "
                                 f"(parsed frames/coordinates only)")
        model.joints[nm] = Joint(nm, j.tag, pf, cf, coords, axes)


def _read_coordinates(ctx: _Ctx, joint: ET.Element, where: str) -> list[Coordinate]:
    """The coordinates of a joint (default value and range in rad or m; unbounded without a range)."""
    coords: list[Coordinate] = []
    for c in joint.findall("coordinates/Coordinate"):
        cw = f"{where} Coordinate '{c.get('name')}'"
        rng = ctx.floats(c, "range", cw, 2, required=False)
        dv = ctx.float1(c, "default_value", cw, required=False)
        coords.append(Coordinate(c.get("name"), joint.get("name"), 0.0 if dv is None else dv,
                                 (-math.inf, math.inf) if rng is None else (float(rng[0]), float(rng[1])),
                                 ctx.boolean(c, "locked", cw, False), ctx.boolean(c, "clamped", cw, False)))
    return coords


def _read_spatial_transform(ctx: _Ctx, joint: ET.Element, where: str, skipped: list[str]) -> list[TransformAxis]:
    """The six transform axes of a ``CustomJoint`` (rotation1-3, translation1-3); a function type
    this reader cannot evaluate is noted in ``skipped``."""
    st = joint.find("SpatialTransform")
    if st is None:
        raise ctx.err(f"{where}: missing <SpatialTransform>")
    axes: list[TransformAxis] = []
    for ta in st.findall("TransformAxis"):
        tw = f"{where} TransformAxis '{ta.get('name')}'"
        cn = tuple((ta.findtext("coordinates") or "").split())
        fel = [ch for ch in ta if ch.tag not in ("coordinates", "axis")]
        if len(fel) != 1:
            raise ctx.err(f"{tw}: expected exactly one function element")
        fn, ftype = _parse_function(ctx, fel[0], tw)
        if isinstance(fn, _Unsupported):
            skipped.append(fn.message)
        if not cn and not isinstance(fn, (_Constant, _Multiplier, _Unsupported)):
            fn = _Constant(fn(0.0))
        axes.append(TransformAxis(ta.get("name"), cn, ctx.floats(ta, "axis", tw, 3), fn, ftype))
    if [a.name for a in axes] != ["rotation1", "rotation2", "rotation3",
                                  "translation1", "translation2", "translation3"]:
        raise ctx.err(f"{where}: SpatialTransform must have rotation1-3, translation1-3")
    return axes


def _read_ligaments(ctx: _Ctx, model: OsimModel, comps: list[tuple[ET.Element, str]]) -> None:
    """Add every Blankevoort1991Ligament to ``model``; the parts of their paths that are not
    represented (moving points, wrapping) are noted in ``model.skipped``."""
    for el, p in comps:
        if el.tag != _LIGAMENT_TAG:
            continue
        nm = el.get("name")
        where = f"{_LIGAMENT_TAG} '{nm}'"
        if nm in model.ligaments:
            raise ctx.err(f"{where}: duplicate name")
        props, present = _ligament_properties(ctx, el, where)
        gp = el.find("GeometryPath")
        if gp is None:
            raise ctx.err(f"{where}: missing <GeometryPath>")
        pts, notes = _read_path_points(ctx, model, gp, f"{p}/{gp.get('name') or 'geometrypath'}", where)
        wraps = [w.findtext("wrap_object", "").strip() for w in gp.findall("PathWrapSet/objects/PathWrap")]
        for w in wraps:
            wo = model.wrap_objects.get(w)
            notes.append(f"{ctx.path}: {where}: PathWrap over '{w}'"
                         f"{' (' + wo.type + ' on ' + wo.body + ')' if wo else ' (wrap object not found)'}"
                         f" skipped: straight segments between fixed points are used")
        model.ligaments[nm] = Ligament(nm, props["linear_stiffness"], props["slack_length"],
                                       props["transition_strain"], props["damping_coefficient"],
                                       ctx.boolean(el, "appliesForce", where, True), pts, wraps, notes,
                                       tuple(present))
        model.skipped.extend(notes)


def _ligament_properties(ctx: _Ctx, el: ET.Element, where: str) -> tuple[dict[str, float], list[str]]:
    """A ligament's material properties (stiffness in N per unit strain, slack length in m,
    transition strain, damping coefficient; OpenSim's defaults for the optional ones) and the names
    of those the file gives."""
    props: dict[str, float] = {}
    present = []
    for key in ("linear_stiffness", "slack_length", "transition_strain", "damping_coefficient"):
        v = ctx.float1(el, key, where, required=key in ("linear_stiffness", "slack_length"))
        if v is None:
            v = BLANKEVOORT_DEFAULTS[key]
        else:
            present.append(key)
        props[key] = v
    if props["slack_length"] <= 0 or props["linear_stiffness"] < 0 or props["transition_strain"] <= 0:
        raise ctx.err(f"{where}: non-physical property values {props}")
    return props, present


def _read_path_points(ctx: _Ctx, model: OsimModel, gp: ET.Element, gp_path: str,
                      where: str) -> tuple[list[PathPoint], list[str]]:
    """The fixed path points of a ligament's ``GeometryPath`` (locations in m, in their frames and
    bodies) and notes on the coordinate-dependent points left out."""
    objs = gp.find("PathPointSet/objects")
    pts: list[PathPoint] = []
    notes: list[str] = []
    for pp in (objs if objs is not None else []):
        pw = f"{where} <{pp.tag}> '{pp.get('name')}'"
        if pp.tag in _SKIPPED_POINT_TAGS:
            notes.append(f"{ctx.path}: {pw}: skipped ({pp.tag} is coordinate dependent; "
                         f"only fixed PathPoints are used)")
            continue
        if pp.tag != "PathPoint":
            raise ctx.err(f"{pw}: unknown path point type")
        fr = _resolve(f"{gp_path}/{pp.get('name')}", ctx.text(pp, "socket_parent_frame", pw))
        try:
            body, X = model.frame_in_body(fr)
        except OsimError:
            raise ctx.err(f"{pw}: parent frame '{fr}' not found") from None
        loc = ctx.floats(pp, "location", pw, 3)
        pts.append(PathPoint(pp.get("name"), fr, body, loc, _apply(X, loc)))
    if len(pts) < 2:
        raise ctx.err(f"{where}: fewer than 2 fixed path points")
    return pts, notes


def _read_contact_meshes(ctx: _Ctx, model: OsimModel, comps: list[tuple[ET.Element, str]]) -> None:
    """Add every Smith2018ContactMesh to ``model`` (location in m, orientation in rad, thickness
    in m, elastic modulus in Pa)."""
    for el, p in comps:
        if el.tag != "Smith2018ContactMesh":
            continue
        nm = el.get("name")
        where = f"Smith2018ContactMesh '{nm}'"
        fr = _resolve(p, ctx.text(el, "socket_frame", where))
        try:
            body, _ = model.frame_in_body(fr)
        except OsimError:
            raise ctx.err(f"{where}: frame '{fr}' not found") from None
        loc = ctx.floats(el, "location", where, 3, required=False)
        ori = ctx.floats(el, "orientation", where, 3, required=False)
        model.contact_meshes[nm] = ContactMesh(
            nm, ctx.text(el, "mesh_file", where), ctx.text(el, "mesh_back_file", where, required=False),
            fr, body, np.zeros(3) if loc is None else loc, np.zeros(3) if ori is None else ori,
            ctx.float1(el, "thickness", where), ctx.float1(el, "elastic_modulus", where),
            ctx.float1(el, "poissons_ratio", where),
            ctx.boolean(el, "use_variable_thickness", where, False))
