"""Sensor noise in the band that carries the gaps, and the residual judged against it.

Why a band, not the whole residual
----------------------------------
A plant records torque through an anti-alias filter before decimation, with
offsets that drift and a rolling load that fluctuates slowly during a bar.  A
fit that is right in the gaps can then leave residuals well above the white
noise (slow misfit below the first mode), and the sensor noise itself has
little power near Nyquist, so a whole-record estimate of its variance (the
fourth difference) reads it low.  What tells a right fit from a local minimum
is the transient's own content: the natural frequencies, where wrong gaps put
wrong phases and amplitudes.  So the verdict compares the residual's power in
the **transient band** ``[max(0.6 f_1, 3/T), min(1.25 f_n, 0.3 f_s)]`` (``f_1 ..
f_n`` the linear baseline's natural frequencies, ``T`` the window length,
``f_s`` the sample rate) with the noise's power in the same band.

The noise's level there comes from the **noise band** ``[1.5 f_n, 0.3 f_s]``
(widened down to ``0.3 f_s - 6/T`` when the modes reach that high), above every
modelled mode and inside any anti-alias filter's pass band: the per-bin median
over many short segments of the recording's quiet stretches (the samples
away from every load step), its median over the band's bins, taken as flat
down into the transient band (white sensor noise through a flat pass band).

Both spectra are the same estimator: each segment with its mean and linear
trend removed, a Hann taper, a one-sided density, so that white noise of
density ``S`` reads ``S`` in every bin.

Statistics: with ``nu`` independent chi-square degrees of freedom in the
transient band (two per bin, adjacent Hann bins sharing about half), the
band ratio of white noise has standard deviation ``sqrt(2 / nu)``, 0.1-0.15 for
four 0.3 s windows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

__all__ = ["NoiseSpectrum", "Bands", "bands", "density", "noise_spectrum",
           "noise_from_windows", "band_ratio", "BAND_RATIO_MAX"]

#: Largest transient-band ratio (residual power over noise power in the band
#: that carries the gaps) of a channel whose fit is accepted: what the model
#: misses at the natural frequencies is at most as large as the sensor noise
#: there.  White noise alone reads 1 +- 0.15 (see the module docstring); a
#: swapped-gap or wrong-gap minimum puts the transient's own misfit there.
BAND_RATIO_MAX = 2.0

#: ln 2: the median of a chi-square(2) periodogram bin over its mean.
_MEDIAN_EXP = math.log(2.0)


@dataclass(frozen=True)
class Bands:
    """The transient band and the noise band of one mill at one sample rate, Hz."""

    transient: tuple[float, float]
    noise: tuple[float, float]


def bands(frequencies_hz: Sequence[float], rate_hz: float, window_s: float) -> Bands:
    """Transient and noise bands (module docstring) for natural frequencies and a rate.

    Parameters
    ----------
    frequencies_hz : sequence of float
        Natural frequencies of the linear baseline, Hz (rigid-body mode left out).
    rate_hz : float
        Sample rate, Hz.
    window_s : float
        Length of the windows the residual is judged on, s.
    """
    f = np.sort(np.asarray(frequencies_hz, dtype=float))
    f = f[f > 0]
    top = 0.3 * rate_hz
    f1 = float(f[0]) if f.size else 10.0
    fn = float(f[-1]) if f.size else 0.1 * rate_hz
    lo = max(0.6 * f1, 3.0 / window_s)
    hi = min(1.25 * fn, top)
    if hi <= lo:
        hi = min(max(lo * 2.0, lo + 3.0 / window_s), top)
    n_lo = max(1.5 * fn, hi)
    if top - n_lo < 6.0 / window_s:  # modes near the top: the noise band's width comes first
        n_lo = max(min(n_lo, top - 6.0 / window_s), 0.5 * top)
    return Bands(transient=(float(lo), float(hi)), noise=(float(n_lo), float(top)))


def density(x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """One-sided spectral density of one segment (mean and trend removed, Hann taper).

    Parameters
    ----------
    x : ndarray, shape (N,) or (N, k)
        Samples (columns are channels).
    dt : float
        Sample interval, s.

    Returns
    -------
    freqs_hz : ndarray, shape (N // 2 + 1,)
    psd : ndarray, shape (N // 2 + 1,) or (N // 2 + 1, k)
        Units of ``x`` squared per Hz; white noise of variance ``s**2`` reads
        ``2 s**2 dt`` in every bin but the first and last.
    """
    x = np.asarray(x, dtype=float)
    one = x.ndim == 1
    X = x[:, None] if one else x
    n = X.shape[0]
    t = np.arange(n) - 0.5 * (n - 1)
    A = np.column_stack([np.ones(n), t])
    X = X - A @ np.linalg.lstsq(A, X, rcond=None)[0]
    w = np.hanning(n + 2)[1:-1] if n > 2 else np.ones(n)
    F = np.fft.rfft(X * w[:, None], axis=0)
    P = 2.0 * dt * np.abs(F) ** 2 / float(w @ w)
    f = np.fft.rfftfreq(n, dt)
    return f, (P[:, 0] if one else P)


@dataclass(frozen=True, eq=False)
class NoiseSpectrum:
    """Sensor-noise density per element, measured on the recording (module docstring).

    Attributes
    ----------
    freqs_hz : ndarray, shape (n_f,)
    psd : mapping of str to ndarray
        Element id -> per-bin median density over the quiet segments (bias
        corrected to a mean), (N*m)**2/Hz, reduced to the motor shaft.
    n_segments : int
        Quiet segments the medians are over.
    segment_s : float
        Segment length, s.
    source : str
        ``"recording"`` (quiet stretches between the steps) or ``"windows"``
        (the fit windows themselves, where no recording was given).
    """

    freqs_hz: np.ndarray
    psd: Mapping[str, np.ndarray]
    n_segments: int
    segment_s: float
    source: str = "recording"
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def level(self, element: str, band: tuple[float, float]) -> float:
        """Median density over ``band`` (Hz), (N*m)**2/Hz: the flat noise level there."""
        m = (self.freqs_hz >= band[0]) & (self.freqs_hz <= band[1])
        p = self.psd.get(element)
        if p is None or not m.any():
            return math.nan
        return float(np.median(p[m]))

    def sigma(self, element: str, band: tuple[float, float], rate_hz: float) -> float:
        """White-noise standard deviation the level in ``band`` stands for, N*m."""
        return math.sqrt(max(self.level(element, band), 0.0) * 0.5 * rate_hz)


def _segments(x: np.ndarray, n: int, keep: np.ndarray) -> list[np.ndarray]:
    """Half-overlapping segments of ``n`` rows of ``x`` whose every row is in ``keep``."""
    out = []
    step = max(n // 2, 1)
    for a in range(0, x.shape[0] - n + 1, step):
        if keep[a:a + n].all():
            out.append(x[a:a + n])
    return out


def _median_psd(segs: Sequence[np.ndarray], dt: float,
                band: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-bin median density over segments (bias-corrected to a mean), per column.

    With ``band``, per column only the quiet segments count: each segment's
    level (its median density over the band) is a tight number for pure
    noise (about +-10 %); a segment holding a ring-down, an idle rattle or an
    impact reads higher.  Segments above 1.5 times the lower quartile of the
    levels are left out before the median.
    """
    f = None
    P = []
    for s in segs:
        f, p = density(s, dt)
        P.append(p if p.ndim == 2 else p[:, None])
    S = np.stack(P)  # (n_seg, n_f, k)
    if band is None:
        return f, np.median(S, axis=0) / _MEDIAN_EXP
    m = (f >= band[0]) & (f <= band[1])
    out = np.empty(S.shape[1:])
    for j in range(S.shape[2]):
        lev = np.median(S[:, m, j], axis=1) if m.any() else np.ones(S.shape[0])
        keep = lev <= 1.5 * np.quantile(lev, 0.25)
        out[:, j] = np.median(S[keep, :, j], axis=0) / _MEDIAN_EXP
    return f, out


def noise_spectrum(t: np.ndarray, y: np.ndarray, elements: Sequence[str], *,
                   segment_n: int, exclude: Sequence[tuple[float, float]] = (),
                   min_segments: int = 8, max_segments: int = 400,
                   band: tuple[float, float] | None = None) -> NoiseSpectrum | None:
    """Sensor-noise density per element from a recording's quiet stretches.

    Parameters
    ----------
    t : ndarray, shape (N,)
        Uniform sample times, s.
    y : ndarray, shape (N, k)
        Reduced torques, N*m, one column per element of ``elements``.
    elements : sequence of str
    segment_n : int
        Segment length, samples (the fit windows' length).
    exclude : sequence of (float, float)
        Time spans (s) left out: each load step and its ring-down.
    min_segments : int
        Fewer quiet segments than this: None (too little to take a median over).
    max_segments : int
        More quiet segments than this (a long recording): this many, evenly spread.
    band : (float, float), optional
        The noise band, Hz: segments whose level there stands out (an idle
        rattle after a release, a ring-down) are left out per element.

    Returns
    -------
    NoiseSpectrum or None
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.size < 2 * segment_n or segment_n < 16:
        return None
    keep = np.all(np.isfinite(y), axis=1)
    for a, b in exclude:
        i0, i1 = np.searchsorted(t, [a, b], side="left")
        keep[i0:i1 + 1] = False
    segs = _segments(y, segment_n, keep)
    if len(segs) < min_segments:
        return None
    if len(segs) > max_segments:
        segs = [segs[i] for i in np.linspace(0, len(segs) - 1, max_segments).astype(int)]
    dt = float((t[-1] - t[0]) / (t.size - 1))
    f, med = _median_psd(segs, dt, band)
    return NoiseSpectrum(freqs_hz=f, psd={e: med[:, j] for j, e in enumerate(elements)},
                         n_segments=len(segs), segment_s=segment_n * dt, source="recording")


def noise_from_windows(y: Sequence[np.ndarray], elements: Sequence[str], dt: float,
                       band: tuple[float, float] | None = None) -> NoiseSpectrum:
    """The fallback without a recording: the same median over the fit windows' own segments.

    Segments a quarter of a window long; the transients' content lies below
    the noise band, so the noise band's level is still the sensor's (impacts
    excepted, which the median ignores), at a coarser resolution.
    """
    n = max(min(len(w) for w in y) // 4, 16)
    segs = []
    for w in y:
        segs += _segments(np.asarray(w, dtype=float), n, np.ones(len(w), dtype=bool))
    f, med = _median_psd(segs, dt, band)
    return NoiseSpectrum(freqs_hz=f, psd={e: med[:, j] for j, e in enumerate(elements)},
                         n_segments=len(segs), segment_s=n * dt, source="windows")


def band_ratio(residuals: Sequence[np.ndarray], dt: float, band: tuple[float, float],
               level: float) -> tuple[float, float]:
    """Residual power in ``band`` over a flat noise ``level`` there, and its degrees of freedom.

    Parameters
    ----------
    residuals : sequence of ndarray, shape (N_w,)
        One channel's residuals per window, in the units of ``level`` (N*m).
    dt : float
        Sample interval, s.
    band : (float, float)
        Hz.
    level : float
        Noise density, (N*m)**2/Hz.

    Returns
    -------
    ratio : float
        1 for white noise of that density (module docstring).
    dof : float
        Approximate chi-square degrees of freedom of the ratio.
    """
    num = 0.0
    n_bins = 0
    for r in residuals:
        f, p = density(np.asarray(r, dtype=float), dt)
        m = (f >= band[0]) & (f <= band[1])
        num += float(np.sum(p[m]))
        n_bins += int(m.sum())
    if n_bins == 0 or not (level > 0):
        return math.nan, 0.0
    return num / (n_bins * level), float(n_bins)  # 2 dof per bin, Hann halves them
