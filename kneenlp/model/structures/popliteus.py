"""The popliteus tendon (PLT), ``[popliteus]`` in a knee file (:mod:`kneenlp.model.placed_bundle`).

The main restraint of external rotation beside the popliteofibular ligament and the LCL.  Placed
from the LCL: its femoral insertion 4 mm anterior, 8 mm distal and 1 mm medial of the LCL's (the
proximal, anterior fifth of the popliteal sulcus, always anterior of the LCL: LaPrade et al. 2003,
Osti et al. 2013), its tibial end at the popliteal musculotendinous junction, 5 mm posterior,
10 mm distal and 12 mm medial of the LCL's fibular insertion (an estimate from the anatomy: James
et al. 2015).  Stiffness log-normal, median 1000 N per unit strain, sd 0.5 of its log (the FE and
multibody values 1040-2200 N); reference strain 0 +- 5 %.  Declared only: a knee file without the
table has no popliteus (no candidate added to every knee).
"""

from __future__ import annotations

from kneenlp.model.placed_bundle import PlacedTable, Placement, declared, describe, reader
from kneenlp.model.structures import StructureTable

PLACEMENT = Placement("popliteus", "popliteus tendon (femoral insertion to the musculotendinous junction)", "LCL",
                      (4.0, -8.0, -1.0), (-5.0, -10.0, -12.0), (1000.0, 0.5), (0.0, 0.05))

TABLE = StructureTable("popliteus", PlacedTable, reader(PLACEMENT), declared(PLACEMENT), lambda knee: [],
                       describe(PLACEMENT))
