"""Benchmark of ``kneenlp diagnose``: false alarms, detection, naming, attachments, noise, speed.

Generates its own datasets on the synthetic knee (``--knee`` for another) and diagnoses each:

* ``clean``: no effect, declared noise (false-alarm rate: any outcome other than ``adequate``);
* ``hidden``: one library effect at ``factor`` times its detection limit for the protocol (the
  simulated limit, :func:`~kneenlp.adequacy.detection.simulated_limits`; flagged, named = the
  verdict's named candidate frees the moved parameter, e.g. ``registration`` or
  ``registration_anterior_translation`` for an anterior bias; top-1 = first of the ranking;
  recommendation correct / wrong; truth among the rivals of an ambiguous verdict);
* ``attachment``: one ligament attachment moved 3-5 mm in a random direction (ranked first,
  refitted position error in mm: in 3D, and across the direction the refit determines least,
  which is close to the ligament's line);
* ``noise``: declared uniform:0.5, true uniform:1.0 (named ``noise_larger``).

Protocols: Sets 3 and 4 and a protocol designed for the knee (``designed``, 16 load cases,
A-criterion, written once into the output directory).  Every case is one line of
``<out>/cases.jsonl`` (resumable: cases already there are skipped); the summary is printed from
all lines at the end, so counts can grow over several runs.

    python benchmarks/bench_adequacy.py --clean 70 --hidden 2 --attachment 10 --noise 5 --out bench-adequacy
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import kneenlp
import kneenlp.base.errors
from kneenlp.adequacy.basefit import base_fit
from kneenlp.adequacy.candidates import base_projection, effect_sensitivity
from kneenlp.adequacy.detection import DetectionTest, detection_limits, noncentrality_needed, simulated_limits
from kneenlp.adequacy.diagnosis import along_the_ligament, diagnose
from kneenlp.adequacy.verdict import ALPHA
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.model.ligament import SHIFT_AXES

NOISE = "uniform:0.5"
#: Hidden effects: (effect, parameter, sign of the change from its neutral or the knee's value).
HIDDEN = [("posterior_capsule", "posterior_capsule.k", 1), ("meniscus", "meniscus.k", 1),
          ("flexion_offset", "flexion_offset.delta", 1), ("contact_modulus", "contact.modulus", -1),
          ("lin_strain", "ACL.lin_strain", 1), ("registration", "registration.anterior_translation", 1),
          ("ALL", "ALL.k", 1), ("LCL_femoral_attachment", "LCL.femur_anterior", 1),
          ("neutral_zone", "neutral_zone.anterior_translation", 1), ("popliteus", "popliteus.k", 1),
          ("oblique_popliteal", "oblique_popliteal.k", 1), ("meniscal_rim", "meniscal_rim.k", 1)]


def hidden_effects(knee) -> list[tuple[str, str, int]]:
    """The :data:`HIDDEN` effects that are candidates of ``knee`` (the default knee's menisci are part
    of its base model; ``ALL`` is the synthetic knee's; ``popliteus``, ``oblique_popliteal`` and
    ``meniscal_rim`` a knee file's that declares their table with ``candidate = true``)."""
    known = {e.name for e in KneeModel.of(knee).effects}
    return [h for h in HIDDEN if h[0] in known]


def protocol_for(name: str, knee, out: Path):
    """A packaged protocol, or ``designed``: an A-optimal 16-case protocol for ``knee``."""
    from kneenlp.experiment.protocol import Protocol

    if name != "designed":
        return Protocol.load(name)
    path = out / "designed.toml"
    if not path.exists():
        from kneenlp.design.optimal import candidate_pool, default_flexions, design, write_protocol

        write_protocol(design(knee, 16, "A", pool=candidate_pool(default_flexions(knee)), robust=1, seed=0), path)
    return Protocol.load(path)


def limits_for(knee, protocol, out: Path) -> dict[str, float]:
    """Detection limit (SI) of each benchmark parameter on ``protocol``, at the knee's own values
    (a noise-free fit), at the verdict's strictest Holm level: simulated (exact noncentrality, in
    the direction the benchmark moves it), with the linearised one alongside (``<par>:linear``)."""
    path = out / f"limits_{protocol.name}.json"
    if path.exists():
        return json.loads(path.read_text())
    data = out / f"truth_{protocol.name}.csv"
    kneenlp.simulate(knee, protocol).measured("none").to_csv(data, index=False)
    fit = base_fit(knee, read_measured(data), NOISE)
    sigma = kneenlp.experiment.noise.NoiseModel.parse(NOISE).std
    level = ALPHA / (len(fit.model.effects) + 1)
    out_limits = {}
    for effect, par, sign in hidden_effects(knee):
        names = list(fit.model.effect(effect).parameters)
        to_si = 1 / fit.model.parameter(par).to_user
        test = DetectionTest(sigma, len(names), level)
        out_limits[f"{par}:linear"] = detection_limits(fit, test, names)[par] * to_si
        out_limits[par] = simulated_limits(fit, test, [par], sign=sign)[par] * to_si
    path.write_text(json.dumps(out_limits, indent=1))
    return out_limits


def run_case(knee, protocol, values: dict, noise: str, seed: int, refit: int, tmp: Path) -> dict:
    """Simulate, fit the base model, diagnose; the numbers the summary needs."""
    path = tmp / "case.csv"
    kneenlp.simulate(knee, protocol, parameters=values).measured(noise, seed).to_csv(path, index=False)
    t0 = time.perf_counter()
    fit = base_fit(knee, read_measured(path), NOISE, seed=seed)
    d = diagnose(fit, NOISE, refit=refit)
    seconds = time.perf_counter() - t0
    rec = d.recommended

    def frees_truth(name: str | None) -> bool:  # the candidate frees every parameter the case moved
        return bool(values) and name is not None and set(values) <= set(fit.model.effect(name).parameters)

    row = {"outcome": d.outcome, "named": d.named.effect if d.named else None,
           "top1": d.ranking[0].effect if d.ranking else None, "recommended": rec.effect if rec else None,
           "rivals": d.decision.rivals, "p_global": d.p_value, "seconds": seconds,
           "base_starts": fit.starts,
           "implied_noise": d.decision.implied_noise.level if d.decision.implied_noise else None}
    row |= {"named_ok": frees_truth(row["named"]), "top1_ok": frees_truth(row["top1"]),
            "recommended_ok": frees_truth(row["recommended"]),
            "among_rivals": any(frees_truth(n) for n in d.decision.rivals)}
    named = d.named  # the refitted position of the named candidate, recommended or ambiguous
    if named is not None and named.effect in d.refits:
        row["estimate"] = {n: d.refits[named.effect].params[n] for n in named.parameters}
        if named.effect.endswith("_attachment"):  # the direction the refit sees least (mm basis)
            lig = named.effect.removesuffix("_attachment").rsplit("_", 1)[0]
            row["weak_direction"] = along_the_ligament(d.refits[named.effect], lig, named.parameters)[3].tolist()
    return row


def shift_noncentrality(knee, protocol, values: dict, seed: int, tmp: Path) -> tuple[float, float]:
    """The linearised noncentrality of a moved attachment's shift ``values`` (SI) in its dataset
    (same simulation and base fit as :func:`run_case`), and the noncentrality its candidate's test
    needs at the verdict's strictest Holm level to flag it in half of repeated experiments: a shift
    below that is below the protocol's detection limit."""
    path = tmp / "case.csv"
    kneenlp.simulate(knee, protocol, parameters=values).measured(NOISE, seed).to_csv(path, index=False)
    fit = base_fit(knee, read_measured(path), NOISE, seed=seed)
    sigma = kneenlp.experiment.noise.NoiseModel.parse(NOISE).std
    proj, _, _ = base_projection(fit)
    moved = proj @ effect_sensitivity(fit, list(values)) @ np.array(list(values.values()))
    needed = noncentrality_needed(len(values), ALPHA / (len(fit.model.effects) + 1))
    return float(moved @ moved / sigma**2), needed


def annotate(rows: list[dict], args, knee, out: Path, log: Path) -> None:
    """Add each moved-attachment case's noncentrality (``lambda``, ``lambda_needed``) where missing,
    and rewrite ``log`` atomically."""
    todo = [r for r in rows if r["kind"] == "attachment" and "lambda" not in r]
    for r in todo:
        protocol = protocol_for(r["protocol"], knee, out)
        r["lambda"], r["lambda_needed"] = shift_noncentrality(knee, protocol, r["values"],
                                                              4000 + int(r["key"].split("|")[-1]), out)
    if todo:
        tmp = log.with_suffix(".tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in rows))
        tmp.replace(log)


def cases(args, knee, out: Path):
    """Every (key, protocol, values, noise, seed, truth) of the requested counts."""
    rng = np.random.default_rng(args.seed)
    for pname in args.protocols.split(","):
        protocol = protocol_for(pname, knee, out)
        for i in range(args.clean):
            yield f"clean|{pname}|{i}", protocol, {}, NOISE, 1000 + i, None
        for i in range(args.noise):
            yield f"noise|{pname}|{i}", protocol, {}, "uniform:1.0", 2000 + i, "noise_larger"
        if args.hidden:
            limits = limits_for(knee, protocol, out)
            theta = KneeModel.of(knee).theta()
            for effect, par, sign in hidden_effects(knee):
                if args.effects and effect not in args.effects.split(","):
                    continue
                for factor in args.factors:
                    for i in range(args.hidden):
                        base = theta[KneeModel.of(knee).index(par)]
                        value = base + sign * factor * limits[par]
                        lo, hi = KneeModel.of(knee).parameter(par).bounds
                        if not lo <= value <= hi or (par == "contact.modulus" and value < 0.2 * base):
                            print(f"skipped: {effect} at {factor:g} detection limits on {pname} is beyond its range")
                            break
                        yield (f"hidden|{pname}|{effect}|{factor:g}|{i}", protocol, {par: value}, NOISE, 3000 + i,
                               effect)
        if pname in ("set3", "set4"):
            for i in range(args.attachment):
                lig = str(rng.choice(KneeModel.of(knee).ligament_names))
                side = str(rng.choice(["femur", "tibia"]))
                direction = rng.normal(size=3)
                shift = direction / np.linalg.norm(direction) * rng.uniform(3e-3, 5e-3)
                values = {f"{lig}.{side}_{a}": float(v) for a, v in zip(SHIFT_AXES, shift, strict=True)}
                word = "femoral" if side == "femur" else "tibial"
                yield f"attachment|{pname}|{i}", protocol, values, NOISE, 4000 + i, f"{lig}_{word}_attachment"


def summarise(rows: list[dict]) -> str:
    lines = []
    for kind in ("clean", "noise", "hidden", "attachment"):
        sel = [r for r in rows if r["kind"] == kind]
        if not sel:
            continue
        groups = sorted({(r["protocol"], r.get("effect", ""), r.get("factor", "")) for r in sel})
        lines.append(f"== {kind} ({len(sel)} datasets)")
        for proto, effect, factor in [*groups, ("ALL", "", "")]:
            g = [r for r in sel if proto == "ALL" or (r["protocol"], r.get("effect", ""), r.get("factor", "")) ==
                 (proto, effect, factor)]
            n = len(g)
            flagged = sum(r["outcome"] != "adequate" for r in g)
            secs = np.array([r["seconds"] for r in g])
            head = f"   {proto:9s} {effect:24s} {factor!s:>4s} n {n:4d}"
            if kind == "clean":
                body = f"false alarms {flagged}/{n} = {100 * flagged / n:5.1f} %"
            elif kind == "noise":
                named = sum(r["outcome"] == "noise_larger" for r in g)
                lv = [r["implied_noise"] for r in g if r["implied_noise"]]
                body = (f"named noise_larger {named}/{n}; implied level {np.mean(lv):.2f}" if lv
                        else f"named noise_larger {named}/{n}")
            else:
                named = sum(r["named_ok"] for r in g)
                top1 = sum(r["top1_ok"] for r in g)
                right = sum(r["recommended_ok"] for r in g)
                wrong = sum(r["recommended"] is not None and not r["recommended_ok"] for r in g)
                rival = sum(r["among_rivals"] and not r["named_ok"] for r in g)
                body = (f"flagged {100 * flagged / n:5.1f} %  named {100 * named / n:5.1f} %  "
                        f"top-1 {100 * top1 / n:5.1f} %  recommended right {right} wrong {wrong}  "
                        f"truth among the rivals {rival}")
                seen = [r for r in g if r.get("lambda", 0.0) >= r.get("lambda_needed", np.inf)]
                if kind == "attachment" and seen:
                    body += (f"  [above the detection limit: {len(seen)}/{n}; of those ranked first "
                             f"{sum(r['top1_ok'] for r in seen)}, named {sum(r['named_ok'] for r in seen)}]")
                if kind == "attachment":
                    for key, what in (("error_mm", "3D"), ("error_across_mm", "across the ligament")):
                        err = [r[key] for r in g if r.get(key) is not None]
                        if err:
                            within = sum(e <= 1.5 for e in err)
                            body += f"  {what} within 1.5 mm {within}/{len(err)} (median {np.median(err):.2f} mm)"
            lines.append(f"{head}  {body}  s/diagnose {secs.mean():.1f} (max {secs.max():.1f})")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--knee", default="synthetic")
    ap.add_argument("--protocols", default="set3,set4,designed")
    ap.add_argument("--clean", type=int, default=70, help="clean datasets per protocol")
    ap.add_argument("--noise", type=int, default=3, help="under-declared-noise datasets per protocol")
    ap.add_argument("--hidden", type=int, default=1, help="datasets per hidden effect, size and protocol")
    ap.add_argument("--factors", type=float, nargs="+", default=[1.0, 2.0, 4.0],
                    help="effect sizes in detection limits")
    ap.add_argument("--effects", default="", help="hidden effects to run (comma-separated; default all)")
    ap.add_argument("--attachment", type=int, default=5, help="moved-attachment datasets per protocol (Sets 3, 4)")
    ap.add_argument("--refit", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench-adequacy")
    ap.add_argument("--summary-only", action="store_true")
    ap.add_argument("--annotate", action="store_true",
                    help="add the noncentrality of each moved attachment (is it above the detection limit?)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "cases.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    done = {r["key"] for r in rows}
    knee = kneenlp.Knee.named(args.knee) if args.knee in ("synthetic", "default") else kneenlp.Knee.load(args.knee)
    if not args.summary_only:
        for key, protocol, values, noise, seed, truth in cases(args, knee, out):
            if key in done:
                continue
            try:
                row = run_case(knee, protocol, values, noise, seed, args.refit, out)
            except kneenlp.base.errors.ConvergenceError as exc:
                print(f"{key}: skipped, the simulation did not converge ({str(exc)[:80]})")
                continue
            kind, pname, *rest = key.split("|")
            row |= {"key": key, "kind": kind, "protocol": pname, "truth": truth, "values": values}
            if kind == "hidden":
                row |= {"effect": rest[0], "factor": rest[1]}
            if kind == "attachment" and row.get("estimate") and row["named_ok"]:
                err = 1e3 * (np.array([row["estimate"].get(n, 0.0) for n in values]) - np.array(list(values.values())))
                u = np.array(row["weak_direction"])
                row["error_mm"] = float(np.linalg.norm(err))
                # what laxity data determine: the position across the direction they see least (close
                # to the ligament's line, along which the reference strain absorbs a shift)
                row["error_across_mm"] = float(np.linalg.norm(err - (err @ u) * u))
            rows.append(row)
            with log.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(f"{key:45s} {row['outcome']:15s} named {row['named']!s:26s} {row['seconds']:.1f} s", flush=True)
    if args.annotate:
        annotate(rows, args, knee, out, log)
    print(summarise(rows))


if __name__ == "__main__":
    main()
