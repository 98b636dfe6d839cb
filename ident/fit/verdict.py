"""The fit's verdict per element: is its gap identified by these windows?

An element's gap is **identified** when all of these hold, and the first that
fails is its one-line ``reason``:

1. the solver converged (its last stage passed IPOPT's or least squares'
   convergence test, within its iteration and time bounds);
2. the gap is **identifiable** from the windows (:func:`ident.fit.core.assess`):
   a torque channel sees it, some window drives the element across its gap
   (drive flank and back flank), and its 95 % interval is no wider than
   ``max(25 %, 0.5 mrad)`` either side;
3. on every channel that carries a fair share of the gap's information
   (:data:`SEEN_SHARE` of the largest channel's), the residual in the
   **transient band** is at the sensor noise there (:mod:`ident.fit.noise`:
   band ratio at most :data:`~ident.fit.noise.BAND_RATIO_MAX`) *or* small
   against the transient the channel recorded (at most :data:`RELATIVE_MAX`
   of its RMS in that band: a model error, not a misplaced impact).  Slow
   misfit (offsets, drift, the rolling load's fluctuation) lies below that
   band and does not count; a local minimum puts wrong phases and amplitudes
   at the natural frequencies, which does;
4. (reported, gate off by default: :data:`WINDOWS_GATE`) the windows
   **agree**: leaving any one window out moves the gap by no more than the
   tolerance of 2. or :data:`Z_WINDOWS` standard deviations (one
   Gauss-Newton step, :func:`ident.fit.uncertainty.window_influence`).

``identifiable`` (2. alone) is kept as it was: a statement about the design
of the experiment (channels and windows), ``identified`` about this fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from ..model.linear import natural_modes
from .noise import BAND_RATIO_MAX, Bands, NoiseSpectrum, band_ratio, bands, noise_from_windows

__all__ = ["BandCheck", "band_check", "verdicts", "SEEN_SHARE", "RELATIVE_MAX",
           "window_residuals"]

#: Largest change of a gap, in standard deviations of the change, when one
#: window is left out (nested estimators: N(0, 1) for windows that agree; 4 keeps
#: the false alarms of 6 elements x 4 windows under 0.2 %).
Z_WINDOWS = 4.0

#: Whether 4. gates the verdict.  Off: the one Gauss-Newton step is a
#: linearisation, and a backlash fit is not linear where a window is the only
#: one that drives an element across its gap (leaving out the one release of
#: a shipped sample moved a right 1.02 mrad gap by 3.7 mrad, "7 standard
#: deviations").  The largest |z| is still reported (``window_z``).
WINDOWS_GATE = False

#: Largest model error a channel may keep in the transient band, as a fraction of the
#: transient it recorded there (RMS over RMS), when its residual is above the noise.
#: Plants' sensors are often far quieter than any model of the driveline is exact:
#: on plant-chain recordings (validation.plantsim) whose gaps the fit got right
#: (within 1-4 %) the motor-side channel kept 0.8-1.4 % of its transient at 29 times
#: its noise, while fits with gaps 11-36 % off kept 4.7-22 %.  A local minimum misplaces
#: the impacts, which costs several per cent; a slow nuisance or a ramp's shape costs
#: about one.
RELATIVE_MAX = 0.03

#: A channel "sees" an element when it carries at least this share of the
#: largest channel's Fisher information about the element's gap.
SEEN_SHARE = 0.2


@dataclass(frozen=True)
class BandCheck:
    """The residual's transient-band ratio per channel (:mod:`ident.fit.noise`).

    Attributes
    ----------
    bands : Bands
    ratio : mapping of str to float
        Element id of the channel -> residual power in the transient band over
        the noise's power there (1 for white noise).
    dof : mapping of str to float
        Frequency bins the ratio is over.
    noise_sigma : mapping of str to float
        White-noise standard deviation the noise band's level stands for, N*m
        (reduced).
    noise_source : str
        ``recording`` or ``windows`` (:class:`~ident.fit.noise.NoiseSpectrum`).
    relative : mapping of str to float
        The residual's RMS in the transient band over the data's there (the
        model error as a fraction of the transient the channel recorded).
    """

    bands: Bands
    ratio: Mapping[str, float]
    dof: Mapping[str, float]
    noise_sigma: Mapping[str, float]
    noise_source: str
    relative: Mapping[str, float] = field(default_factory=dict)

    def at_noise(self, channel: str) -> bool:
        """The channel's transient-band residual is at the sensor noise there."""
        v = self.ratio.get(channel, math.nan)
        return bool(math.isfinite(v) and v <= BAND_RATIO_MAX)

    def passes(self, channel: str) -> bool:
        """At the noise, or a model error small against the transient (:data:`RELATIVE_MAX`)."""
        r = self.relative.get(channel, math.nan)
        return self.at_noise(channel) or bool(math.isfinite(r) and r <= RELATIVE_MAX)

    @property
    def all_pass(self) -> bool:
        return all(self.passes(c) for c in self.ratio)

    @property
    def all_at_noise(self) -> bool:
        return all(self.at_noise(c) for c in self.ratio)


def window_residuals(r: np.ndarray, ny: int, lengths: Sequence[int]) -> list[np.ndarray]:
    """Split a sample-major residual vector into per-window arrays of shape (N_w, ny)."""
    out = []
    a = 0
    for n in lengths:
        out.append(r[a:a + n * ny].reshape(n, ny))
        a += n * ny
    return out


def band_check(problem: Any, residual_windows: Sequence[np.ndarray]) -> BandCheck:
    """Transient-band ratio of every channel's residuals.

    Parameters
    ----------
    problem : Problem
    residual_windows : sequence of ndarray, shape (N_w, ny)
        Weighted residuals per window (channel standard deviations, as the
        fit's residual vector).
    """
    m = problem.model
    dt = problem.dt
    n_min = min(len(w) for w in residual_windows)
    bd = bands(natural_modes(m.mill).frequencies_hz, 1.0 / dt, n_min * dt)
    noise = _noise(problem, bd.noise)
    ratio: dict[str, float] = {}
    dof: dict[str, float] = {}
    sig: dict[str, float] = {}
    rel: dict[str, float] = {}
    for c, eid in enumerate(m.measured):
        level = noise.level(eid, bd.noise)
        res = [w[:, c] * problem.y_scale[c] for w in residual_windows]
        ratio[eid], dof[eid] = band_ratio(res, dt, bd.transient, level)
        sig[eid] = noise.sigma(eid, bd.noise, 1.0 / dt)
        data = [y[:len(w), c] - float(np.mean(y[:len(w), c]))
                for y, w in zip(problem.y, residual_windows)]
        signal, _ = band_ratio(data, dt, bd.transient, level)
        rel[eid] = math.sqrt(ratio[eid] / signal) if signal > 0 else math.nan
    return BandCheck(bands=bd, ratio=ratio, dof=dof, noise_sigma=sig, noise_source=noise.source,
                     relative=rel)


def _noise(problem: Any, band: tuple[float, float]) -> NoiseSpectrum:
    """The recording's noise spectrum the windows carry, else one from the windows."""
    got = problem.windows[0].noise
    if got is not None and all(e in got.psd for e in problem.model.measured):
        return got
    return noise_from_windows(problem.y, problem.model.measured, problem.dt, band)


def verdicts(elements: Mapping[str, Any], *, model: Any, problem: Any, check: BandCheck,
             converged: bool, status: str, information: Mapping[str, np.ndarray] | None,
             moves: Mapping[str, np.ndarray] | None) -> dict[str, Any]:
    """Set ``identified``, ``reason`` and ``seen_by`` of every element (module docstring).

    Parameters
    ----------
    elements : mapping of str to ElementFit
        From the fit's element report (``identifiable`` and its ``reason`` set).
    model : FitModel
    problem : Problem
    check : BandCheck
    converged : bool
    status : str
        The solver's status (for the reason).
    information : mapping of str to ndarray, optional
        Element id -> share of its gap's Fisher information per channel.
    moves : mapping of str to ndarray, optional
        Element id -> array (2, n_windows): change of its gap with each window
        left out, rad, and that change in standard deviations.
    """
    names = _channel_names(model)
    lo, hi = check.bands.transient
    out = {}
    for eid, el in elements.items():
        seen: tuple[str, ...] = ()
        share = None if information is None else information.get(eid)
        if share is not None and float(np.max(share)) > 0:
            seen = tuple(c for c, s in zip(model.measured, share)
                         if s >= SEEN_SHARE * float(np.max(share)))
        reason = ""
        if not converged:
            reason = f"the solver did not converge (status {status})"
        elif not el.identifiable or el.reason:
            reason = el.reason or "not identifiable from these windows"
        else:
            bad = [c for c in seen if not check.passes(c)]
            if bad:
                worst = max(bad, key=lambda c: check.ratio.get(c, math.inf))
                rel = check.relative.get(worst, math.nan)
                reason = (f"the residual of {names[worst]} in the transient band "
                          f"({lo:.0f}-{hi:.0f} Hz) is {check.ratio[worst]:.2f} times the sensor "
                          f"noise there and {100 * rel:.1f} % of the transient (at most "
                          f"{BAND_RATIO_MAX:g} times or {100 * RELATIVE_MAX:g} %): a local "
                          "minimum or an effect the model lacks")
            elif WINDOWS_GATE and moves is not None and eid in moves:
                d, z = moves[eid]
                tol = max(0.25 * abs(el.gap), 5e-4)
                bad = np.isfinite(d) & np.isfinite(z) & (np.abs(d) > tol) & (np.abs(z) > Z_WINDOWS)
                if bad.any():
                    k = int(np.argmax(np.where(bad, np.abs(z), -1.0)))
                    label = problem.windows[k].label or f"window {k}"
                    reason = (f"the windows disagree: leaving out {label} moves the gap by "
                              f"{1e3 * float(d[k]):+.2f} mrad ({abs(float(z[k])):.1f} standard "
                              f"deviations; at most {Z_WINDOWS:g} or {1e3 * tol:.2f} mrad)")
        zmax = math.nan
        dmoves: tuple[float, ...] = ()
        if moves is not None and eid in moves:
            dmoves = tuple(float(v) for v in moves[eid][0])
            if np.any(np.isfinite(moves[eid][1])):
                zmax = float(np.nanmax(np.abs(moves[eid][1])))
        out[eid] = replace(el, identified=not reason, reason=reason,
                           seen_by=tuple(names[c] for c in seen), window_z=zmax,
                           window_moves=dmoves)
    return out


def _channel_names(model: Any) -> dict[str, str]:
    names = {c.element: c.name for c in model.mill.torque_channels()}
    return {e: names.get(e, e) for e in model.measured}
