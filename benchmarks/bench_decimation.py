"""Huge meshes: the time and memory of a knee load, and the decimation's effect on contact.

The default knee's meshes are subdivided (midpoint subdivision: the same surface, 4x the faces
per level) to 1.23 million femoral faces (3 levels) and 2.2 million tibial faces (4 levels), and a
knee file points at them.  Each load runs in its own process with an empty distance-field cache, so
the figures are a first load: ``Knee.load`` plus the femoral distance field (the rest of a command
works on the decimated meshes).  Then Set 1 is simulated on the original knee and on the one read
from the fine meshes, and the contact forces at equilibrium compared.  Finally a 4.9-million-face
femur (4 levels), beyond the files a knee reads, must be refused at once.

    python benchmarks/bench_decimation.py      # about 4 min on 2 cores

Prints: faces before/after, load time, peak RSS, the largest change of contact force (per trial,
medial + lateral) and of the kinematics.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from kneenlp.model.knee_file import knee_file

DEFAULT = knee_file("default")
LENHART = DEFAULT.parent.parent / "lenhart2015" / "opensim"
FEMUR = LENHART / "lenhart2015-R-femur-subchondral-bone.stl"
TIBIA = LENHART / "lenhart2015-R-tibia-cartilage.stl"
PARAMETERS = DEFAULT.parent.parent.parent / "parameters" / "table1.toml"

#: Run in a fresh process: load the knee (and build its field), report, optionally simulate set1.
CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
import kneenlp
from kneenlp.base.errors import InputError
t1 = time.perf_counter()
try:
    knee = kneenlp.Knee.load(sys.argv[1])
    knee.femur.field
except InputError as exc:
    print(json.dumps({"error": str(exc), "seconds": time.perf_counter() - t1}))
    sys.exit(0)
# this process's peak resident memory (VmHWM; ru_maxrss would keep the parent's across fork and exec)
hwm = [line for line in open("/proc/self/status") if line.startswith("VmHWM")]
peak = int(hwm[0].split()[1]) / 1e6 if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
out = {"seconds": time.perf_counter() - t1, "import_seconds": t1 - t0, "peak_rss_gb": peak,
       "femur_faces": len(knee.femur.mesh.faces),
       "tibia_faces": sum(len(c.tibia_mesh.faces) for c in knee.compartments.values()),
       "tibia_points": sum(len(c.points) for c in knee.compartments.values()),
       "notes": [n for n in knee.notes if "decimated" in n]}
if len(sys.argv) > 2:
    result = kneenlp.simulate(knee, "set1")
    out["table"] = result.table().to_dict(orient="list")
print(json.dumps(out))
"""


def subdivided(path: Path, levels: int, out: Path) -> int:
    """Write ``path`` subdivided ``levels`` times to ``out`` (binary STL); returns its faces."""
    mesh = trimesh.load(path)
    v, f = mesh.vertices, mesh.faces
    for _ in range(levels):
        v, f = trimesh.remesh.subdivide(v, f)
    trimesh.Trimesh(v, f, process=False).export(out)
    return len(f)


def knee_with(tmp: Path, name: str, femur: Path, tibia: Path) -> Path:
    text = DEFAULT.read_text()
    text = text.replace('"../lenhart2015/opensim/lenhart2015-R-femur-subchondral-bone.stl"', f'"{femur.as_posix()}"')
    text = text.replace('"../lenhart2015/opensim/lenhart2015-R-tibia-cartilage.stl"', f'"{tibia.as_posix()}"')
    text = text.replace('"../../parameters/table1.toml"', f'"{PARAMETERS.as_posix()}"')
    path = tmp / f"{name}.toml"
    path.write_text(text)
    return path


def child(knee: Path, cache: Path, simulate: bool = False) -> dict:
    env = {**os.environ, "KNEENLP_CACHE": str(cache)}
    args = [sys.executable, "-c", CHILD, str(knee)] + (["simulate"] if simulate else [])
    proc = subprocess.run(args, capture_output=True, text=True, env=env, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        t = time.perf_counter()
        n_femur = subdivided(FEMUR, 3, tmp / "femur_fine.stl")
        n_tibia = subdivided(TIBIA, 4, tmp / "tibia_fine.stl")
        n_huge = subdivided(FEMUR, 4, tmp / "femur_huge.stl")
        print(f"meshes written in {time.perf_counter() - t:.0f} s: femur {n_femur:,} faces, tibia {n_tibia:,}, "
              f"huge femur {n_huge:,}")
        original = knee_with(tmp, "original", FEMUR, TIBIA)
        fine = knee_with(tmp, "fine", tmp / "femur_fine.stl", tmp / "tibia_fine.stl")
        huge = knee_with(tmp, "huge", tmp / "femur_huge.stl", TIBIA)

        ref = child(original, tmp / "cache_original", simulate=True)
        dec = child(fine, tmp / "cache_fine", simulate=True)
        refused = child(huge, tmp / "cache_huge")
        for name, r in (("original", ref), ("fine meshes", dec)):
            print(f"{name:12s} load + field {r['seconds']:5.1f} s (imports {r['import_seconds']:.1f} s), peak RSS "
                  f"{r['peak_rss_gb']:.2f} GB; femur {r['femur_faces']:,} faces, tibia {r['tibia_faces']:,} faces "
                  f"({r['tibia_points']:,} contact points)")
        for note in dec["notes"]:
            print(f"  {note}")
        print(f"huge femur   {refused.get('error', 'NOT REFUSED')} ({refused['seconds']:.2f} s)")

        a, b = ref["table"], dec["table"]
        total_a = np.array(a["contact_medial_N"]) + np.array(a["contact_lateral_N"])
        total_b = np.array(b["contact_medial_N"]) + np.array(b["contact_lateral_N"])
        change = np.abs(total_b - total_a) / total_a
        print("contact force (medial + lateral) per Set 1 trial, original -> fine meshes decimated:")
        for i, trial in enumerate(a["trial"]):
            print(f"  {trial:26s} {total_a[i]:8.1f} N -> {total_b[i]:8.1f} N ({100 * change[i]:+.2f} %)")
        print(f"largest change of contact force: {100 * change.max():.2f} % (target < 1 %)")
        for col in a:
            if col.endswith(("_mm", "_deg")) and col.split("_")[0] in ("varus", "internal", "lateral", "anterior",
                                                                       "proximal"):
                diff = np.max(np.abs(np.array(b[col]) - np.array(a[col])))
                print(f"  largest change of {col}: {diff:.3f}")


if __name__ == "__main__":
    main()
