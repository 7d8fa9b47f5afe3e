"""Pictures of a simulated knee that need no OpenSim: contact pressure maps and a 3-D view
(``scene``: what they show, extracted from a simulation result; ``maps``: 2-D pressure maps;
``render``: the 3-D view).

* :func:`pressure_map`: top view of the tibial cartilage (tibial frame, X anterior up, Z lateral to
  the right) with the contact pressure of each compartment (MPa) and its centre of pressure, one
  panel per trial;
* :func:`knee_view`: the knee at a trial's pose in the femoral frame: femoral articular surface (or
  explicit condyle spheres), tibial cartilage coloured by pressure (MPa) and ligament lines
  coloured by force (N); a static PNG (matplotlib 3-D) and an interactive, self-contained HTML
  file (plotly, the optional extra ``kneenlp[view]``).

Everything is computed in SI from the simulation result (poses from ``model.pose``, pressures from
each contact element's ``pressure``) and drawn in mm, MPa and N.  Figures are matplotlib
:class:`~matplotlib.figure.Figure` objects, never pyplot, so no backend is switched.
"""

from kneenlp.io.views.maps import pressure_map
from kneenlp.io.views.render import knee_view, require_plotly, write_views
from kneenlp.io.views.scene import (
    ContactMap,
    LigamentLine,
    Scene,
    build_scene,
    contact_maps,
    decimate,
    default_view_trials,
    ligament_lines,
    pose,
    solution,
    trial_ids,
)

__all__ = ["ContactMap", "LigamentLine", "Scene", "build_scene", "contact_maps", "decimate", "default_view_trials",
           "knee_view", "ligament_lines", "pose", "pressure_map", "require_plotly", "solution", "trial_ids",
           "write_views"]
