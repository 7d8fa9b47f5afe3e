"""3-D rendering of the knee at a trial's pose (femoral frame, mm): a static PNG (matplotlib 3-D)
and an interactive self-contained HTML file (plotly); and all views of some trials."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib as mpl
import numpy as np
import trimesh
from matplotlib.cm import ScalarMappable
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.figure import Figure

from kneenlp.base.atomic import atomic_target
from kneenlp.base.errors import InputError
from kneenlp.experiment.protocol import Trial
from kneenlp.figures.plots import legend
from kneenlp.io.views.maps import PRESSURE_CMAP, pressure_map, save_figure
from kneenlp.io.views.scene import MM, MPA, Scene, build_scene, decimate
from kneenlp.simulation import SimulationResult
from kneenlp.solvers.forward import TrialSolution

FORCE_CMAP = "Reds"
#: Face budgets of the static 3-D picture (meshes above them are decimated by vertex clustering).
FEMUR_FACES, TIBIA_FACES = 3000, 2500

def knee_view(result: SimulationResult, trial: str | Trial | TrialSolution, path_png: str | Path | None,
              path_html: str | Path | None) -> list[Path]:
    """3-D view of the knee at a trial's pose: femoral surface, tibial cartilage coloured by contact
    pressure (MPa), ligament bundles coloured by force (N), all in the femoral frame in mm.

    Writes a static PNG (matplotlib 3-D, meshes decimated to a few thousand faces) to ``path_png``
    and an interactive self-contained HTML file (plotly, opens offline) to ``path_html``; either may
    be None.  The HTML needs plotly (``pip install 'kneenlp[view]'``); without it an
    :class:`~kneenlp.base.errors.InputError` says so.  Returns the written paths."""
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
            legend(ax, loc="upper left", fontsize=8)
    fig.colorbar(ScalarMappable(norm=pnorm, cmap=PRESSURE_CMAP), ax=axes, label="pressure (MPa)",
                 shrink=0.6, location="right")
    fmap = ScalarMappable(norm=fnorm, cmap=ListedColormap(fcmap(np.linspace(0.25, 1, 256))))
    fig.colorbar(fmap, ax=axes, label="ligament force (N)", shrink=0.6, location="right")
    fig.suptitle(f"{scene.title}\nfemoral frame, mm; {scene.femur_note}; tibial cartilage coloured by contact "
                 "pressure", fontsize=10)
    return save_figure(fig, path)


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
    with atomic_target(path) as tmp:
        fig.write_html(str(tmp), include_plotlyjs=True, full_html=True)
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
