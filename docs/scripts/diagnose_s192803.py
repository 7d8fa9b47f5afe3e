"""The figures of docs/real-experiment.md "Where it fails, and why": ``kneenlp diagnose`` of the
S192803 robot data (``problems/s192803/laxity.csv``) on the s192803 knee, declared with the
robot's precision (uniform +-0.2 mm and deg).

    python docs/scripts/diagnose_s192803.py               # the verdict and its figures (30 s)
    python docs/scripts/diagnose_s192803.py --held-out 2  # and the two best candidates judged by
                                                          # their held-out error (minutes)

Prints the chi-square and its degrees of freedom, the p value of the bias test (mean residuals
per load direction), the sign patterns (mm, deg) and, with ``--held-out``, each candidate's held-out
mean normalised error and the number of hold-outs within 2 mm / 5 deg.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path

from kneenlp.cli.main import main

DATA = Path(__file__).resolve().parents[2] / "problems" / "s192803" / "laxity.csv"


def diagnosis(held_out: int = 0) -> dict:
    """The command's JSON report, and ``pattern_means``: each sign pattern's mean residual (mm or
    deg) by coordinate and place (``"lateral translation under external load"``)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(["diagnose", str(DATA), "--knee", "s192803", "--noise", "uniform:0.2",
                       "--held-out", str(held_out), "--json"])
    assert status == 0, f"diagnose exited {status}"
    report = json.loads(out.getvalue())
    report["pattern_means"] = {f"{p['coordinate'].replace('_', ' ')} {p['where']}": p["mean"]
                               for p in report["pattern_means"]}
    return report


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--held-out", type=int, default=0)
    r = diagnosis(parser.parse_args().held_out)
    print(f"chi-square {r['chi2']:.0f} on {r['dof']} degrees of freedom; bias test p {r['tests']['bias_p']:.4f}")
    print(r["verdict"].split(":")[0])
    for p in r["patterns"]:
        print("  " + p)
    for j in r.get("held_out", []):
        print(f"  {j['name']}: held out mean {j['held_out_mean']:.2f}, met {j['held_out_met']} of 7")
