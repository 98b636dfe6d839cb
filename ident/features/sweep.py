"""Gap-sweep features: when a torque channel's flanks part and meet again (time domain).

A gap shows in an element's own torque channel as time spent at zero torque
and as impacts (seed section 1, Fig. 1a):

* **bite** -- between bars the elements rest on their back flanks (the speed
  loop's braking after the previous release pushed them there), so at the
  bite each element transmits nothing until the load has swept its whole gap
  (``gap_open`` for the first bite of a run).  Under the load step ``S`` the
  driven side accelerates at about ``S/J``, so the delay grows like
  ``sqrt(gap * J / S)`` and the flanks meet with a speed ``~ sqrt(2 S gap /
  J)`` -- a steep rise and a large overshoot (TAF).
* **release** -- the elastic rebound and then the speed loop's braking (its
  torque ``~ T_static``) carry every element across its gap to the back
  flank; the time to that contact grows like ``gap / v`` (rebound, ``v ~
  T_static``) or ``sqrt(gap * J / T_brake)`` (braking).

The features are read from each channel's torque low-passed at 150 Hz and
normalised by its share of the load step, ``y = (x - x_pre) / (share * S)``
(0 before, 1 at the new level, for bites and releases alike), times in ms
from the transient's ``t_step``:

=================  ==========================================================
``rise05_ms`` ...  first time ``y`` reaches 5, 10, 20, 50, 80 % (the gap's
``rise80_ms``      closure delays it)
``peak``           largest ``y`` within 0.3 s (the TAF in units of the step)
``peak_ms``        its time
``onset_rate``     steepest rise of ``y`` (1/s) within 10 ms after ``rise05``:
                   the flanks' closing speed times the stiffness
``impact``         ``onset_rate**2 * T_static/T_nominal * 1e-4``: grows like the
                   gap swept under the load (impact energy)
``back04_ms``      first time after ``y`` passed 0.9 that it goes beyond the
``back10_ms``      new level against the step by 4 % (10 %): the back-flank
                   contact after a release; 400 ms when never
``back04_sq``      ``(back04_ms/1e3)**2 * T_static/T_nominal * 1e3``: ~ gap
                   swept under a torque ~ T_static (the speed loop's braking)
``back04_st``      ``back04_ms * T_static/T_nominal``: ~ gap swept at a speed ~
                   T_static (the rebound)
``rebound``        largest excursion beyond the new level within 0.12 s of
``rebound_ms``     ``y`` passing 0.9, and its time
``brake``          the same 0.08-0.35 s later (the speed loop's braking), and
``brake_ms``       its time
``back_rate``      steepest slope of that excursion within 0.12 s (1/s)
``sweep``          ``back04_ms * back_rate * 1e-3``: crossing time times
                   closing speed
``settled``        fraction of 0.3 s after ``y`` passed 0.9 within 3 % of the
                   new level (zero torque inside a gap after a release)
=================  ==========================================================

:func:`pair_differences` adds, for every pair of channels, the differences of
the timing features (``C46-C57.rise20_ms``...): the order in which the load
reaches the channels separates the elements of one load path.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, sosfiltfilt

__all__ = ["SWEEP_FEATURES", "PAIR_FEATURES", "SQUARED_PAIR_FEATURES", "RISE_LEVELS", "lowpass",
           "normalised_window",
           "sweep_features", "pair_differences"]

#: fractions of the step whose first crossing times are read
RISE_LEVELS: tuple[float, ...] = (0.05, 0.1, 0.2, 0.5, 0.8)
#: back-flank thresholds beyond the new level, fraction of the step
BACK_LEVELS: tuple[float, ...] = (0.04, 0.10)
#: value of a back-flank time when the contact never comes within the window, ms
NEVER_MS = 400.0

SWEEP_FEATURES: tuple[str, ...] = (
    tuple(f"rise{int(round(100 * lv)):02d}_ms" for lv in RISE_LEVELS)
    + ("peak", "peak_ms", "onset_rate", "impact")
    + tuple(f"back{int(round(100 * lv)):02d}{s}" for lv in BACK_LEVELS
            for s in ("_ms", "_sq", "_st"))
    + ("rebound", "rebound_ms", "brake", "brake_ms", "back_rate", "sweep", "settled"))
#: timing features whose differences between channels are kept
PAIR_FEATURES: tuple[str, ...] = ("rise05_ms", "rise10_ms", "rise20_ms", "rise50_ms",
                                  "peak_ms", "back04_ms", "back10_ms", "rebound_ms",
                                  "brake_ms")
#: pair differences also kept squared times the static torque
SQUARED_PAIR_FEATURES: tuple[str, ...] = ("rise10_ms", "rise20_ms", "back04_ms", "back10_ms")


def lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float = 150.0) -> np.ndarray:
    """Zero-phase 4th-order Butterworth low-pass (keeps the 81 Hz mode, cuts the noise)."""
    x = np.asarray(x, dtype=float)
    if cutoff_hz >= 0.5 * rate_hz or x.size < 30:
        return x.copy()
    sos = butter(4, cutoff_hz, fs=rate_hz, output="sos")
    return sosfiltfilt(sos, x)


def normalised_window(x: np.ndarray, t0: float, rate_hz: float, t_step: float, pre: float,
                      step: float, *, before_s: float, after_s: float) -> np.ndarray:
    """``(x - pre) / step`` from ``t_step - before_s`` for ``before_s + after_s`` s.

    Samples past the signal's end repeat its last value (the window length is
    fixed so that features compare).
    """
    n_pre = int(round(before_s * rate_hz))
    n = n_pre + int(round(after_s * rate_hz))
    i0 = int(round((t_step - t0) * rate_hz)) - n_pre
    seg = x[max(i0, 0):max(i0 + n, 0)]
    if i0 < 0:
        seg = np.concatenate([np.full(-i0, x[0] if x.size else 0.0), seg])
    if seg.size < n:
        seg = np.concatenate([seg, np.full(n - seg.size, seg[-1] if seg.size else 0.0)])
    return (seg - pre) / step


def _first_crossing(y: np.ndarray, level: float, start: int) -> float:
    """Fractional index of the first ``y >= level`` at or after ``start``; NaN if never."""
    i = np.flatnonzero(y[start:] >= level)
    if i.size == 0:
        return np.nan
    j = int(i[0]) + start
    if j == 0 or y[j] == y[j - 1]:
        return float(j)
    return j - 1 + (level - y[j - 1]) / (y[j] - y[j - 1])


def sweep_features(y: np.ndarray, rate_hz: float, n_pre: int, static_norm: float,
                   window_valid_s: float) -> dict[str, float]:
    """The :data:`SWEEP_FEATURES` of one normalised channel window.

    Parameters
    ----------
    y : ndarray
        :func:`normalised_window` of the low-passed torque (1).
    rate_hz : float
    n_pre : int
        Samples before ``t_step`` at the window's start.
    static_norm : float
        Static torque of the transient over the nominal torque (1).
    window_valid_s : float
        Time after ``t_step`` before the next step (s): later samples are not read.

    Returns
    -------
    dict
        Feature name (without channel prefix) to value.
    """
    out: dict[str, float] = {}
    ms = 1e3 / rate_hz
    n_valid = min(y.size, n_pre + max(int(window_valid_s * rate_hz), 1))
    y = y[:n_valid]
    start = max(n_pre - int(0.02 * rate_hz), 0)  # 20 ms before t_step
    k05 = np.nan
    for lv in RISE_LEVELS:
        k = _first_crossing(y, lv, start)
        if lv == RISE_LEVELS[0]:
            k05 = k
        out[f"rise{int(round(100 * lv)):02d}_ms"] = (k - n_pre) * ms if np.isfinite(k) else np.nan
    n03 = min(y.size, n_pre + int(0.3 * rate_hz))
    w = y[start:n03]
    if w.size:
        out["peak"] = float(np.max(w))
        out["peak_ms"] = (int(np.argmax(w)) + start - n_pre) * ms
    else:
        out["peak"] = out["peak_ms"] = np.nan
    dy = np.gradient(y) * rate_hz if y.size > 2 else np.zeros_like(y)
    if np.isfinite(k05):
        a = int(k05)
        seg = dy[a:a + max(int(0.01 * rate_hz), 2)]
        rate = float(np.max(seg)) if seg.size else np.nan
    else:
        rate = np.nan
    out["onset_rate"] = rate
    out["impact"] = rate ** 2 * static_norm * 1e-4 if np.isfinite(rate) else np.nan
    k90 = _first_crossing(y, 0.9, start)
    k90i = int(np.ceil(k90)) if np.isfinite(k90) else n_pre
    seg = y[k90i:]
    for lv in BACK_LEVELS:
        j = np.flatnonzero(seg > 1.0 + lv)
        t_b = (int(j[0]) / rate_hz) if j.size else NEVER_MS / 1e3
        key = f"back{int(round(100 * lv)):02d}"
        out[f"{key}_ms"] = 1e3 * t_b
        out[f"{key}_sq"] = t_b ** 2 * static_norm * 1e3
        out[f"{key}_st"] = 1e3 * t_b * static_norm
    n12 = int(0.12 * rate_hz)
    s1 = seg[:n12]
    if s1.size:
        out["rebound"] = float(np.max(s1) - 1.0)
        out["rebound_ms"] = int(np.argmax(s1)) * ms
        ds = dy[k90i:k90i + n12]
        out["back_rate"] = float(np.max(ds)) if ds.size else np.nan
    else:
        out["rebound"] = out["rebound_ms"] = out["back_rate"] = np.nan
    s2 = seg[int(0.08 * rate_hz):int(0.35 * rate_hz)]
    if s2.size:
        out["brake"] = float(np.max(s2) - 1.0)
        out["brake_ms"] = (int(np.argmax(s2)) + int(0.08 * rate_hz)) * ms
    else:
        out["brake"] = out["brake_ms"] = np.nan
    out["sweep"] = (out["back04_ms"] * out["back_rate"] * 1e-3
                    if np.isfinite(out["back_rate"]) else np.nan)
    s3 = seg[:int(0.3 * rate_hz)]
    out["settled"] = float(np.mean(np.abs(s3 - 1.0) < 0.03)) if s3.size else np.nan
    return out


def pair_differences(per_channel: dict[str, dict[str, float]],
                     static_norm: float = np.nan) -> dict[str, float]:
    """Differences of the timing features between every pair of channels (order kept).

    ``{A}-{B}.{f}`` is A's minus B's :data:`PAIR_FEATURES` (ms); for the
    back-flank and rise times also ``{A}-{B}.{f}_dsq``, the signed square of
    that difference (s) times ``static_norm`` times 1e3: the gap between the
    two channels' elements swept under a torque ~ T_static (the delay from
    one flank contact to the next grows like ``sqrt(gap * J / T)``).
    """
    ids = list(per_channel)
    out: dict[str, float] = {}
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            for f in PAIR_FEATURES:
                d = per_channel[a].get(f, np.nan) - per_channel[b].get(f, np.nan)
                out[f"{a}-{b}.{f}"] = d
                if f in SQUARED_PAIR_FEATURES:
                    out[f"{a}-{b}.{f[:-3]}_dsq"] = float(np.sign(d) * (d / 1e3) ** 2
                                                         * static_norm * 1e3)
    return out
