"""The oblique popliteal ligament (OPL), ``[oblique_popliteal]`` in a knee file
(:mod:`kneenlp.model.placed_bundle`).

From the posteromedial tibial condyle superolaterally to the posterior face of the lateral femoral
condyle (Wu et al. 2017: 39.5 mm long; sectioning it added 8.4 deg of external rotation under
18 N m; Osti et al. 2013: 45.6 +- 4.7 mm).  Placed from the PCL (an estimate from that anatomy): its
femoral end 24 mm posterior, 5 mm proximal and 24 mm lateral of the PCL's femoral attachment (the
lateral condyle's posterior face at the flexion axis), its tibial end 6 mm posterior, 2 mm proximal
and 18 mm medial of the PCL's tibial one; 44 mm long in the default knee.  Stiffness log-normal,
median 1000 N per unit strain, sd 0.6 of its log (the capsule's halves: 1800-2100 N in the FE knee);
reference strain 0 +- 5 % (taut in extension, which it resists).  Declared only.
"""

from __future__ import annotations

from kneenlp.model.placed_bundle import PlacedTable, Placement, declared, describe, reader
from kneenlp.model.structures import StructureTable

PLACEMENT = Placement("oblique_popliteal", "oblique popliteal ligament (posteromedial tibia to the lateral condyle)",
                      "PCL", (-24.0, 5.0, 24.0), (-6.0, 2.0, -18.0), (1000.0, 0.6), (0.0, 0.05))

TABLE = StructureTable("oblique_popliteal", PlacedTable, reader(PLACEMENT), declared(PLACEMENT), lambda knee: [],
                       describe(PLACEMENT))
