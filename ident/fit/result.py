"""The frozen result of :func:`ident.fit.fit_gaps` and its cli.md JSON."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

__all__ = ["ElementFit", "SolverReport", "FitResult", "NOISE_RATIO_MAX"]

#: The whole residual's mean square over the white-noise variance (the fourth
#: difference, :func:`ident.fit.uncertainty.noise_floor`) that a right fit of
#: white noise added after decimation stays under (our generator: 0.98-1.05).
#: Informational only since the verdict moved to the transient band
#: (:mod:`ident.fit.verdict`): on plant-like telemetry (anti-alias filtered
#: noise, drifting offsets, a fluctuating load) right fits read 1.1-2.8.
NOISE_RATIO_MAX = 1.2


def _f(x: Any) -> Any:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _band_dict(band: Any) -> dict[str, Any]:
    if band is None:
        return {}
    return {"band_ratio": {k: _f(v) for k, v in band.ratio.items()},
            "band_relative": {k: _f(v) for k, v in band.relative.items()},
            "transient_band_hz": [_f(v) for v in band.bands.transient],
            "noise_band_hz": [_f(v) for v in band.bands.noise],
            "noise_sigma": {k: _f(v) for k, v in band.noise_sigma.items()},
            "noise_source": band.noise_source}


@dataclass(frozen=True)
class ElementFit:
    """What the fit found for one element.

    Attributes
    ----------
    gap : float
        Total gap, rad (reduced); for g2/g3/g4 the family's equivalent gap.
    gap_ci95 : (float, float)
        95 % interval of ``gap``, rad, clipped to ``[0, gap_max]``.
    gap_se : float
        Standard error of ``gap``, rad (``inf`` when the data cannot see it):
        ``hypot(gap_se_noise, gap_se_model)``; ``gap_ci95`` is ``gap`` +- 1.96
        of it, clipped.
    gap_se_noise : float
        The sensor noise's part, rad: the sandwich covariance at the optimum
        (:func:`ident.fit.uncertainty.covariance`).
    gap_se_model : float
        The model error's part, rad (:func:`ident.fit.uncertainty.model_error_se`):
        a floor of the model's own accuracy plus the transient-band misfit left
        above the noise on the channels that see the gap.
    gap_open : float
        Open part of the gap in the drive direction at the start of the first
        window, rad (0 when the element starts loaded).
    gap_open_ci95 : (float, float)
    gap_open_windows : tuple of float
        ``gap_open`` at the start of every window, rad.
    gap_mm : float or None
        ``gap`` as tooth clearance, mm (needs the element's ``radius``).
    params : mapping
        The family's parameters (g1: ``smoothing_final``, rad; g2: ``a1, a2, a3``;
        g3/g4: ``a0, sigma, shift``) with standard errors under ``params_se``.
    identifiable : bool
        False when the channels do not pin the gap down: its interval is wider
        than ``max(25 %, 0.5 mrad)`` either side, the data do not see it, no
        window drives it across its gap, or its series partner is not driven
        across (then its interval is ``[0, gap_max]``).
    gap_open_identifiable : bool
    identified : bool
        The fit's verdict (:mod:`ident.fit.verdict`): identifiable, the solver
        converged, the channels that see it fit (at the noise in the transient
        band, or a small model error there), and its 95 % interval is within
        ``max(10 %, 0.3 mrad)``, the accuracy by which a gap counts as right.
    bounded : bool
        The verdict trusts the gap's interval (the solver converged, the gap is
        identifiable, the channels that see it fit), but the interval is wider
        than the accuracy of an identified gap (:func:`ident.fit.verdict.accuracy`):
        a wear state may be read from the interval, the gap's value is not
        identified.  False when identified.
    reason : str
        Why not, in one line ("" when identified; ``identifiable`` false
        carries its own reason too).
    seen_by : tuple of str
        The torque channels carrying the gap's information.
    window_z : float
        Largest change of the gap when one window is left out, in standard
        deviations of that change (:func:`ident.fit.uncertainty.window_influence`).
    basis : str
        What the verdict rests on, in one line, when identified: the residual
        at the noise, a small model error, or starts that agree
        (:mod:`ident.fit.verdict`).
    window_moves : tuple of float
        Change of the gap when each window is left out, rad (one Gauss-Newton
        step; NaN where the other windows cannot see it).
    """

    gap: float
    gap_ci95: tuple[float, float]
    gap_se: float
    gap_open: float
    gap_open_ci95: tuple[float, float]
    gap_open_windows: tuple[float, ...]
    gap_mm: float | None
    params: Mapping[str, float]
    params_se: Mapping[str, float]
    identifiable: bool
    gap_open_identifiable: bool
    identified: bool = False
    bounded: bool = False
    reason: str = ""
    seen_by: tuple[str, ...] = ()
    window_z: float = math.nan
    window_moves: tuple[float, ...] = ()
    basis: str = ""
    gap_se_noise: float = math.nan
    gap_se_model: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        return {
            "gap": _f(self.gap),
            "gap_ci95": [_f(self.gap_ci95[0]), _f(self.gap_ci95[1])],
            "gap_open": _f(self.gap_open),
            "gap_mm": _f(self.gap_mm),
            "params": {k: _f(v) for k, v in self.params.items()},
            "gap_se": _f(self.gap_se), "gap_se_noise": _f(self.gap_se_noise),
            "gap_se_model": _f(self.gap_se_model),
            "gap_open_ci95": [_f(self.gap_open_ci95[0]), _f(self.gap_open_ci95[1])],
            "gap_open_windows": [_f(v) for v in self.gap_open_windows],
            "params_se": {k: _f(v) for k, v in self.params_se.items()},
            "identifiable": bool(self.identifiable),
            "gap_open_identifiable": bool(self.gap_open_identifiable),
            "identified": bool(self.identified),
            "bounded": bool(self.bounded),
            **({"basis": self.basis} if self.identified else {"reason": self.reason}),
            "seen_by": list(self.seen_by),
            "window_z": _f(self.window_z),
            "window_moves": [_f(v) for v in self.window_moves],
        }


@dataclass(frozen=True)
class SolverReport:
    """How the solver did.

    Attributes
    ----------
    status : str
        IPOPT's return status (collocation) or ``least_squares``' (shooting) of
        the winning start's last stage.
    converged : bool
    iterations : int
        Iterations of the winning start, all stages.
    seconds : float
        Wall time of the whole fit (all starts, the linear baseline and the
        uncertainty), s.
    method : str
    start : int
        Index of the winning start in ``starts``.
    starts : tuple of dict
        Per start and path: start index, path, initial gaps (``gaps``), the gaps
        it ended at (``gaps_end``), final cost, status, iterations, seconds.
    path : str
        How the winner got there: ``continued`` (horizon and smoothing-width
        continuation), ``held`` (the continuation with the gaps held at the
        start, then freed at the final width), ``baseline`` (a continued
        restart from the linear baseline, every gap nearly closed) or ``swap
        A/B`` (a held restart with the gaps of the elements in series A and B
        exchanged).
    stages : tuple of dict
        The winning start's continuation stages.
    build_seconds : float
        Time spent building NLPs / simulators, s.
    nlp : mapping
        Size of the problem.
    """

    status: str
    converged: bool
    iterations: int
    seconds: float
    method: str
    start: int
    starts: tuple = ()
    stages: tuple = ()
    build_seconds: float = 0.0
    nlp: Mapping[str, Any] = field(default_factory=dict)
    path: str = "continued"

    def to_dict(self) -> dict[str, Any]:
        return {"status": self.status, "iterations": int(self.iterations),
                "seconds": _f(self.seconds), "converged": bool(self.converged),
                "method": self.method, "start": int(self.start), "starts": list(self.starts),
                "stages": list(self.stages), "build_seconds": _f(self.build_seconds),
                "nlp": dict(self.nlp), "path": self.path}


@dataclass(frozen=True)
class FitResult:
    """Identified gaps and smoothing parameters of a mill (cli.md ``fit``).

    Attributes
    ----------
    mill : str
    family : str
    elements : mapping of str to ElementFit
        Every element of the mill file.
    nrmse, nrmse_linear : float
        Mean over torque channels of RMS(model - measured) / std(measured)
        over the fitted windows: identified model and linear baseline (all
        gaps closed, its own loads and initial states fitted).
    nrmse_channels, nrmse_linear_channels : mapping
        The same per channel (element id).
    solver : SolverReport
    windows : tuple of dict
        Per window: label, kind, times, fitted load and ``gap_open`` per element.
    noise : mapping
        Residual standard deviation per channel (N*m) and its long-run factor.
    warnings : tuple of str
    noise_ratio : float
        Mean squared residual over the white-noise variance of the fourth
        difference (informational, :data:`NOISE_RATIO_MAX`).
    band : BandCheck or None
        The residual's transient-band ratio per channel (:mod:`ident.fit.verdict`).
    """

    mill: str
    family: str
    elements: Mapping[str, ElementFit]
    nrmse: float
    nrmse_linear: float
    nrmse_channels: Mapping[str, float]
    nrmse_linear_channels: Mapping[str, float]
    solver: SolverReport
    windows: tuple = ()
    noise: Mapping[str, Any] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    noise_ratio: float = math.nan
    band: Any = None

    @property
    def converged(self) -> bool:
        return self.solver.converged

    @property
    def reached_noise_floor(self) -> bool:
        """Whether every channel's residual is down to the sensor noise in the transient band."""
        return bool(self.band is not None and self.band.all_at_noise)

    @property
    def identified(self) -> dict[str, bool]:
        """The verdict per element."""
        return {k: bool(v.identified) for k, v in self.elements.items()}

    def gaps(self) -> dict[str, float]:
        """Identified total gap per element, rad."""
        return {k: v.gap for k, v in self.elements.items()}

    def raise_if_failed(self) -> "FitResult":
        """Return self, or raise :class:`~ident.errors.FitError` when the solver did not converge."""
        if not self.converged:
            from ..errors import FitError

            raise FitError(f"the {self.solver.method} fit did not converge: status "
                           f"{self.solver.status!r} after {self.solver.iterations} iterations; "
                           "its numbers are not an identification.")
        return self

    def to_dict(self) -> dict[str, Any]:
        """The cli.md ``fit`` JSON plus extra keys."""
        return {
            "mill": self.mill,
            "family": self.family,
            "elements": {k: v.to_dict() for k, v in self.elements.items()},
            "metrics": {"nrmse": _f(self.nrmse), "nrmse_linear": _f(self.nrmse_linear),
                        "noise_ratio": _f(self.noise_ratio),
                        "reached_noise_floor": self.reached_noise_floor,
                        **_band_dict(self.band),
                        "nrmse_channels": {k: _f(v) for k, v in self.nrmse_channels.items()},
                        "nrmse_linear_channels": {k: _f(v) for k, v in
                                                  self.nrmse_linear_channels.items()}},
            "solver": self.solver.to_dict(),
            "windows": list(self.windows),
            "noise": dict(self.noise),
            "warnings": list(self.warnings),
        }
