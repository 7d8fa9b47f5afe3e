"""Benchmark / figure: designed protocols vs the paper's Sets 1-4.

Designs 22-case protocols (criteria A and R), prints the predicted relative standard errors of
every set and design, optionally (``--mc N``) runs an N-sample Monte Carlo of the R design and Set
4, and draws number of load cases vs worst relative spread into docs/figures/design_tradeoff.png.
Run: python benchmarks/bench_design.py [--mc 200] [--knee synthetic]
"""

import argparse
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd

from kneenlp import Knee, Protocol
from kneenlp.design.optimal import design, predicted_rse, write_protocol
from kneenlp.experiment.kneemodel import KneeModel


def main(mc: int = 0, knee: str = "default") -> None:
    model = KneeModel.of(Knee.named(knee))
    rows = []
    for s in ("set1", "set2", "set3", "set4"):
        p = Protocol.load(s)
        rse = predicted_rse(model, p, [f"{lig}.{k}" for lig in model.ligament_names for k in ("k", "ref_strain")],
                            "uniform:0.5")
        rows.append({"protocol": s, "cases": len(p), **{k: 100 * v for k, v in rse.items()}})
    tmp = Path(tempfile.mkdtemp())
    designs = {}
    for crit in ("A", "R"):
        t0 = time.perf_counter()
        r = design(Knee.named(knee), max_cases=22, criterion=crit, robust=3)
        designs[crit] = write_protocol(r, tmp / f"designed_{crit}22.toml")
        rows.append({"protocol": f"designed {crit}", "cases": len(r.protocol),
                     **{k: 100 * v for k, v in r.predicted_rse.items()}})
        print(f"design {crit}: {time.perf_counter() - t0:.1f} s, criterion {r.value:.4g}")
    table = pd.DataFrame(rows).set_index("protocol")
    params = [c for c in table.columns if c != "cases"]
    table["worst_%"] = table[params].max(axis=1)
    print("predicted relative standard error (%), uniform +-0.5 noise, linearised at Table 1:")
    print(table.round(2).to_string())
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, r in table.iterrows():
        ax.plot(r["cases"], 2 * r["worst_%"], "o" if name.startswith("set") else "s", ms=8)
        ax.annotate(name, (r["cases"], 2 * r["worst_%"]), textcoords="offset points", xytext=(5, 5), fontsize=8)
    if mc:
        from kneenlp.studies.study import StudySpec, run_study

        spec = StudySpec(knee=knee, sets=(str(designs["R"]), "set4"), samples=mc, seed=5)
        study = run_study(spec, tmp / "mc", progress=False)
        t3 = pd.read_csv(study.out / "table3.csv")
        t3["rel_range_%"] = 100 * t3["range"] / t3["true"].abs()
        t3["rel_std_%"] = 100 * t3["mc_std"] / t3["true"].abs()
        print(f"Monte Carlo ({mc} samples): range and standard deviation relative to the true value (%)")
        print(t3.pivot_table(index=["ligament", "parameter"], columns="set", values=["rel_range_%", "std_ratio"])
              .round(3).to_string())
        for s, sub in t3.groupby("set"):
            cases = len(Protocol.load(s))
            ax.plot(cases, sub["rel_std_%"].max() * 2, "x", color="k", ms=9)
    ax.set_xlabel("number of load cases")
    ax.set_ylabel("worst parameter: 2 x relative standard deviation [%]")
    ax.set_title("Laxity protocols: size vs worst parameter spread\n(markers: linearised; x: Monte Carlo)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(__file__).resolve().parent.parent / "docs" / "figures" / "design_tradeoff.png"
    fig.savefig(out, dpi=110)
    print(f"figure: {out}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--mc", type=int, default=0)
    ap.add_argument("--knee", default="default")
    args = ap.parse_args()
    main(args.mc, args.knee)
