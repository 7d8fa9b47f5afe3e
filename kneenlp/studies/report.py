"""Analysis of a noise study: estimates tables, Table 3 analogue, Fig. 3, Fig. 2, summary.

Units in every table and figure: stiffness k in kN (per unit strain), reference strain in %.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.base.atomic import atomic_target, write_csv_atomic, write_text_atomic
from kneenlp.base.resources import resource
from kneenlp.experiment.noise import NoiseModel
from kneenlp.model.parameters import KINDS
from kneenlp.studies.truth import StudyTruths

# Table 3 units by parameter kind: (unit, factor from SI): the paper's kN for stiffnesses, the
# display units of KINDS for the rest (reference strains and their group offsets in %; group
# stiffness scales dimensionless).
_USER_UNITS = {"k": ("kN", 1e-3), "ref_strain": (KINDS["ref_strain"].unit, KINDS["ref_strain"].to_user),
               "scale": ("-", KINDS["scale"].to_user)}


def _write_csv(df: pd.DataFrame, path: Path) -> None:
    write_csv_atomic(df, path, index=False, float_format="%.10g")


def _write_parquet(df: pd.DataFrame, path: Path) -> bool:
    try:
        with atomic_target(path) as tmp:
            df.to_parquet(tmp, index=False)
        return True
    except ImportError:
        return False


def predicted_std(study, set_name: str, truths: StudyTruths) -> dict[str, float]:
    """Linearised (Gauss-Newton) standard deviation of each free parameter at the true values (SI)."""
    from kneenlp.estimation.statistics import gauss_newton_covariance
    from kneenlp.experiment.problem import IdentificationProblem, free_names

    spec = study.spec
    model, truth = truths.model, truths.truth(set_name)
    free = free_names(model, spec.free, spec.with_effects)
    problem = IdentificationProblem(model, [s.trial for s in truth.solutions], free)
    theta = problem.theta()
    cov = gauss_newton_covariance(problem.sensitivities(truth.q, theta), problem.weights,
                                  NoiseModel.parse(spec.noise).std ** 2, problem.scales, free)
    return {n: float(np.sqrt(cov[i, i])) for i, n in enumerate(free)}


def analyse_study(study, truths: StudyTruths | None = None) -> dict:
    """Write estimates.csv/.parquet, table3.csv, failures.csv, fig3_boxplots.png,
    fig2_set3_forces.png and summary.md into the study directory; return the Table 3 frame.
    ``truths``: the study's model and true simulations (built here when not given)."""
    from kneenlp.figures import plots

    out = study.out
    df = study.load_rows()
    _write_csv(df, out / "estimates.csv")
    parquet = _write_parquet(df, out / "estimates.parquet")
    truths = truths or StudyTruths.of(study.spec)
    model = truths.model
    knee = model.knee
    truth_vals = dict(zip(model.parameter_names, model.theta(), strict=True))
    ok = df[df["success"].astype(bool)] if not df.empty else df
    failures = df[~df["success"].astype(bool)] if not df.empty else df
    _write_csv(failures, out / "failures.csv")
    params = [c for c in df.columns
              if c in model.parameter_names and model.parameter(c).kind in _USER_UNITS]
    rows = []
    for set_name in study.spec.sets:
        sub = ok[ok["set"] == set_name]
        pred = predicted_std(study, set_name, truths)
        for p in params:
            lig, kind = p.rsplit(".", 1)
            unit, f = _USER_UNITS[model.parameter(p).kind]
            vals = sub[p].to_numpy(dtype=float) * f
            rows.append({
                "set": set_name, "ligament": lig, "parameter": kind, "unit": unit,
                "true": truth_vals[p] * f,
                "min": np.min(vals) if vals.size else np.nan,
                "max": np.max(vals) if vals.size else np.nan,
                "range": np.ptp(vals) if vals.size else np.nan,
                "mc_std": np.std(vals, ddof=1) if vals.size > 1 else np.nan,
                "predicted_std": pred.get(p, np.nan) * f,
                "n": int(vals.size),
            })
    table = pd.DataFrame(rows)
    if not table.empty:
        table["std_ratio"] = table["mc_std"] / table["predicted_std"]
    _write_csv(table, out / "table3.csv")
    shown = ok.assign(**{p: ok[p].to_numpy(dtype=float) * _USER_UNITS[model.parameter(p).kind][1]
                         for p in params if p in ok})  # in the units of the table
    plots.study_boxplots(shown, table, study.spec.sets, out / "fig3_boxplots.png",
                         f"{len(ok)} fits, noise {study.spec.noise}")
    fig2_set = "set3" if "set3" in study.spec.sets else study.spec.sets[0]
    truth = truths.truth(fig2_set)
    plots.ligament_forces(truth.table(), list(knee.ligaments), out / f"fig2_{truth.protocol.name}_forces.png",
                          f"Ligament forces, {fig2_set} (true parameters)",
                          truth.recruitment() if any(t.direction == "none" for t in truth.protocol.trials) else None)
    write_text_atomic(out / "summary.md", _summary(study, df, table, failures, parquet))
    return table


def _paper_table() -> pd.DataFrame:
    return pd.read_csv(resource("paper", "table3_stiffness.csv"), comment="#")


def _summary(study, df, table, failures, parquet) -> str:
    spec = study.spec
    lines = [f"# Noise study: {', '.join(spec.sets)}", "",
             f"- samples per set: {spec.samples}; noise: {spec.noise} (mm and deg); seed: {spec.seed}; "
             f"method: {spec.method}",
             f"- fits: {len(df)}; succeeded: {len(df) - len(failures)}; failed: {len(failures)}",
             f"- outputs: estimates.csv{', estimates.parquet' if parquet else ''}, table3.csv, fig3_boxplots.png, "
             "fig2 forces, failures.csv", ""]
    if len(failures):
        lines += ["## Failed identifications (counted, not dropped)", ""]
        lines += [f"- {r['set']} sample {r['sample']} (seed {r['seed']}): {r['status']}"
                  for _, r in failures.iterrows()]
        lines.append("")
    lines += ["## Table 3 analogue (k in kN per unit strain, reference strain in %, scales dimensionless)", "",
              "| set | parameter | true | min | max | range | MC std | linearised std | MC / linearised "
              "| paper min | paper max |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    paper = _paper_table()
    for _, r in table.iterrows():
        pm = paper[(paper["set"] == r["set"]) & (paper["ligament"] == r["ligament"])]
        pmin = f"{pm['min_kN'].iloc[0]:.2f}" if r["parameter"] == "k" and len(pm) else ""
        pmax = f"{pm['max_kN'].iloc[0]:.2f}" if r["parameter"] == "k" and len(pm) else ""
        lines.append(f"| {r['set']} | {r['ligament']}.{r['parameter']} [{r['unit']}] | {r['true']:.3g} | "
                     f"{r['min']:.4g} | {r['max']:.4g} | {r['range']:.3g} | {r['mc_std']:.3g} | "
                     f"{r['predicted_std']:.3g} | {r['std_ratio']:.2f} | {pmin} | {pmax} |")
    ranges = tomllib.loads(resource("paper", "ranges.toml").read_text())
    lines += ["", "Paper (text): Sets 1-3 ranges up to "
              + ", ".join(f"{k} {v} kN" for k, v in ranges["sets_1_to_3"]["k_kN"].items()) + "; "
              + ", ".join(f"{k} {v} %" for k, v in ranges["sets_1_to_3"]["ref_strain_pct"].items())
              + f"; Set 4 at most {ranges['set4']['k_kN_max']} kN and {ranges['set4']['ref_strain_pct_max']} %.", ""]
    lines += ["## The paper's qualitative finding: Set 4 tighter than Sets 1-3 for every parameter", ""]
    paper_sets = [s for s in spec.sets if s in ("set1", "set2", "set3")]
    if "set4" in spec.sets and paper_sets:
        t4 = table[table["set"] == "set4"].set_index(["ligament", "parameter"])["range"]
        exceptions = []
        for s in paper_sets:
            ts = table[table["set"] == s].set_index(["ligament", "parameter"])["range"]
            for key, r4 in t4.items():
                if not r4 < ts.get(key, np.inf):
                    exceptions.append(f"{key[0]}.{key[1]}: set4 range {r4:.3g} vs {s} {ts.get(key):.3g}")
        lines.append("Holds for every parameter and set." if not exceptions else
                     "Does NOT hold everywhere in our knee: " + "; ".join(exceptions) + ".")
    else:
        lines.append("(needs set4 and at least one of sets 1-3)")
    lines += ["", "## Linearised prediction vs Monte Carlo", "",
              "`std_ratio` in table3.csv = Monte Carlo standard deviation / linearised standard deviation "
              "(Gauss-Newton covariance at the true parameters, sigma^2 = noise variance)."]
    far = table[(table["std_ratio"] - 1).abs() > 0.25] if not table.empty else table
    lines.append("All within 25 %." if far.empty else "Beyond 25 %: " + "; ".join(
        f"{r['set']} {r['ligament']}.{r['parameter']} {r['std_ratio']:.2f}" for _, r in far.iterrows()) + ".")
    return "\n".join(lines) + "\n"
