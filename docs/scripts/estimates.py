"""The estimates of every shipped problem (``problems/*``), written to or checked against a JSON file.

A refactoring must not move a number: ``python docs/scripts/estimates.py --write before.json`` before
it, ``python docs/scripts/estimates.py --check before.json`` after it (exit 1 when any parameter's
estimate or the objective moved by more than ``--rtol``, default 1e-10 relative to max(|value|,
the parameter's scale)).  Values are SI, as the fits hold them.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def estimates(problem: Path) -> dict[str, float]:
    """The fitted parameters (SI) and the objective of ``kneenlp identify --problem``."""
    with tempfile.TemporaryDirectory() as out:
        subprocess.run([sys.executable, "-m", "kneenlp.cli", "identify", "--problem", str(problem), "--out", out],
                       check=True, capture_output=True)
        fit = json.loads((Path(out) / "fit.json").read_text())
    return {**{k: float(v) for k, v in fit["params"].items()}, "objective": float(fit["objective"])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", type=Path)
    ap.add_argument("--check", type=Path)
    ap.add_argument("--rtol", type=float, default=1e-10)
    shipped = sorted(str(p.parent) for p in (ROOT / "problems").glob("*/problem.toml"))
    ap.add_argument("problems", nargs="*", default=shipped)
    args = ap.parse_args()
    now = {Path(p).name: estimates(Path(p)) for p in args.problems}
    if args.write:
        args.write.write_text(json.dumps(now, indent=1, sort_keys=True))
    if not args.check:
        return 0
    before, worst = json.loads(args.check.read_text()), 0.0
    for name, values in now.items():
        for key, v in values.items():
            old = before[name][key]
            rel = abs(v - old) / max(abs(old), 1e-3 if key != "objective" else 1e-12)
            worst = max(worst, rel)
            if rel > args.rtol:
                print(f"{name} {key}: {old!r} -> {v!r} (relative {rel:.1e})")
    print(f"largest relative change {worst:.1e} (tolerance {args.rtol:g})")
    return int(worst > args.rtol)


if __name__ == "__main__":
    sys.exit(main())
