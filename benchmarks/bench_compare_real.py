"""Benchmark: the methods on the real experiment's calibration problem (S192803, MAP
with the default priors, registration and load point, all 25 trials): the reduced-space fit, IPOPT
from the calibration's start, IPOPT from the reduced fit (the calibration's solver) and the nested
Complex method, its best MAP objective after 1k, 5k, 20k and 75k rootfinder solves.
Target: the simultaneous NLP's objective <= the reduced method's (within 1e-6 relative).
Run: python benchmarks/bench_compare_real.py [MAX_SOLVES]   (75000: about 15-30 min on 2 cores)
"""

import sys

from kneenlp.base.resources import resource
from kneenlp.cli import main

if __name__ == "__main__":
    solves = sys.argv[1] if len(sys.argv) > 1 else "75000"
    main(["compare-methods", str(resource("datasets", "s192803_laxity.csv")), "--knee", "s192803",
          "--max-solves", solves])
