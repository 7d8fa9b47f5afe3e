"""Cross-validation as text and tables: the hold-outs' errors beside what the calibration expects
and beside the twins', and candidate calibrations judged side by side (mm, deg)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from kneenlp.base.conventions import coordinate_columns
from kneenlp.validation.crossval import (
    ROTATION_TARGET,
    SPREAD_MINIMA,
    TRANSLATION_TARGET,
    HeldOut,
    Judgement,
    judged_best,
    tied,
)


def judgement_lines(judgements: list[Judgement]) -> list[str]:
    """The judgements as a table: fitted RMS beside the held-out error, base and each candidate."""
    holds = list(judgements[0].held_out)
    lines = [f"Judged by what it predicts: fitted RMS (all trials; deg, deg, mm, mm, mm) beside the held-out "
             f"error (RMS over {ROTATION_TARGET:g} deg or {TRANSLATION_TARGET:g} mm, the larger; <= 1 meets the "
             "target) of each hold-out",
             f"    {'calibration':40s} {'free':>4}  {'fitted RMS':>29}  {'mean':>5} {'+-':>5} {'met':>4}  " + " ".join(
                 f"{h[:10]:>10}" for h in holds)]
    for j in judgements:
        fitted = " ".join(f"{v:5.2f}" for v in j.fitted.values())
        cells = " ".join(f"{j.held_out[h]:10.2f}" + ("" if j.converged[h][0] == j.converged[h][1] else "!")
                         for h in holds)
        lines.append(f"    {j.name[:40]:40s} {j.free:4d}  {fitted:>29}  {j.mean:5.2f} {j.margin:5.2f} "
                     f"{j.met:2d}/{len(holds)}  {cells}")
    lines.append("    (+-: the mean spread of the held-out error over each search's lowest minima; a difference "
                 "within it is a tie)")
    lines += [f"    held out, {j.name} ties with the base ({judgements[0].mean:.2f} -> {j.mean:.2f}, within "
              f"{max(judgements[0].margin, j.margin):.2f})" for j in tied(judgements)]
    best = judged_best(judgements)
    lines.append("    ! a held-out trial without equilibrium (the candidate is not recommended)"
                 if any("!" in x for x in lines) else "")
    lines.append(f"    held out, {best.name} lowers the error {judgements[0].mean:.2f} -> {best.mean:.2f} (met "
                 f"{judgements[0].met} -> {best.met} of {len(holds)}): recommended (the held-out error is the judge; "
                 "the tests above rank the candidates)" if best else
                 "    held out, no candidate lowers the error: none is recommended, whatever it does to the fit")
    return [x for x in lines if x]


def table(results: list[HeldOut]) -> pd.DataFrame:
    """One row per hold-out: trial counts, the calibration's RMS on its own trials and the
    held-out RMS per coordinate (columns ``fit_rms_<coordinate>``, ``rms_<coordinate>``: mm, deg)."""
    return pd.DataFrame([r.row() for r in results])


def _number(value: float, spec: str) -> str:
    """``value`` formatted, or "n.d." (not determined: a calibration on too few trials to estimate
    its misfit) right-aligned in the same width."""
    text = format(value, spec)
    return text if np.isfinite(value) else "n.d.".rjust(len(text))


def report(results: list[HeldOut]) -> str:
    """The hold-outs as a text table (mm, deg): each error and, in brackets, the calibration's
    expected error (module docstring); with twins, a second table of each error beside the twins'."""
    cols = coordinate_columns()
    head = "  ".join(f"{c.rsplit('_', 1)[0].replace('_translation', '').replace('_rotation', ''):>13}"
                     for c in cols)
    units = "  ".join(f"{c.rsplit('_', 1)[1]:>13}" for c in cols)
    width = max(12, *(len(r.name) for r in results))

    def rows(second, p):
        for r in results:
            cells = "  ".join(f"{v:5.2f} ({_number(e, '5.2f')})" for v, e in zip(r.rms().values(),
                                                                                  second(r).values(), strict=True))
            n = f"{int(r.prediction.converged.sum())}/{int(r.held.sum())}"
            yield f"{r.name:<{width}}  {n:>6}  {cells}  {_number(p(r), '7.2g')}"

    header = [f"{'held out':<{width}}  trials  {head}  {'p':>7}", f"{'':<{width}}          {units}"]
    lines = ["Held-out prediction: RMS of measured minus predicted on trials the calibration did not see",
             "(in brackets: what the calibration expects it to be, its noise and its parameters' uncertainty;",
             " p: how likely errors this large are if that expectation is right)",
             *header, *rows(HeldOut.expected_rms, HeldOut.p_value)]
    spread = [r for r in results if r.at_minima]
    if spread:
        lines += ["", f"Held-out error (normalised, 1 = on target) at the global search's {SPREAD_MINIMA} lowest "
                  "minima, and their spread (a difference smaller than it is a tie):",
                  *(f"  {r.name:<{width}}  {' / '.join(f'{v:.3f}' for v in r.at_minima)}  spread "
                    f"{_number(r.spread(), '.3f')}" for r in spread)]
    taught = [r for r in results if r.taught]
    if taught:
        lines += ["", "What the held-out trials alone teach the calibration: the parameters whose move, when they",
                  "join it, removes most of their squared error (linearised; display units):",
                  *(line for r in taught for line in [f"  {r.name}:", *(
                      f"    {x.text(r.calibration.fit.problem.model)}" for x in r.taught)])]
    twins = max((len(r.reference) for r in results), default=0)
    if twins:
        lines += ["", "The same errors beside, in brackets, those of the same hold-out on the experiment's twin "
                  f"({twins} noise draw{'s' if twins > 1 else ''}):",
                  "the calibrated knee's own predictions of every trial plus noise at the calibration's level, i.e.",
                  "the error of a model that is exactly right, calibrated the same way (p: how likely errors this",
                  "large are for it)",
                  *header, *rows(HeldOut.reference_rms, HeldOut.p_reference), *twin_verdict(results)]
    return "\n".join(lines)


def twin_verdict(results: list[HeldOut]) -> list[str]:
    """How many hold-outs meet the targets here and on each twin: the second is what these trials
    allow a model that is exactly right, at the calibration's misfit (nothing when the twins do not
    hold every hold-out the same number of times)."""
    draws = {len(r.reference) for r in results}
    if len(draws) != 1 or not draws.pop():
        return []
    per_draw = [sum(v <= 1 for v in column) for column in zip(*(r.reference_normalised() for r in results),
                                                               strict=True)]
    met = sum(r.normalised() <= 1 for r in results)
    return [f"Within {TRANSLATION_TARGET:g} mm and {ROTATION_TARGET:g} deg: {met} of {len(results)} hold-outs here; on "
            f"the twins {min(per_draw)}-{max(per_draw)} (median {np.median(per_draw):g}; per draw "
            f"{', '.join(map(str, per_draw))}):", "what these trials allow a model that is exactly right"]
