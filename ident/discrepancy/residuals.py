"""Where model and data disagree: residuals by window, transient phase, frequency and load.

The residuals analysed are the fitted model's on windows the fit did not see
(``ident.discrepancy.workflow`` passes held-out residuals), normalised per
channel by the channel's scale (its RMS about each window's mean), so that
numbers compare across channels and read as shares of the signal.

* **time**: per window (which bars and steps), per channel, and per phase of
  the transient: ``impact`` (the load ramp and the first 60 ms after it, where
  gaps close and knees are crossed), ``ring_down`` (until 350 ms after the
  step) and ``steady`` (afterwards: rolling after a bite, idling after a
  release);
* **frequency**: the residual spectrum against the linear baseline's natural
  frequencies (``ident.model.linear``), their 2nd and 3rd harmonics and
  sidebands at twice the roll speed (spindle imbalance), as the share of
  residual power within +-1.5 Hz of each;
* **correlation**: of each window's residual RMS with its load level and step
  size (Pearson r), and of the residual with ``sin``/``cos`` of twice the roll
  angle (share of residual variance explained).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..description import Mill
from ..model.linear import natural_modes
from .windows import Window

__all__ = ["ResidualReport", "analyse_residuals", "PHASES", "residual_spectrum"]

#: Phases of a transient: name -> (start, end) in s after the end of the load ramp.
PHASES = {"impact": (-math.inf, 0.06), "ring_down": (0.06, 0.35), "steady": (0.35, math.inf)}


@dataclass(frozen=True)
class ResidualReport:
    """Summary of normalised residuals (dimensionless: share of each channel's scale).

    Attributes
    ----------
    nrmse : float
        Over every window and channel.
    by_window : dict
        Window label -> nrmse.
    by_channel : dict
        Element id -> nrmse.
    by_phase : dict
        ``impact`` / ``ring_down`` / ``steady`` -> nrmse over samples in that phase.
    bands : dict
        Band label (``"mode 12.0 Hz"``, ``"2x 12.0 Hz"``, ``"12.0 Hz +- 2x roll"``) ->
        share of residual power within it.
    peak_hz : float
        Frequency of the largest residual spectral peak, Hz.
    load_correlation, step_correlation : float
        Pearson r of the per-window residual RMS with the load level and the step size.
    roll_angle_share : float
        Share of residual variance explained by sin/cos of twice the roll angle.
    """

    nrmse: float
    by_window: dict
    by_channel: dict
    by_phase: dict
    bands: dict
    peak_hz: float
    load_correlation: float
    step_correlation: float
    roll_angle_share: float
    spectrum: tuple = field(default=(), repr=False)

    def to_dict(self) -> dict[str, Any]:
        top = sorted(self.bands.items(), key=lambda kv: -kv[1])[:6]
        return {"nrmse": self.nrmse, "by_window": self.by_window, "by_channel": self.by_channel,
                "by_phase": self.by_phase, "bands": dict(top), "peak_hz": self.peak_hz,
                "load_correlation": self.load_correlation,
                "step_correlation": self.step_correlation,
                "roll_angle_share": self.roll_angle_share}


def _phase_masks(w: Window, rise: float) -> dict[str, np.ndarray]:
    s = w.t - (w.t_step + 0.5 * rise)
    return {k: (s >= a) & (s < b) for k, (a, b) in PHASES.items()}


def residual_spectrum(windows: Sequence[Window], residuals: Sequence[np.ndarray],
                      *, pad_s: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Mean power spectrum of normalised residuals over windows and channels.

    Each window is detrended, Hann-tapered and zero-padded to ``pad_s`` seconds.

    Returns
    -------
    freq_hz : ndarray
    power : ndarray
        Same length, arbitrary units (normalised residual squared per bin).
    """
    dt = windows[0].dt
    n = max(int(round(pad_s / dt)), windows[0].n_samples)
    acc = None
    for r in residuals:
        x = r - r.mean(axis=0)
        win = np.hanning(x.shape[0])[:, None]
        P = np.abs(np.fft.rfft(x * win, n=n, axis=0)) ** 2
        acc = P.sum(axis=1) if acc is None else acc + P.sum(axis=1)
    f = np.fft.rfftfreq(n, dt)
    return f, acc / max(len(residuals), 1)


def _corr(a: Sequence[float], b: Sequence[float]) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def analyse_residuals(mill: Mill, windows: Sequence[Window], residuals: Sequence[np.ndarray],
                      elements: Sequence[str], *, rises: Sequence[float] | None = None,
                      band_hz: float = 1.5) -> ResidualReport:
    """Locate the disagreement (see the module docstring).

    Parameters
    ----------
    mill : Mill
    windows : sequence of Window
    residuals : sequence of ndarray
        Per window, shape (N, len(elements)): (model - data) / channel scale.
    elements : sequence of str
        Element ids of the residual columns.
    rises : sequence of float, optional
        Fitted load-ramp durations per window, s (default 20 ms).
    band_hz : float
        Half-width of the frequency bands, Hz.
    """
    rises = list(rises) if rises is not None else [0.02] * len(windows)
    allr = np.concatenate(residuals, axis=0)
    total = float(np.sqrt(np.mean(allr ** 2)))
    by_window = {w.label or f"window {i}": float(np.sqrt(np.mean(r ** 2)))
                 for i, (w, r) in enumerate(zip(windows, residuals))}
    by_channel = {e: float(np.sqrt(np.mean(allr[:, j] ** 2))) for j, e in enumerate(elements)}
    sums = {k: [0.0, 0] for k in PHASES}
    for w, r, rise in zip(windows, residuals, rises):
        for k, m in _phase_masks(w, rise).items():
            sums[k][0] += float(np.sum(r[m] ** 2))
            sums[k][1] += int(m.sum()) * r.shape[1]
    by_phase = {k: (math.sqrt(s / n) if n else float("nan")) for k, (s, n) in sums.items()}

    f, P = residual_spectrum(windows, residuals)
    Ptot = float(P[f > 0.5].sum()) or 1.0
    roll_hz = mill.motor_speed / (2 * math.pi) / _roll_ratio(mill)
    bands: dict[str, float] = {}

    def share(fc: float) -> float:
        m = np.abs(f - fc) <= band_hz
        return float(P[m].sum()) / Ptot

    modes = natural_modes(mill).frequencies_hz
    for fm in modes:
        bands[f"mode {fm:.1f} Hz"] = share(fm)
    for fm in modes[:2]:
        for h in (2, 3):
            bands[f"{h}x {fm:.1f} Hz"] = share(h * fm)
        bands[f"{fm:.1f} Hz +- 2x roll"] = share(fm - 2 * roll_hz) + share(fm + 2 * roll_hz)
    peak_hz = float(f[np.argmax(np.where(f > 0.5, P, 0))])

    loads = [w.static_torque for w in windows]
    steps = [abs(w.level_after - w.level_before) for w in windows]
    rms = list(by_window.values())
    return ResidualReport(nrmse=total, by_window=by_window, by_channel=by_channel,
                          by_phase=by_phase, bands=bands, peak_hz=peak_hz,
                          load_correlation=_corr(rms, loads), step_correlation=_corr(rms, steps),
                          roll_angle_share=_roll_share(mill, windows, residuals),
                          spectrum=(f, P))


def _roll_ratio(mill: Mill) -> float:
    """Speed ratio motor / rolls: the ratio of the elements touching the load masses."""
    load = set(mill.load.masses)
    rs = [e.ratio for e in mill.elements if e.to in load or e.from_ in load]
    return float(np.median(rs)) if rs else 1.0


def _roll_share(mill: Mill, windows: Sequence[Window], residuals: Sequence[np.ndarray]) -> float:
    """Share of residual variance explained by sin/cos(2 * roll angle), nominal speed."""
    omega = mill.motor_speed / _roll_ratio(mill)
    t = np.concatenate([w.t for w in windows])
    r = np.concatenate(residuals, axis=0)
    r = r - r.mean(axis=0)
    A = np.stack([np.sin(2 * omega * t), np.cos(2 * omega * t)], axis=1)
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    fitted = A @ coef
    den = float(np.sum(r ** 2))
    return float(np.sum(fitted ** 2)) / den if den > 0 else 0.0
