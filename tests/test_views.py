"""Pictures without OpenSim (kneenlp.io.views, ``kneenlp view``): pressure maps and 3-D views.

Fast tests on the synthetic knee (explicit spheres) with Set 1, one on the default real knee (mesh
contact; ~20 s the first time its distance field is built, then cached)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.cli import main
from kneenlp.experiment.protocol import Protocol
from kneenlp.io import views

pytest.importorskip("plotly")

LIGAMENTS = ("ACL", "PCL", "MCL", "LCL")


@pytest.fixture(scope="module")
def set1(knee) -> kneenlp.SimulationResult:
    return kneenlp.simulate(knee, "set1")


def _check_png(path) -> None:
    assert path.exists() and path.stat().st_size > 10_000, path
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _check_html(path) -> None:
    assert path.exists() and path.stat().st_size > 10_000, path
    text = path.read_text()
    assert "plotly" in text
    for name in LIGAMENTS:
        assert name in text, name


def test_pressure_map_and_knee_view_files(set1, tmp_path):
    png = views.pressure_map(set1, ["none_flex30", "anterior_134N_flex30", "varus_10Nm_flex0"], tmp_path / "p.png")
    _check_png(png)
    written = views.knee_view(set1, "none_flex30", tmp_path / "v.png", tmp_path / "v.html")
    assert written == [tmp_path / "v.png", tmp_path / "v.html"]
    _check_png(written[0])
    _check_html(written[1])


def test_unloaded_pressure_integrates_to_the_contact_force(set1):
    sol = next(s for s in set1.solutions if s.trial.id == "none_flex30")
    maps = views.contact_maps(set1, "none_flex30")
    assert set(maps) == {"medial", "lateral"}
    R, p = views.pose(set1, sol)
    for name, m in maps.items():
        comp = set1.knee.compartments[name]
        assert m.pressure.max() > 0 and len(m.pressure) == len(comp.points)
        output = sol.outputs[f"contact_{name}_N"]
        # pressure x area summed along the sphere's normals is exactly the element's force ...
        X = comp.points @ R.T + p
        n = (X - comp.centre) / np.linalg.norm(X - comp.centre, axis=1, keepdims=True)
        vector = ((m.pressure * m.areas)[:, None] * n).sum(axis=0)
        assert np.linalg.norm(vector) == pytest.approx(output, rel=1e-9)
        # ... and the plain sum exceeds it only by the normals' spread over the contact patch (~1 %)
        assert output <= m.integrated <= 1.015 * output
        # the centre of pressure lies on the plateau, in the loaded patch
        assert np.linalg.norm(m.cop - comp.points[np.argmax(m.pressure)]) < 3e-3


def test_unknown_trial_and_missing_plotly(set1, monkeypatch, tmp_path):
    with pytest.raises(InputError, match="unknown trial 'nope'; known: "):
        views.pressure_map(set1, ["nope"], tmp_path / "x.png")
    monkeypatch.setitem(sys.modules, "plotly", None)
    monkeypatch.setitem(sys.modules, "plotly.graph_objects", None)
    with pytest.raises(InputError, match=r"needs plotly: pip install 'kneenlp\[view\]'"):
        views.knee_view(set1, "none_flex30", None, tmp_path / "v.html")
    assert not (tmp_path / "v.html").exists()


def test_default_view_trials():
    assert views.default_view_trials(Protocol.load("set3")) == [
        "none_flex0", "none_flex30", "anterior_134N_flex0", "posterior_67N_flex0", "internal_2Nm_flex0",
        "external_2Nm_flex0", "varus_10Nm_flex0", "valgus_10Nm_flex0"]
    # Set 1 tests AP and IE at 30 deg only: those directions are drawn at their own first flexion
    assert len(views.default_view_trials(Protocol.load("set1"))) == 7


def test_decimate_keeps_shape_and_budget():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=20.0)
    v, f, val = views.decimate(sphere.vertices, sphere.faces, 2000, sphere.vertices[:, 1])
    assert len(f) < 4000 and len(f) > 500
    assert np.allclose(np.linalg.norm(v, axis=1), 20.0, atol=1.0)
    assert np.allclose(val, v[:, 1])


def test_cli_view(tmp_path, capsys):
    code = main(["view", "--knee", "synthetic", "--protocol", "set1", "--trial", "none_flex30",
                 "--out", str(tmp_path)])
    out = capsys.readouterr().out.split()
    assert code == 0
    expected = [tmp_path / f"{kind}_none_flex30.{ext}" for kind, ext in (("pressure", "png"), ("view", "png"),
                                                                          ("view", "html"))]
    assert out == [str(p) for p in expected]
    for p in expected[:2]:
        _check_png(p)
    _check_html(expected[2])


def test_cli_view_unknown_trial(tmp_path, capsys):
    code = main(["view", "--knee", "synthetic", "--protocol", "set1", "--trial", "x", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("kneenlp: error: --trial: unknown trial 'x'; known: anterior_134N_flex30") and "\n" not in err
    assert not any(tmp_path.iterdir())


def test_real_knee_unloaded_views(real_knee, tmp_path):
    protocol = Protocol.from_dict({"name": "unloaded", "cases": [{"direction": "none", "flexion": [0.0]}]})
    result = kneenlp.simulate(real_knee, protocol)
    assert not result.failed
    sol = result.solutions[0]
    maps = views.contact_maps(result, sol.trial.id)
    for name, m in maps.items():
        assert m.pressure.max() > 0
        assert m.integrated == pytest.approx(sol.outputs[f"contact_{name}_N"], rel=0.01)
        assert m.load == pytest.approx(sol.outputs[f"contact_{name}_N"], rel=1e-9)
    _check_png(views.pressure_map(result, [sol.trial.id], tmp_path / "p.png"))
    png, html = views.knee_view(result, sol.trial.id, tmp_path / "v.png", tmp_path / "v.html")
    _check_png(png)
    _check_html(html)


def test_an_empty_legend_is_not_drawn():
    """No matplotlib warning about a legend without labelled artists (a stray library warning)."""
    import warnings

    from kneenlp.figures.plots import _subplots, legend

    _, ax = _subplots(1, 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        legend(ax)
    assert ax.get_legend() is None
    ax.plot([0, 1], [0, 1], label="x")
    legend(ax)
    assert ax.get_legend() is not None
