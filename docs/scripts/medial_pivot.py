"""Is the S192803 translation misfit a pivot in the wrong place?

Two measurements from the calibration:

1. the lateral and anterior translation residuals regressed on the internal rotation (a rotation
   axis shifted by ``a`` moves the tibial origin by ``a`` per radian): the slope and the RMS left;
2. the tibial and femoral origins shifted (6 parameters, linear least squares on the calibrated
   poses, beside the calibration's constant registration of the translations): where the robot's
   translations would be measured from if the bones' origins were registered a few mm off;
3. meniscus springs per compartment (a medial pivot: the medial meniscus held, the lateral one
   mobile), transverse or anterior-posterior only, as user elements, each refitted with the
   calibration's parameters from the calibrated values (as ``benchmarks/bench_real_candidates.py``).

    python docs/scripts/medial_pivot.py
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.calibrate import calibrate
from kneenlp.estimation.solve import reduced_fit
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.model.effects import Meniscus
from kneenlp.model.kinematics import reference_transform
from kneenlp.model.parameters import Parameter
from kneenlp.prediction.predict import rms_by_coordinate


class CompartmentMeniscus(Meniscus):
    """:class:`~kneenlp.model.effects.Meniscus` at one condyle, with its own stiffness (N/mm)
    and the tibial directions it resists (``mask``: X anterior, Y proximal, Z lateral)."""

    def __init__(self, name: str, centre: np.ndarray, rest: np.ndarray, mask: tuple[float, float, float]):
        super().__init__([centre], None, [rest])
        self.name, self.description, self.mask = name, f"{name}: one meniscus's restraint", mask

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"{self.name}.k", "spring", "meniscal spring stiffness", 0.0, 0.0)]

    def wrench(self, pose, values):
        c = pose.to_tibial(self.centres[0])
        f_t = values[f"{self.name}.k"] * ca.DM(list(self.mask)) * (c - ca.DM(self.rest[0]))
        return pose.R @ f_t, pose.R @ ca.cross(c, f_t)


def main() -> None:
    knee = kneenlp.Knee.named("s192803")
    extra = []
    for name, centre, rest in zip(knee.compartments, knee.condyle_centres(), knee.condyle_rest(), strict=True):
        extra += [CompartmentMeniscus(f"meniscus_{name}", centre, rest, (1.0, 0.0, 1.0)),
                  CompartmentMeniscus(f"meniscus_{name}_ap", centre, rest, (1.0, 0.0, 0.0))]
    model = KneeModel(knee, extra_elements=extra)
    data = read_measured(resource("datasets", "s192803_laxity.csv"))
    fit = calibrate(model, data, keep_outliers=True).fit
    loaded = np.array([t.dominant != "none" for t in data.trials])
    base = float(np.sum(fit.residuals**2))
    r = data.q_user - fit.predicted_user  # measured - model, mm and deg

    def rms(res: np.ndarray) -> str:
        return ", ".join(f"{v:.2f}" for v in rms_by_coordinate(res[loaded]).values())

    print(f"calibration: {len(fit.free)} free, sum of squares {base:.1f} (mm^2 + deg^2); loaded RMS "
          f"(varus, internal deg; lateral, anterior, proximal mm) {rms(r)}")
    internal = np.radians(data.q_user[:, 1])
    for j, name in ((2, "lateral"), (3, "anterior")):
        A = np.c_[internal, np.ones_like(internal)]
        coef = np.linalg.lstsq(A, r[:, j], rcond=None)[0]
        left = r[:, j] - A @ coef
        print(f"{name} residual vs internal rotation: slope {coef[0]:+.1f} mm/rad, r = "
              f"{np.corrcoef(internal, r[:, j])[0, 1]:+.2f}, RMS {np.sqrt(np.mean(r[:, j] ** 2)):.2f} -> "
              f"{np.sqrt(np.mean(left ** 2)):.2f} mm")
    # 2. origin shifts: translations = A p with p' = p + R s_t - s_f, A the inverse of [e1 e2 e3]
    rows = []
    for t, q in zip(data.trials, fit.q_pred, strict=True):
        R, _ = reference_transform(t.flexion, q)
        e2 = np.array([np.cos(t.flexion), -np.sin(t.flexion), 0.0])  # rot_z(-flexion) @ rot_x(varus), column 0
        A = np.linalg.inv(np.column_stack([[0.0, 0.0, 1.0], e2, R[:, 1]]))
        rows.append(np.hstack([A @ R, -A, np.eye(3)]))  # mm per mm; the last three: the constant registration
    M, b = np.vstack(rows), r[:, 2:5].ravel()
    shift = np.linalg.lstsq(M, b, rcond=None)[0]
    left = (b - M @ shift).reshape(-1, 3)
    left_rms = ", ".join(f"{v:.2f}" for v in np.sqrt(np.mean(left[loaded] ** 2, axis=0)))
    print(f"origins shifted by {np.round(shift[:3], 2)} mm (tibial frame) and {np.round(shift[3:6], 2)} mm "
          f"(femoral frame): loaded translation RMS {left_rms} mm")
    for effects in (["meniscus"], ["meniscus_medial"], ["meniscus_lateral"], ["meniscus_medial", "meniscus_lateral"],
                    ["meniscus_medial_ap"], ["meniscus_lateral_ap"]):
        t0 = time.perf_counter()
        names = [n for e in effects for n in model.effect(e).free_names() if n not in fit.free]
        problem = IdentificationProblem.from_data(model, data, [*fit.free, *names], with_effects=effects)
        start = fit.params | {n: float(model.theta()[model.index(n)]) for n in names}
        refit = reduced_fit(problem, start, q0=fit.q_pred, max_evaluations=60)
        res = data.q_user - refit.predicted_user
        ss = float(np.sum(res**2))
        springs = ", ".join(f"{n} {refit.params[n] * 1e-3:.2f} N/mm" for n in names)
        print(f"{' + '.join(effects):38s} sum of squares {ss:6.1f} ({100 * (ss / base - 1):+5.1f} %)  loaded RMS "
              f"{rms(res)}  {springs}  {time.perf_counter() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    main()
