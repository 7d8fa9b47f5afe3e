"""The noise study of docs/opensim.md ("Noise study: Set 4 vs Set 4 + high flexion vs a designed
protocol") on the imported Lenhart 2015 OpenSim knee, and the figures the doc quotes from it.

    python docs/scripts/multibundle_study.py --osim-dir ../shared/data/opensim-jam-lenhart2015 --work W
        # imports the knee into W/lenhart, runs the two studies (100 samples x 3 protocols each, about
        # 2 h on 2 cores; resumable), copies their table3.csv and boxplots into docs/figures/
    python docs/scripts/multibundle_study.py          # the figures of the shipped tables (instant)

The studies are the doc's ``kneenlp study`` command: all 12 group parameters free, and the 10
identifiable ones (the posterior capsule at its model values).  :func:`figures` reads a table
(docs/figures/multibundle_study_table3_12.csv or _10.csv) and returns what the doc quotes: the
ratios of Monte Carlo to linearised standard deviation (``std_ratio``), dimensionless.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import pandas as pd

from kneenlp.cli.main import main

FIGURES = Path(__file__).resolve().parents[1] / "figures"
SETS = f"set4,set4_high_flexion,{FIGURES / 'designed_multibundle_protocol.toml'}"
#: The 10 identifiable group parameters (the capsule, pCAP, fixed).
IDENTIFIABLE = [f"{g}.{p}" for g in ("MCL", "ACL", "PCL", "LCL", "PFL") for p in ("k_scale", "ref_strain_offset")]


def figures(free: int) -> dict:
    """The quoted figures of the shipped table with ``free`` (12 or 10) parameters free: the
    ratio range of the capsule (12 only), of Set 4's PCL stiffness scale and of every other row, and
    the PCL stiffness scale's ratio per protocol."""
    t = pd.read_csv(FIGURES / f"multibundle_study_table3_{free}.csv")
    t["protocol"] = t["set"].map(lambda s: s if s.startswith("set") else "designed")
    capsule = t["ligament"] == "pCAP"
    pcl_k = (t["ligament"] == "PCL") & (t["parameter"] == "k_scale")
    set4_pcl_k = pcl_k & (t["protocol"] == "set4")
    rest = t[~capsule & ~set4_pcl_k]["std_ratio"]
    out = {"rows": len(t), "set4_pcl_k_scale": float(t[set4_pcl_k]["std_ratio"].iloc[0]),
           "others": (float(rest.min()), float(rest.max())),
           "others_within_25pct": int(((rest - 1).abs() <= 0.25).sum()),
           "pcl_k_scale": dict(zip(t[pcl_k]["protocol"], t[pcl_k]["std_ratio"].astype(float), strict=True))}
    if capsule.any():
        out["capsule"] = (float(t[capsule]["std_ratio"].min()), float(t[capsule]["std_ratio"].max()))
    return out


def run(osim_dir: Path, work: Path, samples: int) -> None:
    """Import the knee, run both studies into ``work``, copy their tables and boxplots to docs/figures."""
    knee = work / "lenhart" / "knee.toml"
    if not knee.exists():
        assert main(["import-osim", str(osim_dir / "lenhart2015.osim"), "--out", str(knee.parent), "--groups",
                     "coarse", "--femur-mesh", str(osim_dir / "lenhart2015-R-femur-subchondral-bone.stl"),
                     "--femur-offset", "2"]) == 0
    for free, extra in ((12, []), (10, ["--free", ",".join(IDENTIFIABLE)])):
        out = work / f"study_{free}"
        assert main(["study", "--knee", str(knee), "--sets", SETS, "--samples", str(samples), "--start", "truth",
                     "--noise", "uniform:0.5", "--seed", "0", "--workers", "2", "--out", str(out), *extra]) == 0
        shutil.copy(out / "table3.csv", FIGURES / f"multibundle_study_table3_{free}.csv")
        if free == 12:
            shutil.copy(out / "fig3_boxplots.png", FIGURES / "multibundle_study_fig3.png")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--osim-dir", type=Path, help="the OpenSim JAM Lenhart 2015 model's folder: run the studies")
    parser.add_argument("--work", type=Path, default=Path("multibundle_study"))
    parser.add_argument("--samples", type=int, default=100)
    args = parser.parse_args()
    if args.osim_dir:
        run(args.osim_dir, args.work, args.samples)
    for free in (12, 10):
        print(f"{free} free:", figures(free))
