"""2-D maps: the contact pressure of each compartment on the tibial cartilage (top view, tibial
frame, mm; MPa) and its centre of pressure, one panel per trial."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from kneenlp.base.atomic import save_figure_atomic
from kneenlp.base.errors import InputError
from kneenlp.experiment.protocol import Trial
from kneenlp.io.views.scene import MM, MPA, ContactMap, contact_maps, solution
from kneenlp.simulation import SimulationResult
from kneenlp.solvers.forward import TrialSolution

PRESSURE_CMAP = "viridis"
#: Marker of a centre of pressure (matplotlib ``plot`` keywords).
COP_STYLE = {"marker": "X", "ms": 10, "color": "w", "mec": "k", "mew": 1.2, "ls": "none"}

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
    return save_figure(fig, path)


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


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write a figure (its layout is constrained, so no tight_layout)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure_atomic(fig, path, dpi=110)
    return path
