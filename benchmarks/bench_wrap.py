"""Benchmark: what a wrapped ligament path costs.  The default knee as shipped (straight MCL) beside
the same knee whose MCL wraps the ellipsoid its OpenSim source gives the superficial MCL
(``Med_Lig_r``), and beside it wrapping a cylinder of the same place (the ellipsoid's long axis,
its middle radius): a Set 4 identification (uniform +-0.5 noise), median over seeds of the total
seconds and IPOPT iterations, and the forward solve of Set 4.  Target: a wrapped path costs at
most 2x a straight one.  Run: python benchmarks/bench_wrap.py [n_seeds]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.identify import identify
from kneenlp.experiment.measured import read_measured
from kneenlp.io.osim import read_osim
from kneenlp.io.osim.model import rot_body_xyz


def wrapped_default(folder: Path, shape: str) -> kneenlp.Knee:
    """The default knee with its MCL over Lenhart's ``Med_Lig_r`` (as an ellipsoid or a cylinder)."""
    src = Path(kneenlp.Knee.named("default").source)
    wo = read_osim(resource("knees", "lenhart2015", "opensim", "lenhart2015.osim")).wrap_objects["Med_Lig_r"]
    axes = rot_body_xyz(wo.xyz_body_rotation)
    centre = ", ".join(f"{v:.6f}" for v in wo.translation)
    if shape == "ellipsoid":
        table = (f'shape = "ellipsoid"\nbody = "tibia"\ncentre = [{centre}]\n'
                 f"axes = [{', '.join('[' + ', '.join(f'{v:.9f}' for v in a) + ']' for a in axes.T)}]\n"
                 f"radii = [{', '.join(f'{v:.4f}' for v in wo.dimensions['dimensions'])}]\n")
    else:
        table = (f'body = "tibia"\ncentre = [{centre}]\naxis = [{", ".join(f"{v:.9f}" for v in axes[:, 0])}]\n'
                 f'radius = {wo.dimensions["dimensions"][1]:.4f}\nside = "positive"\n')
    text = src.read_text().replace('"../', f'"{src.parent}/../')
    text = text.replace("[ligaments.LCL]", f"[ligaments.MCL.wrap]\n{table}\n[ligaments.LCL]")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "knee.toml").write_text(text)
    return kneenlp.Knee.load(folder / "knee.toml")


def bench(label: str, knee: kneenlp.Knee, seeds: range, tmp: Path) -> float:
    t0 = time.perf_counter()
    res = kneenlp.simulate(knee, "set4")
    forward = time.perf_counter() - t0
    rows = []
    for seed in (10_000, *seeds):  # the first fit builds the NLP: timed apart
        path = tmp / f"{label}_{seed}.csv"
        res.measured("uniform:0.5", seed).to_csv(path, index=False)
        t0 = time.perf_counter()
        fit = identify(knee, read_measured(path), seed=seed, noise="uniform:0.5")
        rows.append((time.perf_counter() - t0, fit.iterations, fit.success))
    first, rows = rows[0], rows[1:]
    total = float(np.median([r[0] for r in rows]))
    print(f"{label}: Set 4 forward (build + solve) {forward:.2f} s; first fit {first[0]:.2f} s; median of "
          f"{len(rows)} seeds: total {total:.2f} s, {np.median([r[1] for r in rows]):.0f} iterations, converged "
          f"{sum(r[2] for r in rows)}/{len(rows)}", flush=True)
    return total


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    tmp = Path(tempfile.mkdtemp())
    straight = bench("straight MCL", kneenlp.Knee.named("default"), range(n), tmp)
    for shape in ("ellipsoid", "cylinder"):
        knee = wrapped_default(tmp / shape, shape)
        mcl = knee.ligaments["MCL"]
        b = mcl.bundles[0]
        print(f"MCL over a {shape}: reference length {1e3 * mcl.bundle_length(b):.2f} mm "
              f"(straight {1e3 * np.linalg.norm(b.femur - mcl.tibia_at_reference(b.tibia)):.2f} mm)")
        cost = bench(f"MCL over a {shape}", knee, range(n), tmp)
        print(f"  wrapped / straight: {cost / straight:.2f}x (target <= 2x)")
