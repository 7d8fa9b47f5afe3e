"""Values of command-line options: argparse types that check each value's type and range before
any work starts, the limits of counts, and a parser whose errors are one-line input errors naming
the option (``--seed: must be >= 0, got -1``).  Documented in docs/inputs.md.
"""

from __future__ import annotations

import argparse
import math
import re

from kneenlp.base.errors import InputError

#: Upper limits of counts (documented in docs/inputs.md): beyond them a run
#: would take days or exhaust memory, which is never what a user meant.
MAX_SAMPLES = 1_000_000
MAX_WORKERS = 512
MAX_STARTS = 1000
MAX_EVALS = 10_000_000
MAX_ROBUST = 100
MAX_CASES = 1000
MAX_SEED = 2**63 - 1


def integer(lo: int, hi: int):
    """An argparse type: an integer in [lo, hi]."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be between {lo} and {hi}, got {value}" if hi < MAX_SEED
                                             else f"must be >= {lo}, got {value}")
        return value
    return parse


def finite(text: str) -> float:
    """An argparse type: a finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def point3(text: str) -> tuple[float, float, float]:
    """An argparse type: three finite numbers separated by commas (``X,Y,Z``)."""
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z (three numbers), got {text!r}")
    return tuple(finite(p.strip()) for p in parts)  # type: ignore[return-value]


def positive(text: str) -> float:
    """An argparse type: a finite number > 0."""
    value = finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def prior_weight(text: str) -> float | str:
    """An argparse type: a misfit variance > 0 (mm^2, deg^2) or ``estimate``."""
    return "estimate" if text.strip() == "estimate" else positive(text)


def fraction(text: str) -> float:
    """An argparse type: a finite number with 0 < value < 1."""
    value = finite(text)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"must be between 0 and 1 (exclusive), got {text!r}")
    return value


def names(text: str) -> list[str]:
    """An argparse type: a comma-separated list of names (at least one, no repeats)."""
    items = [n.strip() for n in text.split(",")]
    if not any(items) or not all(items):
        raise argparse.ArgumentTypeError(f"expected comma-separated names, got {text!r}")
    dup = sorted({n for n in items if items.count(n) > 1})
    if dup:
        raise argparse.ArgumentTypeError(f"{', '.join(dup)} given twice")
    return items


def flexions(text: str) -> tuple[float, ...]:
    """An argparse type: comma-separated flexion angles in [-10, 120] deg (as protocol files)."""
    values = []
    for item in names(text):
        try:
            f = float(item)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected angles in deg, got {item!r}") from None
        if not -10.0 <= f <= 120.0:
            raise argparse.ArgumentTypeError(f"flexion {item} deg outside [-10, 120]")
        values.append(f)
    return tuple(values)


def noise(text: str) -> str:
    """An argparse type: a noise model ``uniform:B``, ``gaussian:SIGMA`` or ``none``."""
    from kneenlp.experiment.noise import NoiseModel

    try:
        NoiseModel.parse(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(exc.message) from None
    return text


def noise_level(text: str) -> str:
    """An argparse type: a noise model with a level above zero (for the commands that judge a
    misfit or a covariance against it; a zero level would divide by zero)."""
    from kneenlp.experiment.noise import NoiseModel

    noise(text)
    if not NoiseModel.parse(text).std > 0:
        raise argparse.ArgumentTypeError(f"needs a noise level above zero (the misfit is judged against it), "
                                         f"got {text!r}; e.g. uniform:0.5")
    return text


def scheduler(text: str) -> str:
    """An argparse type: a Dask scheduler address ``SCHEME://HOST:PORT`` (e.g. tcp://10.0.0.5:8786)."""
    import re

    if not re.fullmatch(r"[a-z]+://[^\s:/]+:\d{1,5}", text):
        raise argparse.ArgumentTypeError(f"expected a scheduler address like tcp://HOST:PORT, got {text!r}")
    return text


def solver(text: str) -> str:
    """An argparse type: a CasADi nlpsol plugin that is installed."""
    import casadi

    if not text or not casadi.has_nlpsol(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not an installed CasADi nlpsol plugin (e.g. ipopt, "
                                         "sqpmethod)")
    return text


SEED = integer(0, MAX_SEED)


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors: a bad option is an :class:`InputError` naming the option."""

    def error(self, message: str):
        m = re.match(r"argument ([^:]+): (.*)", message)
        field, text = (m.group(1).split("/")[-1], m.group(2)) if m else (None, message)
        raise InputError(f"{text} (see '{self.prog} --help')", field=field)
