"""Figures (matplotlib Figure objects, no pyplot): laxity curves and ligament forces per load case.

Every axis states its unit (mm, deg, N, N m).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib as mpl
import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from kneenlp.base.conventions import BAND_Z
from kneenlp.experiment.protocol import LAXITY_PAIRS

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
    fig, axes = _subplots(1, 3, figsize=(13, 4))
    flexions = sorted(table["flexion_deg"].unique())
    colors = mpl.rcParams["axes.prop_cycle"].by_key()["color"]
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
    legend(axes[0], fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def ligament_forces(table: pd.DataFrame, ligaments: list[str], path: str | Path, title: str = "",
                    recruitment: pd.DataFrame | None = None) -> Path:
    """Grouped bars of each ligament's force (N) per load case (the paper's Fig. 2); with
    ``recruitment`` (:meth:`SimulationResult.recruitment`) a second panel shows each force's change
    from the unloaded pose (N) and names the ligament that dominates each case."""
    n = len(table)
    rows = 1 if recruitment is None else 2
    fig, axes = _subplots(rows, 1, figsize=(max(8, 0.45 * n), 4.5 * rows), sharex=True, squeeze=False)
    width = 0.8 / len(ligaments)
    x = np.arange(n)
    panels = [(axes[0, 0], table, "force", "ligament force [N]")]
    if recruitment is not None:
        panels.append((axes[1, 0], recruitment, "force_change", "force change from unloaded pose [N]"))
    for ax, frame, key, label in panels:
        for j, lig in enumerate(ligaments):
            ax.bar(x + (j - (len(ligaments) - 1) / 2) * width, frame[f"{lig}_{key}_N"], width, label=lig,
                   color=f"C{j}")
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    legend(axes[0, 0])
    if recruitment is not None:
        ax = axes[1, 0]
        ax.axhline(0.0, color="k", lw=0.6)
        top = ax.get_ylim()[1]
        for i, lig in enumerate(recruitment["dominant"]):
            if lig:
                ax.text(i, top, lig, ha="center", va="top", fontsize=7, rotation=90,
                        color=f"C{ligaments.index(lig)}")
    axes[-1, 0].set_xticks(x)
    axes[-1, 0].set_xticklabels(table["trial"], rotation=70, ha="right", fontsize=8)
    if title:
        axes[0, 0].set_title(title)
    return _save(fig, path)


def study_boxplots(estimates: pd.DataFrame, table: pd.DataFrame, sets, path: str | Path, title: str = "") -> Path:
    """The paper's Fig. 3: estimates per set as boxplots, true values marked, linearised +-2 sigma.

    One column per ligament, one row per parameter of the Table 3 analogue (e.g. stiffness k in kN
    per unit strain and reference strain in %, or a group's stiffness scale and reference-strain
    offset), in the units of ``table`` (its ``unit`` column), as the ``estimates`` columns are.
    """
    ligs = list(dict.fromkeys(table["ligament"])) if len(table) else []
    kinds = list(dict.fromkeys(table["parameter"])) if len(table) else []
    rows_n = max(len(kinds), 1)
    fig, axes = _subplots(rows_n, max(len(ligs), 1), figsize=(3.2 * max(len(ligs), 1), 3.25 * rows_n),
                          squeeze=False)
    for j, lig in enumerate(ligs):
        for i, kind in enumerate(kinds):
            ax = axes[i, j]
            rows = table[(table["ligament"] == lig) & (table["parameter"] == kind)]
            if rows.empty:
                ax.set_visible(False)
                continue
            unit = rows["unit"].iloc[0]
            true = rows["true"].iloc[0]
            col = f"{lig}.{kind}"
            data = [estimates.loc[estimates["set"] == s, col].to_numpy(dtype=float)
                    if col in estimates else np.array([]) for s in sets]
            pos = np.arange(1, len(sets) + 1)
            ax.boxplot(data, positions=pos, widths=0.5, flierprops={"marker": "x"})
            ax.axhline(true, color="0.5", ls="--", lw=1, label="true")
            pred = [rows.loc[rows["set"] == s, "predicted_std"].iloc[0] if (rows["set"] == s).any() else np.nan
                    for s in sets]
            ax.errorbar(pos + 0.33, [true] * len(sets), yerr=2 * np.asarray(pred), fmt="o", ms=3, color="C3",
                        capsize=3, label="linearised +-2 sd")
            ax.set_xticks(pos)
            ax.set_xticklabels([Path(s).stem if str(s).endswith(".toml") else str(s) for s in sets], rotation=30)
            ax.set_title(f"{lig} {kind.replace('_', ' ')}", fontsize=9)
            ax.set_ylabel(f"{kind.replace('_', ' ')} [{unit}]")
            ax.grid(alpha=0.3)
    if ligs:
        legend(axes[0, 0], fontsize=7)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def residual_map(rmap: pd.DataFrame, path: str | Path, title: str = "") -> Path:
    """Heat map of residuals (trials x coordinates) in units of the noise standard deviation."""
    fig, ax = _subplots(figsize=(6.5, max(3.0, 0.22 * len(rmap) + 1.5)))
    lim = max(3.0, float(np.nanmax(np.abs(rmap.to_numpy()))))
    im = ax.imshow(rmap.to_numpy(), cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
    ax.set_yticks(range(len(rmap)))
    ax.set_yticklabels(rmap.index, fontsize=7)
    units = {"rotation": "deg", "translation": "mm"}
    ax.set_xticks(range(len(rmap.columns)))
    ax.set_xticklabels([f"{c.replace('_', ' ')} [{units[c.split('_')[-1]]}]" for c in rmap.columns], rotation=30,
                       ha="right", fontsize=8)
    fig.colorbar(im, ax=ax, label="(model - measured) / noise sd")
    if title:
        ax.set_title(title, fontsize=9)
    return _save(fig, path)


#: Panels of measured against predicted laxity: the direction pair and the coordinate it moves.
PAIR_PANELS = tuple((pair, col, f"{col.rsplit('_', 1)[0].replace('_', ' ')} [{col.rsplit('_', 1)[1]}]")
                    for col, pair in LAXITY_PAIRS.items())


def measured_vs_predicted(table: pd.DataFrame, path: str | Path, title: str = "",
                          extra: dict[str, pd.DataFrame] | None = None) -> Path:
    """Measured (filled) against predicted (open, joined) laxity per load direction and flexion: the
    coordinate each direction pair moves against the measured flexion (deg).  ``table`` has the
    load columns, the predicted coordinates and ``measured_<coordinate>`` (as
    :meth:`kneenlp.prediction.predict.Prediction.table` writes it); ``extra`` adds further
    predictions (label -> such a table), dashed.  With predictive sds (``sd_<coordinate>``, a
    calibration's posterior) the 95 % predictive band is shaded."""
    from kneenlp.experiment.protocol import dominant_direction

    load_cols = [c for c in table.columns if c.endswith(("_force_N", "_moment_Nm"))]
    words = [dominant_direction({c.rsplit("_", 1)[0]: float(r[c]) for c in load_cols}) for _, r in table.iterrows()]
    fig, axes = _subplots(1, 3, figsize=(14, 4.2))
    colors = mpl.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (pair, col, ylabel) in zip(axes, PAIR_PANELS, strict=True):
        for k, word in enumerate((*pair, "none")):
            sel = np.array([w == word for w in words])
            if not sel.any():
                continue
            sub = table[sel].sort_values("flexion_deg")
            c = colors[k % len(colors)]
            ax.plot(sub["flexion_deg"], sub[f"measured_{col}"], "o", color=c, label=f"{word} measured")
            ax.plot(sub["flexion_deg"], sub[col], "o--" if word == "none" else "o-", mfc="none", color=c,
                    label=f"{word} predicted")
            if f"sd_{col}" in sub:  # the 95 % predictive band (posterior and noise)
                ax.fill_between(sub["flexion_deg"], sub[col] - BAND_Z * sub[f"sd_{col}"],
                                sub[col] + BAND_Z * sub[f"sd_{col}"], color=c, alpha=0.15, lw=0)
            for label, other in (extra or {}).items():
                o = other[sel].sort_values("flexion_deg")
                ax.plot(o["flexion_deg"], o[col], "s:", mfc="none", color=c, alpha=0.7, label=f"{word} {label}")
        ax.set_xlabel("flexion [deg]")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        legend(ax, fontsize=7)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def legend(ax, **kwargs) -> None:
    """``ax.legend`` where the axes have labelled artists (matplotlib warns on an empty legend)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kwargs)


def _subplots(*args, **kwargs):
    """A figure and its axes without pyplot: no global figure registry and no backend switch, so
    importing or calling kneenlp never changes the user's matplotlib backend."""
    figsize = kwargs.pop("figsize", None)
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*args, **kwargs)


def _save(fig, path: str | Path) -> Path:
    """Save through a temporary file: a figure file is either whole or absent (kneenlp.base.atomic)."""
    from kneenlp.base.atomic import save_figure_atomic

    fig.tight_layout()
    return save_figure_atomic(fig, path, dpi=110)


def waterfall(objectives: np.ndarray, best_hits: int, path: str | Path, title: str = "") -> Path:
    """The global search's waterfall (as pyPESTO draws it): the MAP objective of every converged
    solve, sorted, against its rank; the lowest minimum's solves marked."""
    fig, ax = _subplots(figsize=(6, 4))
    values = np.sort(np.asarray(objectives, float))
    ranks = np.arange(1, len(values) + 1)
    ax.plot(ranks, values, "o-", color="0.4", markersize=4)
    ax.plot(ranks[:best_hits], values[:best_hits], "o", color="C3", label=f"lowest minimum ({best_hits} solves)")
    ax.set_xlabel("solve, sorted by its end")
    ax.set_ylabel("MAP objective [mm^2 + deg^2, weighted]")
    ax.set_title(title or "global search: every solve's end")
    legend(ax)
    return _save(fig, path)
