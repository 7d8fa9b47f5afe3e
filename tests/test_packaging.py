"""The package ships its data: a built wheel holds the default knee, parameters and protocols."""

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)],
                   check=True, capture_output=True)
    return next(out.glob("kneenlp-*.whl"))


def test_wheel_contains_package_data(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {p.relative_to(ROOT).as_posix() for p in (ROOT / "kneenlp" / "resources").rglob("*") if p.is_file()}
    assert {"kneenlp/resources/knees/default/knee.toml", "kneenlp/resources/parameters/table1.toml",
            "kneenlp/resources/protocols/set4.toml", "kneenlp/resources/datasets/hidden_effect_set3.csv"} <= shipped
    assert shipped <= names, sorted(shipped - names)[:5]
    assert any(n.startswith("kneenlp/resources/knees/synthetic/meshes/") and n.endswith(".stl") for n in names)
    for sub in ("geometry", "model", "experiment", "solvers", "inference", "studies", "io"):
        assert f"kneenlp/{sub}/__init__.py" in names


def test_installed_wheel_runs_from_another_directory(wheel, tmp_path):
    """The wheel's own copy of kneenlp (not this checkout) simulates Set 3 from an unrelated directory."""
    import json
    import os

    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
                   check=True, capture_output=True)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(target), "MPLBACKEND": "Agg"}
    where = subprocess.run([sys.executable, "-c", "import kneenlp; print(kneenlp.__file__)"], cwd=work, env=env,
                           check=True, capture_output=True, text=True).stdout
    assert where.startswith(str(target))
    run = subprocess.run([sys.executable, "-m", "kneenlp.cli", "simulate", "--protocol", "set3", "--no-plots",
                          "--out", "out", "--json"], cwd=work, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["converged"] == 26
