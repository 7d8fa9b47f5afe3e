"""Where the S192803 calibration misses the translations, and what does not fix it.

Measurements, each from the default calibration:

1. the laxity per flexion and load pair, measured and calibrated (``Calibration.laxity``);
2. the residuals' structure: their RMS left after removing a mean per flexion, per load direction,
   or both (an additive two-way table), and the anterior-internal coupling at each flexion;
3. straight fibres through bone: the length of each fibre inside the tibial or femoral bone mesh of
   the deposit in every calibrated pose (winding number, 49 points per fibre);
4. the superficial MCL wrapped over a cylinder fitted to the medial tibial flare (axis anterior,
   the exact geodesic: tangent lines and a helix), the whole calibration repeated;
5. the tibial origin re-registered: the knee imported with its tibial frame moved, the whole
   calibration repeated (the robot's loads act at, and its translations are read at, that origin);
6. transverse springs about the passive path (menisci that follow the condyles; a central one,
   the tibial eminence), refitted from the calibration;
7. the cruciates' femoral attachments fitted beside the calibration (``calibrate(also_free=...)``);
8. those and the tibial origin (``TibialOrigin``: where the experiment reads its translations).

3-5 need the deposit at ../shared/data/du-s192803 (skipped without it).  ~5 min on 2 cores.
Every calibration here fits all 25 trials (``keep_outliers=True``).  ``TibialOrigin`` moves the
robot's joint loads with the reading point.

    python docs/scripts/translation_misfit.py
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np
import pandas as pd

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.calibrate import calibrate
from kneenlp.estimation.solve import reduced_fit
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.geometry.distance import winding_number
from kneenlp.model.effects import Meniscus
from kneenlp.model.kinematics import reference_transform
from kneenlp.model.ligament import Ligament, slack_length
from kneenlp.model.parameters import Parameter
from kneenlp.prediction.predict import rms_by_coordinate
from kneenlp.solvers.forward import forward_solver

DEPOSIT = Path(__file__).resolve().parents[3] / "shared" / "data" / "du-s192803"
GRID = np.radians(np.arange(-10.0, 101.0, 5.0))  # flexions of the passive path (rad)
MIRROR = np.diag([1.0, 1.0, -1.0])  # the left knee's files into kneenlp's right-knee frames


def summary(data, fit, loaded) -> str:
    r = data.q_user - fit.predicted_user
    rms = ", ".join(f"{v:.2f}" for v in rms_by_coordinate(r[loaded]).values())
    return f"sum of squares {np.sum(r**2):6.1f}; loaded RMS (varus, internal deg; lateral, anterior, proximal mm) {rms}"


# ----------------------------------------------------------------------------- 4. wrapping
def wrapped_path(A, S, centre, radius: float, sense: float):
    """Shortest path from ``A`` to ``S`` (tibial frame, m) around a cylinder with its axis along X
    through ``centre``, passing on side ``sense``: its length and the point where it leaves the
    cylinder towards ``A`` (``S`` itself where the straight line clears the cylinder)."""
    p, s = A[1:] - centre[1:], S[1:] - centre[1:]
    rp, rs = ca.norm_2(p), ca.norm_2(s)
    theta = ca.atan2(p[0] * s[1] - p[1] * s[0], p[0] * s[0] + p[1] * s[1])
    ap, as_ = ca.acos(radius / rp), ca.acos(radius / rs)
    arc = sense * theta - ap - as_  # the angle wrapped (rad); > 0: the line would cut the cylinder
    tp = ca.sqrt(rp**2 - radius**2)
    plane = tp + ca.sqrt(rs**2 - radius**2) + radius * arc
    dx = S[0] - A[0]
    beta = ca.atan2(p[1], p[0]) + sense * ap
    leave = ca.vertcat(A[0] + dx * tp / plane, centre[1] + radius * ca.cos(beta), centre[2] + radius * ca.sin(beta))
    on = ca.logic_and(arc > 0, ca.logic_and(rp > radius, rs > radius))
    return ca.if_else(on, ca.sqrt(plane**2 + dx**2), ca.norm_2(A - S)), ca.if_else(on, leave, S)


class WrappedGroup(Ligament):
    """A bundle group whose fibres wrap over the cylinder; the tibia feels the tension along the
    free segment, at the point it leaves the cylinder (the rest acts within the tibia)."""

    def __init__(self, base: Ligament, centre: np.ndarray, radius: float, sense: float):
        super().__init__(base.name, base.bundles, law=base.law, reference=base.reference)
        self.centre, self.radius, self.sense = ca.DM(centre), radius, sense

    def _bundle_terms(self, pose, values):
        scale, offset = values[f"{self.name}.k_scale"], values[f"{self.name}.ref_strain_offset"]
        R_ref, p_ref = ca.DM(self.reference[0]), ca.DM(self.reference[1])
        for b in self.bundles:
            femur, tibia = ca.DM(b.femur), ca.DM(b.tibia)
            reference = wrapped_path(R_ref.T @ (femur - p_ref), tibia, self.centre, self.radius, self.sense)[0]
            length, leave = wrapped_path(pose.R.T @ (femur - pose.p), tibia, self.centre, self.radius, self.sense)
            arm = pose.R @ leave
            u = femur - (pose.p + arm)
            strain = length / slack_length(reference, b.ref_strain + offset) - 1
            yield arm, u / ca.norm_2(u), strain, self.law.tension(strain, scale * b.stiffness, b.lin_strain)


def bones():
    """The deposit's femoral and tibial bone surfaces in kneenlp's femoral and tibial frames (m),
    simplified to 5000 faces each (the winding numbers below cost points x faces)."""
    import trimesh
    from fast_simplification import simplify

    from kneenlp.io.abaqus import read_mesh
    from kneenlp.io.import_abaqus import read_abaqus_knee

    fe = read_abaqus_knee(DEPOSIT)
    out = []
    for (rot, origin), name in ((fe.femur_frame, "BONE1-FEMUR"), (fe.tibia_frame, "BONE2-TIBFIB")):
        mesh = read_mesh(next((DEPOSIT / "geometry").glob(f"{name}*.inp")))
        faces = np.vstack(mesh.cells["triangle"]).astype(np.int64)
        vertices, faces = simplify(np.asarray(mesh.points, np.float64), faces, target_count=5000)
        tri = trimesh.Trimesh((vertices - origin) @ rot.T @ MIRROR * 1e-3, faces, process=True)
        out.append(tri)
    return out


def fibres_in_bone(knee, data, fit, femur, tibia) -> None:
    s = np.linspace(0.02, 0.98, 49)
    fibres = [(group, b) for group, lig in knee.ligaments.items() for b in lig.bundles]
    inside: dict[str, list[float]] = {}
    for t, q in zip(data.trials, fit.q_pred, strict=True):
        R, p = reference_transform(t.flexion, q)
        ends = [(np.asarray(b.femur), R @ np.asarray(b.tibia) + p) for _, b in fibres]
        pts = np.vstack([a + s[:, None] * (z - a) for a, z in ends])  # every fibre's points, femoral frame
        for bone, mesh, local in (("tibia", tibia, (pts - p) @ R), ("femur", femur, pts)):
            frac = (np.abs(winding_number(mesh, local)) > 0.5).reshape(len(fibres), len(s)).mean(axis=1)
            for (group, _), (a, z), f in zip(fibres, ends, frac, strict=True):
                if f > 0:
                    inside.setdefault(f"{group} through the {bone}", []).append(1e3 * np.linalg.norm(z - a) * f)
    for key, mm in sorted(inside.items()):
        print(f"  {key}: {len(mm)} fibre-trials, {min(mm):.0f}-{max(mm):.0f} mm of the fibre inside the bone")


def wrapped_mcl(knee, data, loaded, tibia) -> None:
    v = tibia.vertices
    band = (v[:, 0] > -0.005) & (v[:, 0] < 0.025) & (v[:, 1] < -0.015) & (v[:, 1] > -0.060) & (v[:, 2] < -0.005)
    ys, zs = [], []
    for y in np.arange(-0.058, -0.014, 0.002):  # the medial profile: the most medial bone per level
        level = band & (np.abs(v[:, 1] - y) < 0.001)
        if level.any():
            ys.append(y)
            zs.append(v[level, 2].min())
    ys, zs = np.array(ys), np.array(zs)
    sol = np.linalg.lstsq(np.c_[2 * ys, 2 * zs, np.ones_like(ys)], ys**2 + zs**2, rcond=None)[0]
    centre, radius = np.array([0.0, sol[0], sol[1]]), float(np.sqrt(sol[2] + sol[0] ** 2 + sol[1] ** 2))
    ligaments = dict(knee.ligaments)
    for group in ("MCLa", "MCLm", "MCLp"):  # the path passes medially of the centre (negative Z)
        ligaments[group] = WrappedGroup(knee.ligaments[group], centre, radius, -1.0)
    model = KneeModel(dataclasses.replace(knee, ligaments=ligaments))
    t0 = time.perf_counter()
    fit = calibrate(model, data, keep_outliers=True).fit
    print(f"  cylinder centre Y {1e3 * centre[1]:.1f}, Z {1e3 * centre[2]:.1f} mm, radius {1e3 * radius:.1f} mm: "
          f"{summary(data, fit, loaded)} ({time.perf_counter() - t0:.0f} s)")


# ----------------------------------------------------------------------------- 5. origins
def moved_origin(data, loaded, shifts) -> None:
    import kneenlp.io.import_abaqus as importer

    read = importer.read_abaqus_knee
    for dx, dz in shifts:  # mm along the tibial frame's AP axis and its ML axis (medial for this left knee)
        def moved(folder, dx=dx, dz=dz):
            fe = read(folder)
            rot, origin = fe.tibia_frame
            fe.tibia_frame = (rot, origin + rot.T @ np.array([dx, 0.0, dz]))
            return fe

        importer.read_abaqus_knee = moved
        try:
            with tempfile.TemporaryDirectory() as tmp:
                knee = kneenlp.Knee.load(importer.import_abaqus(DEPOSIT, Path(tmp) / "k", side="left", name="s"))
                fit = calibrate(KneeModel(knee), data, keep_outliers=True).fit
        finally:
            importer.read_abaqus_knee = read
        print(f"  tibial origin {dx:+.0f} mm anterior, {dz:+.0f} mm medial: {summary(data, fit, loaded)}")


# ----------------------------------------------------------------------------- 6. springs
class PathSpring(Meniscus):
    """A transverse spring (N/mm) from a femoral point to where that point sits over the plateau
    on the passive path at the trial's flexion (interpolated on :data:`GRID`)."""

    def __init__(self, name: str, point: np.ndarray, path: np.ndarray, mask: tuple[float, float, float]):
        super().__init__([point], None, [path[0]])
        self.name, self.description, self.path, self.mask = name, f"{name}: spring about the passive path", path, mask

    def parameters(self) -> list[Parameter]:
        return [Parameter(f"{self.name}.k", "spring", "spring stiffness", 0.0, 0.0)]

    def wrench(self, pose, values):
        c = pose.to_tibial(self.centres[0])
        rest = ca.vertcat(*[ca.pw_lin(pose.flexion, ca.DM(GRID), ca.DM(self.path[:, j])) for j in range(3)])
        f_t = values[f"{self.name}.k"] * ca.DM(list(self.mask)) * (c - rest)
        return pose.R @ f_t, pose.R @ ca.cross(c, f_t)


def path_springs(knee, data, loaded, fit) -> None:
    base = KneeModel.of(knee)
    theta = base.theta(fit.params)
    solver = forward_solver(base)
    poses = [reference_transform(float(f), solver.cold_start(float(f), theta)) for f in GRID]
    medial, lateral = (np.asarray(c) for c in knee.condyle_centres())
    points = {"medial": medial, "lateral": lateral, "centre": 0.5 * (medial + lateral)}
    springs = [PathSpring(f"spring_{n}", c, np.array([R.T @ (c - p) for R, p in poses]), (1.0, 0.0, 1.0))
               for n, c in points.items()]
    springs.append(PathSpring("spring_centre_ml", points["centre"], springs[2].path, (0.0, 0.0, 1.0)))
    model = KneeModel(knee, extra_elements=springs)
    for effects in (["spring_medial"], ["spring_lateral"], ["spring_centre"], ["spring_centre_ml"]):
        names = [n for e in effects for n in model.effect(e).free_names()]
        problem = IdentificationProblem.from_data(model, data, [*fit.free, *names], with_effects=effects)
        refit = reduced_fit(problem, fit.params | {n: 0.0 for n in names}, q0=fit.q_pred, max_evaluations=80)
        k = ", ".join(f"{refit.params[n] * 1e-3:.2f} N/mm" for n in names)
        print(f"  {' + '.join(effects):18s} {k:12s} {summary(data, refit, loaded)}")


def main() -> None:
    pd.set_option("display.width", 160)
    knee = kneenlp.Knee.named("s192803")
    model = KneeModel.of(knee)
    data = read_measured(resource("datasets", "s192803_laxity.csv"))
    loaded = np.array([t.dominant != "none" for t in data.trials])
    cal = calibrate(model, data, keep_outliers=True)
    fit = cal.fit
    print(f"calibration: {len(fit.free)} free, {summary(data, fit, loaded)}")

    print("1. laxity per flexion (mm, deg): the knee's, the model's with the FE values and calibrated")
    lax = cal.before.laxity()[["flexion_deg", "laxity", "unit", "measured"]].assign(
        fe_values=cal.before.laxity()["predicted"], calibrated=cal.laxity()["predicted"])
    print(lax.round(2).to_string(index=False))

    print("2. residual structure (loaded trials; RMS varus, internal deg; lateral, anterior, proximal mm)")
    r = (data.q_user - fit.predicted_user)[loaded]
    trials = [t for t, ok in zip(data.trials, loaded, strict=True) if ok]
    flex = np.round([t.flexion_deg / 30.0 for t in trials]).astype(int)  # the four nominal flexions
    word = np.array([t.dominant for t in trials])
    for label, groups in (("a mean per flexion", [flex]), ("a mean per load direction", [word]),
                          ("both (additive)", [flex, word])):
        X = np.column_stack([g == v for g in groups for v in np.unique(g)]).astype(float)
        left = r - X @ np.linalg.lstsq(X, r, rcond=None)[0]
        print(f"  {label} removed: {', '.join(f'{v:.2f}' for v in np.sqrt(np.mean(left**2, axis=0)))}")
    for f in np.unique(flex):
        i, e = (np.flatnonzero((flex == f) & (word == w))[0] for w in ("internal", "external"))
        knee_, model_ = (d[loaded][i] - d[loaded][e] for d in (data.q_user, fit.predicted_user))
        print(f"  {trials[i].flexion_deg:4.0f} deg: anterior translation per internal rotation (internal minus "
              f"external trial): knee {knee_[3] / np.radians(knee_[1]):5.1f} mm/rad, "
              f"model {model_[3] / np.radians(model_[1]):5.1f}")

    if DEPOSIT.is_dir():
        femur, tibia = bones()
        print("3. straight fibres through bone in the calibrated poses")
        fibres_in_bone(knee, data, fit, femur, tibia)
        print("4. the superficial MCL wrapped over the medial tibial flare, calibrated again")
        wrapped_mcl(knee, data, loaded, tibia)
        print("5. the tibial origin moved, knee imported again and calibrated")
        moved_origin(data, loaded, [(-4.0, 0.0), (0.0, 4.0), (-4.0, 4.0)])
    else:
        print(f"3-5 skipped: no deposit at {DEPOSIT}")
    print("6. transverse springs about the passive path, refitted from the calibration")
    path_springs(knee, data, loaded, fit)
    print("7. the cruciates' femoral attachments fitted beside the calibration (also_free)")
    also = ["PCLal_femoral_attachment", "ACLam_femoral_attachment", "PCLal_bundles"]
    wider = calibrate(model, data, also_free=also, keep_outliers=True)
    moved = ", ".join(f"{n} {1e3 * wider.fit.params[n]:+.1f}" for n in wider.fit.free if ".femur_" in n)
    print(f"  {', '.join(also)}: {summary(data, wider.fit, loaded)}\n  shifts (mm): {moved}")
    lax["attachments"] = wider.laxity()["predicted"]
    print("8. and the tibial origin as a fitted registration (TibialOrigin)")
    both = calibrate(model, data, also_free=["tibial_origin", *also], keep_outliers=True)
    moved = ", ".join(f"{n} {1e3 * both.fit.params[n]:+.1f}" for n in both.fit.free if n.startswith("tibial_origin"))
    print(f"  {summary(data, both.fit, loaded)}\n  shifts (mm): {moved}")
    lax["both"] = both.laxity()["predicted"]
    print(lax[lax["laxity"] == "anterior-posterior"].round(2).to_string(index=False))


if __name__ == "__main__":
    main()
