"""Pictures of a simulated knee that need no OpenSim: contact pressure maps and a 3-D view.

* :func:`pressure_map`: top view of the tibial cartilage (tibial frame, X anterior up, Z lateral to
  the right) with the contact pressure of each compartment (MPa) and its centre of pressure, one
  panel per trial;
* :func:`knee_view`: the knee at a trial's pose in the femoral frame: femoral articular surface (or
  explicit condyle spheres), tibial cartilage coloured by pressure (MPa) and ligament lines
  coloured by force (N); a static PNG (matplotlib 3-D) and an interactive, self-contained HTML
  file (plotly, the optional extra ``kneenlp[view]``).

Everything is computed in SI from the simulation result (poses from ``model.pose``, pressures from
each contact element's ``pressure``) and drawn in mm, MPa and N.  Figures are matplotlib
:class:`~matplotlib.figure.Figure` objects, never pyplot, so no backend is switched.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib as mpl
import numpy as np
import trimesh
from matplotlib.cm import ScalarMappable
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from kneenlp.errors import InputError, unknown_name
from kneenlp.experiment.protocol import Protocol, Trial
from kneenlp.io.atomic import save_figure_atomic
from kneenlp.model.articular import Compartment
from kneenlp.model.knee import Knee
from kneenlp.model.kneemodel import KneeModel
from kneenlp.simulation import SimulationResult
from kneenlp.solvers.forward import TrialSolution

MM, MPA = 1e3, 1e-6  # SI -> display units
PRESSURE_CMAP = "viridis"
#: Marker of a centre of pressure (matplotlib ``plot`` keywords).
COP_STYLE = {"marker": "X", "ms": 10, "color": "w", "mec": "k", "mew": 1.2, "ls": "none"}
FORCE_CMAP = "Reds"
#: Face budgets of the static 3-D picture (meshes above them are decimated by vertex clustering).
FEMUR_FACES, TIBIA_FACES = 3000, 2500
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
    one-line :class:`~kneenlp.errors.InputError`."""
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


# ---------------------------------------------------------------------------------------- pressure map
def pressure_map(result: SimulationResult, trials: Iterable[str | Trial | TrialSolution], path: str | Path) -> Path:
    """Contact pressure maps (MPa) on the tibial plateau, one panel per trial, written to ``path``.

    Top view of the tibial cartilage in the tibial frame (mm; X anterior up, Z lateral to the
    right, i.e. looking down on the right tibia from proximal), per-vertex pressure shaded on each
    compartment's cartilage mesh with a colour scale shared by all panels, the centre of pressure
    of each compartment marked and the contact forces (N) in each panel's title."""
    sols = [solution(result, t) for t in trials]
    if not sols:
        raise InputError("no trial to draw", field="trials")
    maps = [contact_maps(result, s) for s in sols]
    vmax = max([m.pressure.max() * MPA for mm in maps for m in mm.values()] + [1e-3])
    norm = Normalize(0.0, vmax)
    ncols = min(len(sols), 3)
    nrows = -(-len(sols) // ncols)
    fig = Figure(figsize=(4.3 * ncols + 1.2, 4.6 * nrows), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    for ax, sol, mm in zip(axes, sols, maps, strict=False):
        _pressure_panel(ax, sol, mm, norm)
    for ax in axes[len(sols):]:
        ax.set_visible(False)
    mappable = ScalarMappable(norm=norm, cmap=PRESSURE_CMAP)
    fig.colorbar(mappable, ax=list(axes[: len(sols)]), label="pressure (MPa)", shrink=0.85)
    fig.legend(handles=[Line2D([], [], **COP_STYLE, label="centre of pressure")], loc="outside lower center",
               fontsize=8, frameon=False)
    fig.suptitle(f"{result.knee.name} knee, {result.protocol.title or result.protocol.name}\ncontact pressure on the "
                 "tibial cartilage (top view, tibial frame; mm, MPa)", fontsize=10)
    return _save(fig, path)


def _pressure_panel(ax, sol: TrialSolution, maps: dict[str, ContactMap], norm: Normalize) -> None:
    """One trial's pressure map: top view (Z lateral [mm] horizontal, X anterior [mm] up)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for m in maps.values():
        v = np.asarray(m.mesh.vertices) * MM
        lo, hi = np.minimum(lo, v.min(axis=0)), np.maximum(hi, v.max(axis=0))
        ax.tripcolor(v[:, 2], v[:, 0], np.asarray(m.mesh.faces), m.pressure * MPA, shading="gouraud",
                     cmap=PRESSURE_CMAP, norm=norm, rasterized=True)
        if np.all(np.isfinite(m.cop)):
            ax.plot(m.cop[2] * MM, m.cop[0] * MM, **COP_STYLE)
        ax.text(0.5 * (v[:, 2].min() + v[:, 2].max()), v[:, 0].min() - 1.0, m.name, ha="center", va="top",
                fontsize=8)
    forces = ", ".join(f"{m.name} {m.load:.0f} N" for m in maps.values())
    flag = "" if sol.converged else " (NOT CONVERGED)"
    ax.set_title(f"{sol.trial.id}{flag}\ncontact force: {forces}", fontsize=9)
    ax.set_xlabel("Z, lateral (+) [mm]")
    ax.set_ylabel("X, anterior (+) [mm]")
    ax.set_aspect("equal")
    if np.all(np.isfinite(lo)):
        ax.set_xlim(lo[2] - 3.0, hi[2] + 3.0)
        ax.set_ylim(lo[0] - 6.0, hi[0] + 3.0)
    ax.grid(alpha=0.25)


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


def knee_view(result: SimulationResult, trial: str | Trial | TrialSolution, path_png: str | Path | None,
              path_html: str | Path | None) -> list[Path]:
    """3-D view of the knee at a trial's pose: femoral surface, tibial cartilage coloured by contact
    pressure (MPa), ligament bundles coloured by force (N), all in the femoral frame in mm.

    Writes a static PNG (matplotlib 3-D, meshes decimated to a few thousand faces) to ``path_png``
    and an interactive self-contained HTML file (plotly, opens offline) to ``path_html``; either may
    be None.  The HTML needs plotly (``pip install 'kneenlp[view]'``); without it an
    :class:`~kneenlp.errors.InputError` says so.  Returns the written paths."""
    if path_html is not None:
        require_plotly()
    scene = build_scene(result, trial)
    written = []
    if path_png is not None:
        written.append(_view_png(scene, Path(path_png)))
    if path_html is not None:
        written.append(_view_html(scene, Path(path_html)))
    return written


def require_plotly():
    """The plotly.graph_objects module, or the one-line error naming the optional extra."""
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise InputError("the interactive view needs plotly: pip install 'kneenlp[view]'", field="--view") from None
    return go


def _pressure_range(scene: Scene) -> float:
    """Upper end of the pressure colour scale (MPa)."""
    return max([m.pressure.max() * MPA for m in scene.contact.values()] + [1e-3])


def _force_range(scene: Scene) -> float:
    """Upper end of the ligament-force colour scale (N)."""
    return max([line.force for line in scene.ligaments] + [1.0])


def _plot_axes(points_mm: np.ndarray) -> np.ndarray:
    """Femoral (X anterior, Y proximal, Z lateral) -> matplotlib 3-D axes (Z, X, Y): proximal up; a
    cyclic permutation, so still right-handed."""
    return np.asarray(points_mm)[..., [2, 0, 1]]


def _shade(vertices: np.ndarray, faces: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Per-face colours (N x 3) dimmed by a fixed light (from anterior, proximal, lateral)."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-30
    light = np.array([0.5, 0.7, 0.5]) / np.linalg.norm([0.5, 0.7, 0.5])
    return np.clip((0.45 + 0.55 * np.abs(n @ light))[:, None] * rgb, 0, 1)


def _view_png(scene: Scene, path: Path) -> Path:
    """The static 3-D picture: an anterolateral and a medial view side by side (mm)."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    pnorm = Normalize(0.0, _pressure_range(scene))
    fnorm = Normalize(0.0, _force_range(scene))
    pcmap, fcmap = mpl.colormaps[PRESSURE_CMAP], mpl.colormaps[FORCE_CMAP]
    polys, colors = [], []
    bone = [scene.femur] if scene.femur is not None else []
    for mesh in bone + list(scene.caps.values()):
        v, f, _ = decimate(mesh.vertices * MM, mesh.faces, FEMUR_FACES)
        polys.append(_plot_axes(v)[f])
        rgba = np.ones((len(f), 4))
        rgba[:, :3] = _shade(v, f, np.array([0.85, 0.82, 0.76]))
        rgba[:, 3] = 0.35
        colors.append(rgba)
    for name, mesh in scene.tibiae.items():
        values = scene.contact[name].pressure * MPA if name in scene.contact else np.zeros(len(mesh.vertices))
        v, f, val = decimate(mesh.vertices * MM, mesh.faces, TIBIA_FACES, values)
        polys.append(_plot_axes(v)[f])
        colors.append(pcmap(pnorm(val[f].mean(axis=1))))  # unshaded: the colour is the data
    polys_all, colors_all = np.concatenate(polys), np.concatenate(colors)
    segs = np.array([_plot_axes(np.stack([line.femur, line.tibia]) * MM) for line in scene.ligaments])
    everything = np.concatenate([polys_all.reshape(-1, 3)] + ([segs.reshape(-1, 3)] if len(segs) else []))
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    fig = Figure(figsize=(12, 6.2), layout="constrained")
    views = (("anterolateral view", 20, 60), ("medial view", 10, 190))
    axes = []
    for k, (label, elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        axes.append(ax)
        ax.computed_zorder = False  # ligaments on top: they are seen through the surfaces
        ax.add_collection3d(Poly3DCollection(list(polys_all), facecolors=colors_all, edgecolors=colors_all,
                                             linewidths=0.15, zorder=1))  # edges hide the seams
        if len(segs):
            lc = Line3DCollection(list(segs), colors=fcmap(0.25 + 0.75 * fnorm([ln.force for ln in scene.ligaments])),
                                  linewidths=4, zorder=3)
            ax.add_collection3d(lc)
            for line, seg in zip(scene.ligaments, segs, strict=True):  # labels at the tibial ends: apart
                ax.text(*seg[1], f" {line.ligament} {line.force:.0f} N", fontsize=8, zorder=4)
            ends = segs.reshape(-1, 3)
            ax.scatter(*ends.T, s=12, color="k", depthshade=False, zorder=4)
        for name, cop in scene.cops.items():
            c = _plot_axes(cop * MM)
            ax.scatter(*c, marker="X", s=60, color="w", edgecolors="k", depthshade=False, zorder=5,
                       label="centre of pressure" if name == next(iter(scene.cops)) else None)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(hi - lo, zoom=0.88)  # equal scale on every axis, room for the labels
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("Z lateral [mm]")
        ax.set_ylabel("X anterior [mm]")
        ax.set_zlabel("Y proximal [mm]")
        ax.set_title(label, fontsize=10)
        ax.tick_params(labelsize=7)
        if scene.cops and k == 0:
            ax.legend(loc="upper left", fontsize=8)
    fig.colorbar(ScalarMappable(norm=pnorm, cmap=PRESSURE_CMAP), ax=axes, label="pressure (MPa)",
                 shrink=0.6, location="right")
    fmap = ScalarMappable(norm=fnorm, cmap=ListedColormap(fcmap(np.linspace(0.25, 1, 256))))
    fig.colorbar(fmap, ax=axes, label="ligament force (N)", shrink=0.6, location="right")
    fig.suptitle(f"{scene.title}\nfemoral frame, mm; {scene.femur_note}; tibial cartilage coloured by contact "
                 "pressure", fontsize=10)
    return _save(fig, path)


def _mesh3d(go, mesh: trimesh.Trimesh, name: str, **kwargs):
    """A plotly Mesh3d of a mesh in the femoral frame, drawn in mm."""
    v = np.round(np.asarray(mesh.vertices) * MM, 3)
    f = np.asarray(mesh.faces)
    return go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2], name=name,
                     showlegend=True, **kwargs)


def _view_html(scene: Scene, path: Path) -> Path:
    """The interactive 3-D view (plotly, self-contained: plotly.js is embedded, opens offline)."""
    go = require_plotly()
    from plotly.colors import sample_colorscale

    traces = []
    surfaces = ([(scene.femur, scene.femur_note.split(";")[0])] if scene.femur is not None else [])
    surfaces += [(cap, f"{name} condyle sphere") for name, cap in scene.caps.items()]
    for mesh, label in surfaces:
        traces.append(_mesh3d(go, mesh, label, color="rgb(222,210,190)", opacity=0.45, flatshading=False,
                              hoverinfo="name"))
    pmax = _pressure_range(scene)
    for k, (name, mesh) in enumerate(scene.tibiae.items()):
        values = scene.contact[name].pressure * MPA if name in scene.contact else np.zeros(len(mesh.vertices))
        load = f", {scene.contact[name].load:.0f} N" if name in scene.contact else ""
        traces.append(_mesh3d(go, mesh, f"{name} tibial cartilage{load}", intensity=values, intensitymode="vertex",
                              colorscale=PRESSURE_CMAP.capitalize(), cmin=0.0, cmax=pmax, showscale=k == 0,
                              colorbar={"title": {"text": "pressure (MPa)"}, "x": 1.0, "len": 0.7},
                              hovertemplate="%{intensity:.2f} MPa<extra>" + name + "</extra>"))
    fmax = _force_range(scene)
    for line in scene.ligaments:
        seg = np.stack([line.femur, line.tibia]) * MM
        color = sample_colorscale("Reds", [0.25 + 0.75 * min(line.force / fmax, 1.0)])[0]
        traces.append(go.Scatter3d(x=seg[:, 0], y=seg[:, 1], z=seg[:, 2], mode="lines+markers",
                                   line={"color": color, "width": 9}, marker={"size": 3, "color": "black"},
                                   name=f"{line.ligament} {line.force:.0f} N", hoverinfo="name"))
    if scene.ligaments:
        ends = np.array([line.femur for line in scene.ligaments]) * MM
        forces = [line.force for line in scene.ligaments]
        scale = [[t, c] for t, c in zip(np.linspace(0, 1, 5), sample_colorscale("Reds", list(np.linspace(0.25, 1, 5))),
                                        strict=True)]
        traces.append(go.Scatter3d(x=ends[:, 0], y=ends[:, 1], z=ends[:, 2], mode="markers", showlegend=False,
                                   hoverinfo="skip", marker={"size": 0.1, "color": forces, "cmin": 0, "cmax": fmax,
                                                             "colorscale": scale, "showscale": True,
                                                             "colorbar": {"title": {"text": "ligament force (N)"},
                                                                          "x": 1.12, "len": 0.7}}))
    if scene.cops:
        c = np.array(list(scene.cops.values())) * MM
        traces.append(go.Scatter3d(x=c[:, 0], y=c[:, 1], z=c[:, 2], mode="markers", name="centre of pressure",
                                   marker={"symbol": "x", "size": 5, "color": "white",
                                           "line": {"color": "black", "width": 2}}))
    fig = go.Figure(traces)
    fig.update_layout(
        title={"text": f"{scene.title}<br><sub>femoral frame, mm; {scene.femur_note}</sub>"},
        scene={"xaxis": {"title": {"text": "X anterior (mm)"}}, "yaxis": {"title": {"text": "Y proximal (mm)"}},
               "zaxis": {"title": {"text": "Z lateral (mm)"}}, "aspectmode": "data",
               "camera": {"up": {"x": 0, "y": 1, "z": 0}, "eye": {"x": 1.4, "y": 0.5, "z": 1.2}}},
        legend={"x": 0.0, "y": 1.0}, margin={"l": 0, "r": 0, "t": 60, "b": 0})
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.write_html(str(path), include_plotlyjs=True, full_html=True)
    return path


def _save(fig: Figure, path: str | Path) -> Path:
    """Write a figure (its layout is constrained, so no tight_layout)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure_atomic(fig, path, dpi=110)
    return path


def write_views(result: SimulationResult, trials: Sequence[str], out: str | Path,
                html: bool = True) -> list[Path]:
    """For each trial: ``pressure_<trial>.png``, ``view_<trial>.png`` and (with ``html``)
    ``view_<trial>.html`` in ``out``.  Returns the written paths."""
    out = Path(out)
    written = []
    for tid in trials:
        written.append(pressure_map(result, [tid], out / f"pressure_{tid}.png"))
        written += knee_view(result, tid, out / f"view_{tid}.png", out / f"view_{tid}.html" if html else None)
    return written
