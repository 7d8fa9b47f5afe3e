"""Noise studies: outputs, determinism across executors, resume after a kill."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest

import kneenlp
import kneenlp.base.resources
from kneenlp.cli import main
from kneenlp.studies.study import StudySpec, run_study, sample_seed

VOLATILE = ["seconds", "wall_seconds"]


def rows(study):
    return study.load_rows().drop(columns=VOLATILE)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    spec = StudySpec(knee="synthetic", sets=("set1", "set2"), samples=3, seed=7)
    return run_study(spec, tmp_path_factory.mktemp("study") / "local", workers=1, progress=False)


def test_outputs_and_one_row_per_sample(small):
    df = small.load_rows()
    assert len(df) == 6 and not df.duplicated(["set", "sample"]).any()
    assert df["success"].all()
    for name in ("estimates.csv", "estimates.parquet", "table3.csv", "failures.csv", "fig3_boxplots.png",
                 "fig2_set1_forces.png", "summary.md"):
        assert (small.out / name).stat().st_size > 0, name
    table = pd.read_csv(small.out / "table3.csv")
    assert {"true", "min", "max", "range", "mc_std", "predicted_std", "unit"} <= set(table.columns)
    assert set(table["unit"]) == {"kN", "%"}
    assert np.all(table["predicted_std"] > 0)
    text = (small.out / "summary.md").read_text()
    assert "Table 3 analogue" in text and "paper min" in text


def test_seeds_derive_from_study_seed_and_index_only():
    assert sample_seed(0, "set1", 5) == sample_seed(0, "set1", 5)
    assert len({sample_seed(0, s, i) for s in ("set1", "set2") for i in range(50)}) == 100


def test_protocol_file_draws_do_not_depend_on_its_directory(tmp_path):
    from kneenlp.studies.study import run_sample

    text = kneenlp.base.resources.resource("protocols", "set1.toml").read_text()
    text = text.replace('name = "set1"', 'name = "mine"')
    rows_ = []
    for where in ("a", "b/c"):
        path = tmp_path / where / "mine.toml"
        path.parent.mkdir(parents=True)
        path.write_text(text)
        rows_.append(run_sample(StudySpec(knee="synthetic", sets=(str(path),), samples=1, seed=3), str(path), 0))
    assert rows_[0]["seed"] == rows_[1]["seed"] == sample_seed(3, "mine", 0)
    assert rows_[0]["ACL.k"] == rows_[1]["ACL.k"] and rows_[0]["success"]


def test_truth_start_reaches_the_scatter_start_estimate(tmp_path):
    from kneenlp.studies.study import run_sample

    rows_ = [run_sample(StudySpec(knee="synthetic", sets=("set2",), samples=1, seed=4, start=start), "set2", 0)
             for start in ("scatter", "truth")]
    assert rows_[0]["seed"] == rows_[1]["seed"] and rows_[0]["success"] and rows_[1]["success"]
    for n in (f"{lig}.{p}" for lig in ("ACL", "PCL", "MCL", "LCL") for p in ("k", "ref_strain")):
        assert rows_[1][n] == pytest.approx(rows_[0][n], rel=1e-6), n
    assert rows_[1]["iterations"] <= rows_[0]["iterations"]
    with pytest.raises(kneenlp.InputError, match="unknown start 'middle'"):
        run_study(StudySpec(knee="synthetic", sets=("set1",), samples=1, start="middle"), tmp_path / "s",
                  progress=False)


def test_local_processes_give_identical_rows(small, tmp_path):
    other = run_study(small.spec, tmp_path / "two", workers=2, progress=False)
    pd.testing.assert_frame_equal(rows(small), rows(other))


def test_dask_local_cluster_gives_identical_rows(small, tmp_path):
    pytest.importorskip("dask.distributed")
    other = run_study(small.spec, tmp_path / "dask", workers=2, dask_local=True, progress=False)
    pd.testing.assert_frame_equal(rows(small), rows(other))


def test_resume_after_kill_loses_and_duplicates_nothing(tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "kneenlp.cli", "study", "--knee", "synthetic", "--sets", "1", "--samples", "8",
           "--workers", "1", "--seed", "3", "--quiet", "--out", str(out)]
    proc = subprocess.Popen(cmd, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and len(list((out / "samples").glob("*.json"))) < 2:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done_before = {p.name: p.read_text() for p in (out / "samples").glob("*.json")}
    assert 2 <= len(done_before) < 8
    assert subprocess.run(cmd, timeout=600).returncode == 0
    df = pd.read_csv(out / "estimates.csv")
    assert len(df) == 8 and not df.duplicated(["set", "sample"]).any()
    assert sorted(df["sample"]) == list(range(8))
    for name, text in done_before.items():  # finished samples were not recomputed
        assert (out / "samples" / name).read_text() == text
    assert not list(out.glob("samples/.*.tmp"))


def test_resume_with_other_arguments_is_refused(small, capsys):
    code = main(["study", "--knee", "synthetic",
                 "--sets", "1,2", "--samples", "3", "--seed", "8", "--quiet", "--out", str(small.out)])
    err = capsys.readouterr().err
    assert code == 2 and "holds a study with other arguments" in err and "seed" in err


def test_cli_study_json(tmp_path, capsys):
    code = main(["study", "--knee", "synthetic", "--sets", "1", "--samples", "2", "--workers", "1", "--quiet", "--json",
                 "--out", str(tmp_path / "s")])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["fits"] == 2 and out["failed"] == 0
    assert "table3.csv" in out["outputs"]


def test_protocol_files_as_sets_stay_inside_the_study(tmp_path):
    proto = tmp_path / "protocols" / "my protocol.toml"
    proto.parent.mkdir()
    proto.write_text((kneenlp_problems() / "protocols" / "set1.toml").read_text().replace('"set1"', '"mine"'))
    study = run_study(StudySpec(knee="synthetic", sets=(str(proto),), samples=2, seed=1), tmp_path / "s", workers=1,
                      progress=False)
    files = sorted(p.name for p in (tmp_path / "s" / "samples").glob("*.json"))
    assert len(files) == 2 and all(f.startswith("my_protocol-") for f in files)
    assert list(study.load_rows()["set"]) == [str(proto)] * 2
    assert not list(proto.parent.glob("*.json"))


def kneenlp_problems():
    from kneenlp.base.resources import resource

    return resource()


@pytest.mark.parametrize("address, needle", [("localhost", "tcp://HOST:PORT"),
                                             ("tcp://127.0.0.1:1", "cannot connect to the Dask scheduler")])
def test_scheduler_refused_before_any_output(tmp_path, capsys, address, needle):
    """A malformed or unreachable scheduler address is one line, exit 2, and leaves no study.json
    or samples/ behind."""
    out = tmp_path / "s"
    code = main(["study", "--knee", "synthetic", "--sets", "1", "--samples", "1", "--scheduler", address,
                 "--out", str(out), "--quiet"])
    assert code == 2 and needle in capsys.readouterr().err
    assert not (out / "study.json").exists() and not (out / "samples").exists()
