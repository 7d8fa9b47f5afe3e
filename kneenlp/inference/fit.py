"""The result of an identification: estimates, uncertainty, residuals, diagnostics."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from kneenlp.conventions import COORDINATE_UNITS, COORDINATES, coordinate_columns
from kneenlp.experiment.measured import MeasuredData
from kneenlp.model.kneemodel import KneeModel


@dataclass
class Fit:
    """Identified parameters of a knee from measured laxity data.

    Values are SI inside (``params``, ``stderr``: N per unit strain, fractions, N/m^3); the
    report, tables and JSON use the display units (N, %, GN/m^3).  ``q_pred`` are the model's
    poses at the estimate (SI), ``residuals`` the model minus measured coordinates (mm, deg).
    """

    model: KneeModel
    data: MeasuredData
    method: str
    free: list[str]
    params: dict[str, float]
    theta: np.ndarray  # full parameter vector (SI) at the estimate
    objective: float
    status: str
    success: bool
    iterations: int
    seconds: float
    max_residual: float  # largest equilibrium residual at the solution (N or N m)
    q_pred: np.ndarray  # (T, 5) SI
    sensitivity: np.ndarray  # (5T, n_free): d q_user / d p (SI parameter units)
    weights: np.ndarray  # (T, 5)
    noise_variance: np.ndarray  # (T, 5), mm^2 / deg^2
    noise_source: str  # "given" or "estimated"
    start: dict[str, float] = field(default_factory=dict)
    build_seconds: float = 0.0
    evaluations: int = 0
    message: str = ""
    solver: str = "ipopt"
    extra: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ derived
    @property
    def predicted_user(self) -> np.ndarray:
        """The model's measured coordinates (T x 5, mm and deg), including any registration bias."""
        from kneenlp.conventions import coords_to_user

        return coords_to_user(self.q_pred) + self.model.bias_user(self.theta)

    @property
    def residuals(self) -> np.ndarray:
        """Model minus measured coordinates (T x 5, mm and deg)."""
        return self.predicted_user - self.data.q_user

    @property
    def scales(self) -> np.ndarray:
        return np.array([self.model.parameter_info[self.model.index(n)].scale for n in self.free])

    def _svd(self):
        s_scaled = self.sensitivity * self.scales  # columns per unit of scaled parameter
        w = np.sqrt(self.weights.ravel())[:, None]
        return np.linalg.svd(w * s_scaled, full_matrices=True)

    @property
    def rank(self) -> int:
        """Numerical rank of the (weighted, scaled) sensitivity matrix: how many parameter
        directions the data determine (relative singular-value threshold 1e-6)."""
        _, sv, _ = self._svd()
        return int(np.sum(sv > 1e-6 * sv.max())) if sv.size and sv.max() > 0 else 0

    @property
    def identifiable(self) -> bool:
        return self.rank == len(self.free)

    def unidentifiable_directions(self) -> list[dict[str, float]]:
        """Parameter combinations (scaled units) the data cannot determine."""
        vt = self._svd()[2]
        dirs = []
        for i in range(self.rank, len(self.free)):
            v = vt[i]
            dirs.append({n: float(c) for n, c in zip(self.free, v, strict=True) if abs(c) > 0.05})
        return dirs

    @property
    def covariance(self) -> np.ndarray:
        """Gauss-Newton (linearised) covariance of the free parameters (SI units).

        Sandwich form ``A^-1 S' W Sigma W S A^-1`` with ``A = S' W S`` (reduces to
        ``sigma^2 (S'S)^-1`` for an unweighted fit with equal noise).  Directions the data do not
        determine get infinite variance.
        """
        s = self.sensitivity
        w = self.weights.ravel()
        sig = self.noise_variance.ravel()
        a = s.T @ (w[:, None] * s)
        b = s.T @ ((w * sig * w)[:, None] * s)
        # pseudo-inverse in scaled units, with the rank cut of `rank`
        d = self.scales
        a_s = a * np.outer(d, d)
        u, sv, vt = np.linalg.svd(a_s)
        keep = sv > (1e-12 * sv.max() if sv.size else 0)
        keep[self.rank:] = False
        inv = (vt[keep].T / sv[keep]) @ u[:, keep].T
        cov_s = inv @ (b * np.outer(d, d)) @ inv.T
        cov = cov_s * np.outer(d, d)
        if not self.identifiable:
            for direction in self.unidentifiable_directions():
                for n in direction:
                    i = self.free.index(n)
                    cov[i, :] = cov[:, i] = np.nan
                    cov[i, i] = np.inf
        return cov

    @property
    def stderr(self) -> dict[str, float]:
        """Standard errors (SI) of the free parameters."""
        return {n: float(np.sqrt(v)) for n, v in zip(self.free, np.diag(self.covariance), strict=True)}

    @property
    def rms(self) -> float:
        """RMS of all coordinate residuals (mm and deg together)."""
        return float(np.sqrt(np.mean(self.residuals**2)))

    # ------------------------------------------------------------------ presentation
    def _info(self, name):
        return self.model.parameter_info[self.model.index(name)]

    def params_user(self) -> dict[str, float]:
        return {n: self.params[n] * self._info(n).to_user for n in self.free}

    def stderr_user(self) -> dict[str, float]:
        return {n: v * self._info(n).to_user for n, v in self.stderr.items()}

    def table(self) -> pd.DataFrame:
        """Per trial: measured and predicted coordinates and residuals (mm, deg)."""
        df = pd.DataFrame({"trial": [t.id for t in self.data.trials]})
        pred = self.predicted_user
        for j, col in enumerate(coordinate_columns()):
            df[f"measured_{col}"] = self.data.q_user[:, j]
            df[f"predicted_{col}"] = pred[:, j]
            df[f"residual_{col}"] = pred[:, j] - self.data.q_user[:, j]
        return df

    def summary(self) -> dict:
        return {
            "method": self.method,
            "solver": self.solver,
            "status": self.status,
            "success": self.success,
            "params": {n: self.params[n] for n in self.free},
            "stderr": self.stderr,
            "params_display": self.params_user(),
            "stderr_display": self.stderr_user(),
            "units_display": {n: self._info(n).unit for n in self.free},
            "objective": self.objective,
            "rms": self.rms,
            "iterations": self.iterations,
            "evaluations": self.evaluations,
            "seconds": self.seconds,
            "build_seconds": self.build_seconds,
            "max_residual": self.max_residual,
            "rank": self.rank,
            "identifiable": self.identifiable,
            "unidentifiable_directions": self.unidentifiable_directions(),
            "noise_variance_source": self.noise_source,
            "trials": len(self.data),
            "data": self.data.source,
            "start": self.start,
            "message": self.message,
        }

    def to_json(self) -> str:
        from kneenlp.io.serialize import dumps

        return dumps(self.summary())

    def report(self) -> str:
        """lmfit-like text report (display units: N per unit strain, %, GN/m^3; mm and deg)."""
        lines = [
            f"[[Fit]] {self.method} ({self.solver}) on {self.data.source or 'data'}",
            f"    status          = {self.status} ({'success' if self.success else 'FAILED'})",
            f"    trials          = {len(self.data)}  (observations {5 * len(self.data)}, "
            f"free parameters {len(self.free)})",
            f"    objective       = {self.objective:.6g}  (sum of squared residuals, mm^2 + deg^2)",
            f"    RMS residual    = {self.rms:.4g} (mm, deg)",
            f"    iterations      = {self.iterations}   evaluations = {self.evaluations}",
            f"    time            = {self.seconds:.3f} s (build {self.build_seconds:.3f} s)",
            f"    max equilibrium residual = {self.max_residual:.2e} (N, N m)",
            f"    rank            = {self.rank} of {len(self.free)}"
            + ("" if self.identifiable else "  ** NOT ALL PARAMETERS IDENTIFIABLE **"),
            f"    noise variance  = {self.noise_source}",
            "[[Parameters]]",
        ]
        pu, su = self.params_user(), self.stderr_user()
        for n in self.free:
            unit = self._info(n).unit
            se = su[n]
            rel = f"({100 * se / abs(pu[n]):.2f}%)" if np.isfinite(se) and pu[n] != 0 else ""
            se_txt = f"+/- {se:.4g} {rel}" if np.isfinite(se) else "+/- (not identifiable)"
            start = self.start.get(n)
            init = f"(init = {start * self._info(n).to_user:.6g})" if start is not None else ""
            lines.append(f"    {n:18s} = {pu[n]:12.6g} {unit:7s} {se_txt} {init}")
        for d in self.unidentifiable_directions():
            lines.append("    unidentified direction: " + ", ".join(f"{v:+.2f} {k}" for k, v in d.items()))
        lines.append("[[Residuals]] largest |model - measured| per coordinate")
        res = self.residuals
        for j, (c, u) in enumerate(zip(COORDINATES, COORDINATE_UNITS, strict=True)):
            i = int(np.argmax(np.abs(res[:, j])))
            lines.append(f"    {c:22s} {res[i, j]:+8.3f} {u}  ({self.data.trials[i].id})")
        if self.message:
            lines.append(f"[[Message]] {self.message}")
        return "\n".join(lines)
