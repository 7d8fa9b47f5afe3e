"""Measurement-noise models for simulated laxity data (user units: mm and deg).

``uniform:b`` adds independent uniform noise on ``[-b, b]`` mm / deg to every coordinate (the
paper uses b = 0.5; standard deviation ``b / sqrt(3)``); ``gaussian:s`` adds normal noise with
standard deviation ``s``; ``none`` adds nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kneenlp.base.errors import InputError

KINDS = ("none", "uniform", "gaussian")


@dataclass(frozen=True)
class NoiseModel:
    """A noise distribution in user units (mm for translations, deg for rotations)."""

    kind: str = "none"
    level: float = 0.0  # half-width b (uniform) or standard deviation (gaussian)

    @classmethod
    def parse(cls, spec: str | NoiseModel | None) -> NoiseModel:
        """Parse ``"uniform:0.5"``, ``"gaussian:0.3"`` or ``"none"``."""
        if isinstance(spec, NoiseModel):
            return spec
        if spec is None or spec == "none":
            return cls()
        kind, _, value = str(spec).partition(":")
        if kind not in KINDS[1:]:
            raise InputError(f"unknown noise kind {kind!r}; known: uniform:B, gaussian:SIGMA, none",
                             field="noise")
        try:
            level = float(value)
        except ValueError:
            raise InputError(f"expected a number after '{kind}:', got {value!r}", field="noise") from None
        if not np.isfinite(level) or level < 0:
            raise InputError(f"level must be finite and >= 0, got {value}", field="noise")
        return cls(kind, level)

    @property
    def std(self) -> float:
        """Standard deviation (mm or deg)."""
        if self.kind == "uniform":
            return self.level / np.sqrt(3.0)
        return self.level if self.kind == "gaussian" else 0.0

    @property
    def bound(self) -> float | None:
        """Largest possible absolute error (uniform noise), else ``None``."""
        return self.level if self.kind == "uniform" else None

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        """Draw noise of ``shape`` (user units)."""
        if self.kind == "uniform":
            return rng.uniform(-self.level, self.level, size=shape)
        if self.kind == "gaussian":
            return rng.normal(0.0, self.level, size=shape)
        return np.zeros(shape)

    def __str__(self) -> str:
        return "none" if self.kind == "none" else f"{self.kind}:{self.level:g}"
