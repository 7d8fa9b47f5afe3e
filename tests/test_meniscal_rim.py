"""The deforming menisci (kneenlp.model.structures.meniscal_rim).

Oracles: the closed form of a rim without hoop (each node its own spring in series with the
contact) and of its push against a transverse move (``k delta``, the definition of ``k``), a
brute-force minimisation of the rim's energy for the nodes' balance with hoop, and the knee
without the rim (a neutral candidate changes nothing, to the last digit).
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import minimize

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.model.structures.meniscal_rim import SWITCH, MeniscalRim, MeniscalRimTable


def node_forces(rim: MeniscalRim, move: np.ndarray, k: float) -> np.ndarray:
    """The rim's node forces (N) with the condyle moved by ``move`` (tibial frame, m) from rest."""
    c, ks = ca.SX.sym("c", 3), ca.SX.sym("k")
    f = ca.Function("f", [c, ks], [rim.node_forces(c, np.zeros(3), ks)])
    return np.asarray(f(move, k)).ravel()


def rim(**table) -> MeniscalRim:
    return MeniscalRim([np.zeros(3)], MeniscalRimTable(**table), [np.zeros(3)])


def test_without_hoop_each_node_is_a_spring_in_series_with_the_contact():
    r = rim(hoop_ratio=0.0, nodes=12)
    k, move = 5e3, np.array([1.2e-3, 0.0, -0.7e-3])
    d = r.directions @ move
    w = 0.5 * (1 + np.tanh(d / SWITCH))
    k_n, k_c = 4 * k / 12, r.contact
    np.testing.assert_allclose(node_forces(r, move, k), k_n * k_c * w * d / (k_n + k_c * w), rtol=1e-10, atol=1e-12)


def test_a_stiff_contact_without_hoop_pushes_back_with_k_times_the_move():
    """With the contact rigid, a rim of 12 nodes pushes a condyle moved anteriorly back with
    ``4 k / 12 * sum cos^2`` over the nodes in front = ``k delta``: the definition of k."""
    r = rim(hoop_ratio=0.0, contact=1e9, nodes=12)
    k, delta = 5e3, 5e-3  # 5 N/mm, 5 mm: far beyond the switch's width
    total = r.directions.T @ node_forces(r, np.array([delta, 0.0, 0.0]), k)
    np.testing.assert_allclose(total, [k * delta, 0.0, 0.0], rtol=1e-6, atol=1e-9)


def test_with_hoop_the_nodes_minimise_the_rims_energy():
    r = rim(hoop_ratio=300.0, nodes=8)
    k, move = 5e3, np.array([-2e-3, 0.0, 1e-3])
    d = r.directions @ move
    w = 0.5 * (1 + np.tanh(d / SWITCH))
    k_n = 4 * k / 8

    def energy(u):
        return 0.5 * k_n * u @ r.structure @ u + 0.5 * r.contact * np.sum(w * (d - u) ** 2)

    u = minimize(energy, np.zeros(8), method="BFGS", options={"gtol": 1e-14}).x
    np.testing.assert_allclose(node_forces(r, move, k), r.contact * w * (d - u), rtol=1e-5, atol=1e-9)
    # the hoop spreads the push over the rim: the rim pushes back harder than without it
    assert np.linalg.norm(r.directions.T @ node_forces(r, move, k)) > np.linalg.norm(
        r.directions.T @ node_forces(rim(hoop_ratio=0.0, nodes=8), move, k))


def _synthetic_copy(folder: Path, extra: str) -> Path:
    src = Path(kneenlp.Knee.named("synthetic").source)
    folder.mkdir(parents=True, exist_ok=True)
    text = src.read_text().replace('"meshes/', f'"{src.parent}/meshes/').replace('"../', f'"{src.parent}/../')
    (folder / "knee.toml").write_text(text + extra)
    return folder / "knee.toml"


def test_a_knee_declares_the_rim_and_a_candidate_changes_nothing(tmp_path):
    base = kneenlp.Knee.named("synthetic")
    knee = kneenlp.Knee.load(_synthetic_copy(tmp_path / "on", "\n[meniscal_rim]\nstiffness = 8\n"))
    assert "meniscal_rim: 12 nodes on a 18 mm rim" in knee.report()
    model = KneeModel.of(knee)
    assert model.theta()[model.index("meniscal_rim.k")] == pytest.approx(8e3)
    plain, with_rim = kneenlp.simulate(base, "set1"), kneenlp.simulate(knee, "set1")
    assert with_rim.converged == len(with_rim.solutions)
    assert (with_rim.table()[["meniscal_rim_medial_N", "meniscal_rim_lateral_N"]].to_numpy() >= 0).all()
    assert np.abs(with_rim.q - plain.q).max() > 1e-4  # the rim holds the condyles
    candidate = kneenlp.Knee.load(_synthetic_copy(tmp_path / "cand", "\n[meniscal_rim]\ncandidate = true\n"))
    assert "meniscal_rim" in [e.name for e in KneeModel.of(candidate).effects]
    np.testing.assert_array_equal(kneenlp.simulate(candidate, "set1").q, plain.q)


@pytest.mark.parametrize(("line", "needle"), [("nodes = 2", "meniscal_rim.nodes"),
                                              ("radius = -3", "meniscal_rim.radius")])
def test_a_bad_rim_is_one_line_naming_the_field(tmp_path, line, needle):
    with pytest.raises(InputError, match=needle):
        kneenlp.Knee.load(_synthetic_copy(tmp_path, f"\n[meniscal_rim]\n{line}\n"))
