"""Calibrated ligaments out: a fit of an imported knee written back into the user's OpenSim model.

``kneenlp export-osim FIT.json --knee KNEE --model MODEL.osim --out CALIBRATED.osim``
(:func:`calibrated_values`, :func:`export_osim`): a copy of the model in which every bundle of a
fitted group gets its ``linear_stiffness`` and ``slack_length`` from the fit and nothing else
changes (:func:`kneenlp.io.osim.write_calibrated` edits the numbers inside the XML as text).

For a bundle ``i`` of group ``g`` with stiffness ``k_i`` and reference strain ``eps_i`` in the knee
(``eps_i = l_i / L0_i - 1``, ``l_i`` its length along its path in the reference pose, wrapped where
the model wraps it, ``L0_i`` the model's slack length), the fit's ``g.k_scale`` and
``g.ref_strain_offset`` give ``linear_stiffness = k_scale k_i`` and ``slack_length = l_i / (1 + eps_i
+ offset)``: the slack length of the path OpenSim computes, as kneenlp's (the model keeps its
PathWraps, which the import read: tests/test_osim_wraps.py).
"""

from __future__ import annotations

from pathlib import Path

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.io.osim import OsimError, write_calibrated
from kneenlp.model.knee import Knee
from kneenlp.model.ligament import bundle_law


def calibrated_values(knee: Knee, params: dict[str, float]) -> dict[str, dict[str, float]]:
    """``{bundle: {"linear_stiffness": N per unit strain, "slack_length": m}}`` for every bundle of
    the groups the fit ``params`` (SI, by name) calibrates: the stiffness where it has the group's
    ``k_scale``, the slack length where it has the group's ``ref_strain_offset``."""
    out: dict[str, dict[str, float]] = {}
    for name, lig in knee.ligaments.items():
        if not lig.grouped:
            continue
        scale, offset = params.get(f"{name}.k_scale"), params.get(f"{name}.ref_strain_offset")
        for b in lig.bundles:
            values = {}
            imaged = lig.bundle_length(b)
            group = (1.0 if scale is None else scale, 0.0 if offset is None else offset)
            slack, k, _ = bundle_law(b, imaged, imaged, group, lig.shift)
            if scale is not None:
                values["linear_stiffness"] = k
            if offset is not None:
                values["slack_length"] = slack
            if values:
                out[b.name] = values
    return out


def export_osim(fit_json: str | Path, knee: Knee | str | Path, model: str | Path, out: str | Path) -> list[tuple]:
    """Write ``out``: ``model`` with the ligament properties of the calibration in ``fit_json`` (the
    JSON of ``kneenlp identify --json``, ``Fit.to_json()`` or ``calibrated.toml``) for the imported
    ``knee``; returns the changes ``(bundle, property, old, new)``."""
    from kneenlp.io.export_abaqus import read_calibration

    path = Path(fit_json)
    params = read_calibration(path)
    if not Path(model).is_file():
        raise InputError("file not found", source=str(model), field="--model")
    if not Path(out).resolve().parent.is_dir():
        raise InputError(f"the directory {Path(out).resolve().parent} does not exist", source=str(out), field="--out")
    knee = knee if isinstance(knee, Knee) else Knee.load(knee)
    known = set(KneeModel.of(knee).parameter_names)
    exported = [f"{g}.{k}" for g, lig in knee.ligaments.items() if lig.grouped
                for k in ("k_scale", "ref_strain_offset")]
    for name in params:
        if name not in known:  # the list names what export-osim writes (the model has many more)
            raise unknown_name("parameter", name, exported, source=str(path)).with_context(field=f"params.{name}")
    values = calibrated_values(knee, params)
    if not values:
        raise InputError("the fit frees no bundle group of this knee (expected <group>.k_scale or "
                         "<group>.ref_strain_offset)", source=str(path), field="params")
    try:
        return write_calibrated(model, out, values)
    except OsimError as exc:
        raise InputError(str(exc)) from None
