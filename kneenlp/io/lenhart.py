"""The default knee, built from the Lenhart 2015 OpenSim JAM model shipped with the package.

``python -m kneenlp.io.lenhart [DIR]`` (re)writes ``knee.toml`` of the default knee from
``kneenlp/resources/knees/lenhart2015/opensim/`` (Apache-2.0, see its README and LICENSE):

* coordinates: the model's ``femur_distal_r`` frame (``tibia_proximal_r`` for tibial points; the
  two coincide at the model's default pose, which is the reference pose), in metres as in
  OpenSim; kneenlp builds its femoral frame from cylinder fits to the condyles and the hip centre
  (the femur_r origin) when the knee is loaded (:mod:`kneenlp.model.frames`);
* articular surfaces: the segmented tibial cartilage, and the femoral subchondral bone with the
  articular surface 2 mm outside it (:data:`CARTILAGE_THICKNESS`; the femoral cartilage mesh is
  not part of the data: docs/real-knee.md);
* four single-bundle ligaments as in the laxity-noise paper: each is the line between the
  centroids of the femoral and of the tibial attachments of the model's bundles of that ligament
  (:data:`BUNDLES`); properties from Table 1 (the knee names ``parameters/table1.toml``);
* the tibial tuberosity: centroid of the patellar-tendon insertions;
* candidate effects for model adequacy: the posterior capsule (medial and lateral halves of the
  pCAP bundles) and the popliteofibular ligament, with the reference strains of the OpenSim
  slack lengths at the reference pose.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from kneenlp.base.atomic import write_text_atomic
from kneenlp.base.resources import resource
from kneenlp.io.osim import knee_line_elements, ligament_groups, read_osim
from kneenlp.model.parameters import KINDS

#: Which OpenSim bundle groups make each of the paper's four single-bundle ligaments.
BUNDLES = {"ACL": ("ACLam", "ACLpl"), "PCL": ("PCLal", "PCLpm"), "MCL": ("MCLs",), "LCL": ("LCL",)}
#: Femoral cartilage thickness on the subchondral bone (m): 2 mm gives 0.33 mm of overlap with the
#: tibial cartilage in the MRI pose, 3 mm 1.3 mm (docs/research/mesh-contact-representation.md).
CARTILAGE_THICKNESS = 2e-3
#: Lumped transverse meniscus springs (N/mm per compartment) of the base model: without them this
#: four-ligament knee resists at most 1.6 N m of internal rotation at 0 deg flexion (docs/real-knee.md).
MENISCUS_STIFFNESS = 5.0
OPENSIM_DIR = ("knees", "lenhart2015", "opensim")
OSIM = "lenhart2015.osim"
TIBIA_MESH = "lenhart2015-R-tibia-cartilage.stl"
FEMUR_MESH = "lenhart2015-R-femur-subchondral-bone.stl"


def _fmt(p: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.6f}" for v in p) + "]"


def knee_toml() -> str:
    """The default knee's TOML text (see module docstring)."""
    model = read_osim(resource(*OPENSIM_DIR, OSIM))
    lines = knee_line_elements(model)
    fine = ligament_groups(list(lines))["fine"]

    def centroids(names: list[str]) -> tuple[np.ndarray, np.ndarray]:
        return (np.mean([lines[n].femoral_point for n in names], axis=0),
                np.mean([lines[n].tibial_point for n in names], axis=0))

    def strain(names: list[str]) -> float:
        return float(np.mean([np.linalg.norm(lines[n].femoral_point - lines[n].tibial_point) / lines[n].slack_length - 1
                              for n in names]))

    hip = model.transform("femur_distal_r", "femur_r")[:3, 3]
    pt = [p for name, lig in model.ligaments.items() if name.startswith("PT")
          for p in [lig.points[-1]] if p.body in model.welded_bodies("tibia_proximal_r")]
    tuberosity = np.mean([model.point_in_body(p, "tibia_proximal_r") for p in pt], axis=0)
    rel = "../lenhart2015/opensim/"
    out = [
        "# kneenlp knee description: the default knee, a real right knee (Lenhart et al. 2015, OpenSim JAM).",
        "# Written by `python -m kneenlp.io.lenhart` from ../lenhart2015/opensim/lenhart2015.osim (Apache-2.0,",
        "# see the README and LICENSE there); do not edit by hand.",
        "#",
        "# Coordinates: metres in the OpenSim frame femur_distal_r (tibial points in tibia_proximal_r, which",
        "# coincides with it in the model's default pose = the reference pose).  kneenlp builds its femoral",
        "# frame from cylinder fits to the condyles and the hip centre (frame = \"cylinders\").",
        "",
        'name = "default"',
        'description = "Lenhart 2015 right knee (MRI): segmented tibial cartilage, femoral articular surface 2 mm '
        'outside the subchondral bone, four single-bundle ligaments (centroids of the model\'s bundles)"',
        'side = "right"',
        'units = "m"',
        'coordinates = "scan"',
        'frame = "cylinders"',
        'parameters = "../../parameters/table1.toml"',
        "",
        "[landmarks]",
        f"hip_center = {_fmt(hip)}                  # femur_r origin (hip joint centre)",
        f"tibial_tuberosity = {_fmt(tuberosity)}    # tibial frame: centroid of the patellar-tendon insertions",
        "",
        "[contact]",
        f'femur = "{rel}{FEMUR_MESH}"',
        f"femur_offset = {CARTILAGE_THICKNESS}   # articular surface = subchondral bone + 2 mm cartilage",
        f'tibia = "{rel}{TIBIA_MESH}"     # both plateaus, split automatically',
        "gate = 1e-5          # 0.01 mm",
        "grid_spacing = 5e-4  # 0.5 mm distance-field grid",
        "",
        "# The menisci are missing from the segmented cartilage: lumped transverse springs at the condyle",
        "# centres (without them the knee cannot carry 2 N m of internal rotation at 0 deg; docs/real-knee.md).",
        "[menisci]",
        f"stiffness = {MENISCUS_STIFFNESS}   # N/mm per compartment",
        "",
        "# Ligament attachments: centroids of the OpenSim bundles "
        + ", ".join(f"{k} = {' + '.join(v)}" for k, v in BUNDLES.items()) + ".",
    ]
    for lig, groups in BUNDLES.items():
        names = [n for g in groups for n in fine[g]]
        f, t = centroids(names)
        out += [f"[ligaments.{lig}]", f"femur = {_fmt(f)}", f"tibia = {_fmt(t)}", ""]
    cap = fine["pCAP"]
    med = [n for n in cap if lines[n].femoral_point[2] < 0]
    lat = [n for n in cap if lines[n].femoral_point[2] >= 0]
    (fm, tm), (fl, tl) = centroids(med), centroids(lat)
    out += ["# Candidate effects (model adequacy): neutral (k = 0) in the base model.",
            "[candidates.posterior_capsule]", 'kind = "bundle"',
            'description = "posterior capsule: medial and lateral halves of the pCAP bundles"',
            f"femur = [{_fmt(fm)}, {_fmt(fl)}]", f"tibia = [{_fmt(tm)}, {_fmt(tl)}]",
            f"ref_strain = {KINDS['ref_strain'].to_user * strain(cap):.2f}   # %, OpenSim slack lengths at the "
            "reference pose", ""]
    pfl = fine["PFL"]
    f, t = centroids(pfl)
    out += ["[candidates.popliteofibular]", 'kind = "bundle"',
            'description = "popliteofibular ligament (centroid of the PFL bundles)"',
            f"femur = [{_fmt(f)}]", f"tibia = [{_fmt(t)}]",
            f"ref_strain = {KINDS['ref_strain'].to_user * strain(pfl):.2f}   # %, OpenSim slack lengths at the "
            "reference pose", ""]
    return "\n".join(out)


if __name__ == "__main__":  # pragma: no cover - maintenance script
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("kneenlp/resources/knees/default")
    target.mkdir(parents=True, exist_ok=True)
    write_text_atomic(target / "knee.toml", knee_toml())
    print(target / "knee.toml")
