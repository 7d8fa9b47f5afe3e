"""A built-in structure is one module of :mod:`kneenlp.model.structures`, found by its table.

The worked example: a new structure (a spring that stops anterior tibial translation, declared by
``[anterior_stop] stiffness`` in a knee file) written as one module, and nothing else edited: the
knee file's schema takes its table, the knee carries its element, the model its parameter, a knee
that does not declare it carries it as a neutral candidate.  The menisci are such a module."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

import kneenlp
from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.model import structures
from kneenlp.model.knee_file import knee_file

STOP = '''"""An anterior stop: a spring (N/mm) against the tibia's anterior translation from the reference pose."""
import casadi as ca
from pydantic import Field

from kneenlp.base.schema import Number, Table
from kneenlp.model.elements import ForceElement
from kneenlp.model.parameters import UNIT_FACTORS, Parameter
from kneenlp.model.structures import StructureTable


class StopTable(Table):
    stiffness: Number = Field(description="stiffness (N/mm)")


class AnteriorStop(ForceElement):
    name = "anterior_stop"
    description = "a spring against anterior tibial translation"

    def __init__(self, stiffness=None):
        self.stiffness, self.candidate = stiffness, stiffness is None

    def parameters(self):
        if self.candidate:
            return [Parameter("anterior_stop.k", "spring", "stop stiffness", 0.0, 0.0)]
        return [Parameter("anterior_stop.k", "spring", "stop stiffness", self.stiffness)]

    def wrench(self, pose, values):
        force = ca.vertcat(-values["anterior_stop.k"] * pose.p[0], 0, 0)  # at the tibial origin
        return force, ca.SX.zeros(3)


TABLE = StructureTable("anterior_stop", StopTable,
                       lambda table, source: table.stiffness * UNIT_FACTORS["spring"]["N/mm"],
                       lambda knee, k: [AnteriorStop(k)], lambda knee: [AnteriorStop()],
                       lambda k: f"anterior stop: {k / 1000:g} N/mm")
'''


@pytest.fixture
def with_stop(tmp_path, monkeypatch):
    """The structures package with the anterior stop's module beside its own (one new file)."""
    (tmp_path / "anterior_stop.py").write_text(STOP)
    monkeypatch.setattr(structures, "__path__", [*structures.__path__, str(tmp_path)])
    structures.structure_tables.cache_clear()
    yield tmp_path
    monkeypatch.undo()
    structures.structure_tables.cache_clear()


def _synthetic_copy(directory: Path, extra: str = "") -> Path:
    src = knee_file("synthetic")
    shutil.copytree(src.parent, directory / "knee")
    text = src.read_text().replace('"../../parameters/', f'"{src.parent.parent.parent.as_posix()}/parameters/')
    (directory / "knee" / "knee.toml").write_text(text + extra)
    return directory / "knee" / "knee.toml"


def test_a_new_structure_is_one_module(with_stop, tmp_path):
    names = [t.name for t in structures.structure_tables()]
    assert names == ["anterior_stop", "contact", "meniscal_rim", "menisci", "oblique_popliteal", "popliteus"]
    declared = kneenlp.Knee.load(_synthetic_copy(tmp_path / "a", "\n[anterior_stop]\nstiffness = 50.0\n"))
    plain = kneenlp.Knee.load(_synthetic_copy(tmp_path / "b"))
    assert declared.structures == {"anterior_stop": pytest.approx(5e4)}
    assert "anterior stop: 50 N/mm" in declared.report()
    assert plain.structures == {}
    assert {type(e).__name__ for e in plain.structure_candidates()} == {"AnteriorStop", "Meniscus"}
    model = KneeModel.of(declared)
    assert model.theta()[model.index("anterior_stop.k")] == pytest.approx(5e4)
    drawer = next(t for t in kneenlp.Protocol.load("set1").trials if t.id.startswith("anterior"))
    stopped = kneenlp.simulate(declared, kneenlp.Protocol("one", [drawer])).solutions[0]
    free = kneenlp.simulate(plain, kneenlp.Protocol("one", [drawer])).solutions[0]
    assert stopped.converged and free.converged
    assert 0 < stopped.q[3] < free.q[3]  # the stop shortens the drawer; with it neutral, nothing changes
    with pytest.raises(InputError, match="anterior_stop"):
        kneenlp.Knee.load(_synthetic_copy(tmp_path / "c", "\n[anterior_stop]\nstiffnes = 50.0\n"))


def test_the_menisci_are_a_structure_module():
    """The Lenhart knee declares [menisci] (5 N/mm, part of its base model); a knee without the
    table carries the springs as a neutral candidate; nothing outside their module knows them."""
    default, synthetic = kneenlp.Knee.default(), kneenlp.Knee.named("synthetic")
    assert default.structures == {"menisci": pytest.approx(5e3)} and not default.structure_candidates()
    assert [e.name for e in synthetic.structure_candidates()] == ["meniscus"]
    root = Path(kneenlp.__file__).parent
    knowing = sorted(str(p.relative_to(root)) for p in root.rglob("*.py")
                     if "Meniscus" in p.read_text() and p.parent.name != "structures")
    assert knowing == []
    assert np.isclose(KneeModel.of(synthetic).theta()[KneeModel.of(synthetic).index("meniscus.k")], 0.0)


def _default_copy(folder: Path, extra: str) -> Path:
    """A copy of the default knee's file (its meshes and parameters by absolute path) plus ``extra``."""
    src = Path(kneenlp.Knee.named("default").source)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "knee.toml").write_text(src.read_text().replace('"../', f'"{src.parent}/../') + extra)
    return folder / "knee.toml"


def test_the_posterolateral_corner_structures_are_placed_from_the_knees_ligaments(tmp_path):
    """[popliteus] and [oblique_popliteal]: one module each, placed from the LCL's and the PCL's
    attachments (their documented offsets), with their own priors.  As candidates they change
    nothing (k = 0: the default knee's Set 1 to the last digit); in the base model the popliteus
    restrains external rotation, and a knee without the anchor ligament is refused in one line."""
    base = kneenlp.Knee.default()
    path = _default_copy(tmp_path / "on", "\n[popliteus]\n\n[oblique_popliteal]\n")
    knee = kneenlp.Knee.load(path)
    els = {e.name: e for e in knee.elements()}
    plt, opl = els["popliteus"], els["oblique_popliteal"]
    lcl, pcl = base.ligaments["LCL"].bundles[0], base.ligaments["PCL"].bundles[0]
    np.testing.assert_allclose(plt.bundles[0].femur - lcl.femur, [0.004, -0.008, -0.001], atol=1e-12)
    np.testing.assert_allclose(opl.bundles[0].tibia - pcl.tibia, [-0.006, 0.002, -0.018], atol=1e-12)
    assert 0.040 < opl.bundle_length(opl.bundles[0]) < 0.050  # Wu 2017: 39.5 mm, Osti 2013: 45.6 +- 4.7 mm
    model = KneeModel.of(knee)
    prior = model.parameter("popliteus.k").default_prior(1000.0)
    assert prior.shape == "lognormal" and prior.sd == 0.5
    assert "popliteus: popliteus tendon" in knee.report()
    external = [t for t in kneenlp.Protocol.load("set1").trials if t.id.startswith("external")]
    free = kneenlp.simulate(base, kneenlp.Protocol("one", external)).q
    held = kneenlp.simulate(knee, kneenlp.Protocol("one", external)).q
    assert held[0, 1] > free[0, 1] + np.radians(0.3)  # less external (negative) rotation
    neutral = kneenlp.Knee.load(_default_copy(tmp_path / "cand", "\n[popliteus]\ncandidate = true\n"))
    np.testing.assert_array_equal(kneenlp.simulate(neutral, "set1").q, kneenlp.simulate(base, "set1").q)
    from kneenlp.model.placed_bundle import Placed, declared
    from kneenlp.model.structures.popliteus import PLACEMENT

    elsewhere = dataclasses.replace(PLACEMENT, anchor="FCL")  # a knee whose LCL is called otherwise
    placed = Placed(False, np.zeros(3), np.zeros(3), 1000.0, 0.0)
    with pytest.raises(InputError, match=r"popliteus \(placed from the FCL's attachments\).*unknown ligament 'FCL'"):
        declared(elsewhere)(base, placed)
