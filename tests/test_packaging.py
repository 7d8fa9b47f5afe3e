"""The package ships its data: a built wheel holds the default knee, parameters and protocols."""

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_contains_package_data(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
                   check=True, capture_output=True)
    wheel = next(tmp_path.glob("kneenlp-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {p.relative_to(ROOT).as_posix() for p in (ROOT / "kneenlp" / "resources").rglob("*") if p.is_file()}
    assert {"kneenlp/resources/knees/default/knee.toml", "kneenlp/resources/parameters/table1.toml",
            "kneenlp/resources/protocols/set4.toml", "kneenlp/resources/datasets/hidden_effect_set3.csv"} <= shipped
    assert shipped <= names, sorted(shipped - names)[:5]
    assert any(n.startswith("kneenlp/resources/knees/default/meshes/") and n.endswith(".stl") for n in names)
    for sub in ("model", "experiment", "solvers", "inference", "studies", "io"):
        assert f"kneenlp/{sub}/__init__.py" in names
