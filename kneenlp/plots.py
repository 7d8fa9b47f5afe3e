"""Figures (matplotlib, Agg backend): laxity curves and ligament forces per load case.

Every axis states its unit (mm, deg, N, N m).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

PANELS = (
    ("anterior_force_N", "anterior_translation_mm", "anterior (+) / posterior (-) force [N]",
     "anterior translation [mm]"),
    ("varus_moment_Nm", "varus_rotation_deg", "varus (+) / valgus (-) moment [N m]", "varus rotation [deg]"),
    ("internal_moment_Nm", "internal_rotation_deg", "internal (+) / external (-) moment [N m]",
     "internal rotation [deg]"),
)


def laxity_curves(table: pd.DataFrame, path: str | Path, title: str = "",
                  measured: pd.DataFrame | None = None, band: float | None = None) -> Path:
    """Load-displacement curves per load direction and flexion angle.

    Each curve shows the primary coordinate at every load level of one direction pair (e.g.
    anterior and posterior), including the unloaded trial at that flexion.  ``measured`` adds data
    points and ``band`` (mm/deg) a +-band around the model curve.
    """
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    flexions = sorted(table["flexion_deg"].unique())
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    load_cols = [p[0] for p in PANELS]
    for ax, (lcol, ccol, xlabel, ylabel) in zip(axes, PANELS, strict=True):
        for i, flex in enumerate(flexions):
            others = [c for c in load_cols if c != lcol]
            sel = (table["flexion_deg"] == flex) & (table[others].abs().sum(axis=1) == 0)
            sub = table[sel].sort_values(lcol)
            if len(sub) < 2:
                continue
            c = colors[i % len(colors)]
            ax.plot(sub[lcol], sub[ccol], "o-", color=c, label=f"model, {flex:g} deg flexion")
            if band:
                ax.fill_between(sub[lcol], sub[ccol] - band, sub[ccol] + band, color=c, alpha=0.15)
            if measured is not None:
                msel = (measured["flexion_deg"] == flex) & (measured[others].abs().sum(axis=1) == 0)
                m = measured[msel].sort_values(lcol)
                ax.plot(m[lcol], m[ccol], "x", color=c, label=f"measured, {flex:g} deg")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.axhline(0, color="k", lw=0.5)
        ax.axvline(0, color="k", lw=0.5)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def ligament_forces(table: pd.DataFrame, ligaments: list[str], path: str | Path, title: str = "") -> Path:
    """Grouped bars of each ligament's force (N) per load case (the paper's Fig. 2)."""
    n = len(table)
    fig, ax = plt.subplots(figsize=(max(8, 0.45 * n), 4.5))
    width = 0.8 / len(ligaments)
    x = np.arange(n)
    for j, lig in enumerate(ligaments):
        ax.bar(x + (j - (len(ligaments) - 1) / 2) * width, table[f"{lig}_force_N"], width, label=lig)
    ax.set_xticks(x)
    ax.set_xticklabels(table["trial"], rotation=70, ha="right", fontsize=8)
    ax.set_ylabel("ligament force [N]")
    ax.legend()
    ax.grid(axis="y", alpha=0.3)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
