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
    packages = {p.relative_to(ROOT).as_posix() for p in (ROOT / "kneenlp").rglob("__init__.py")}
    assert len(packages) >= 15 and packages <= names, sorted(packages - names)[:5]  # every layer's folder


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


def test_compiled_loops_are_cached_in_the_users_cache(tmp_path):
    """numba's machine code goes to kneenlp's cache directory ($KNEENLP_CACHE here), never into the
    installed package."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    import kneenlp.geometry.kernels as kernels

    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"} | {"KNEENLP_CACHE": str(tmp_path)}
    code = ("import numpy as np\nfrom kneenlp.geometry.spline_kernels import field_values\n"
            "field_values((np.zeros((5, 5, 5)), np.zeros(3), 1.0), np.full((1, 3), 1.5), np.empty(1))\n")
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=300)
    assert list((tmp_path / "numba").rglob("*field_values*.nbi"))
    package = Path(kernels.__file__).parent
    assert not list(package.rglob("*.nbi")) and not list(package.rglob("*.nbc"))
