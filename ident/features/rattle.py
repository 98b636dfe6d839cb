"""Bearing-housing vibration in windows around a load step: the shaft rattling in its clearance.

In the radial model (seed section 2.2, Fig. 8a) the shaft flies freely inside
its clearance whenever the mesh force does not hold it against the housing,
and every contact is an impact that rings the housing.  The contacts are
nearly elastic, so after a release the shaft keeps rattling under gravity
through the pause between bars: the wider the clearance, the longer each
flight and the faster the shaft when it hits (``v**2 ~ v0**2 + 4 g c``) --
fewer, harder impacts, the housing's energy moving from its ringing to the
impacts' low-frequency pattern.  At a bite the mesh force throws the shaft
across the clearance before it comes to rest against the loaded side.

Per window, with the acceleration referred to ``a_ref`` (the acceleration the
mesh-force step would give the housing mass alone):

============  ================================================================
``lrms``      log10 RMS over ``a_ref``
``lpeak``     log10 largest magnitude over ``a_ref``
``kurt``      kurtosis (impacts: large)
``lpeak_med`` log10 median height of the impacts over ``a_ref``
``rate``      impacts per second (peaks above 30 % of the largest, 2 ms apart)
``ival_ms``   median interval between those impacts
``lswing``    log10 of median impact height (m/s^2) times median interval (s):
              the housing's acceleration at an impact grows with the shaft's
              speed, and speed times flight time is the distance flown --
              the clearance, while the rattle's energy carries the shaft
              across it
``cent_hz``   spectral centroid
``cent_low_hz`` spectral centroid below 700 Hz (the shaft-bearing-housing
              modes, 150-450 Hz here: their frequency falls as the clearance
              grows, seed section 2.2)
``b0`` ...    energy fractions in 0-75, 75-150, 150-225, 225-300, 300-450,
``b7``        450-700, 700-1200 Hz and above
============  ================================================================

Windows (:data:`WINDOWS`): ``hit`` from 30 ms before to 120 ms after
``t_step``; ``after`` from then to 500 ms after it (or 50 ms before the next
step): after a release the rattle in the pause, after a bite the rolling.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

__all__ = ["RATTLE_FEATURES", "RATTLE_BANDS_HZ", "WINDOWS", "rattle_features"]

#: band edges of the energy fractions, Hz
RATTLE_BANDS_HZ: tuple[float, ...] = (0.0, 75.0, 150.0, 225.0, 300.0, 450.0, 700.0, 1200.0,
                                      np.inf)
RATTLE_FEATURES: tuple[str, ...] = (("lrms", "lpeak", "lpeak_med", "kurt", "rate", "ival_ms",
                                     "lswing", "cent_hz", "cent_low_hz")
                                    + tuple(f"b{i}" for i in range(len(RATTLE_BANDS_HZ) - 1)))
#: window name to (start, end) relative to ``t_step`` in s (ending 50 ms before the next step
#: at the latest)
WINDOWS: dict[str, tuple[float, float]] = {"hit": (-0.03, 0.12), "after": (0.12, 0.5)}


def rattle_features(x: np.ndarray, rate_hz: float, a_ref: float) -> dict[str, float]:
    """:data:`RATTLE_FEATURES` of one accelerometer window (m/s^2) against ``a_ref`` (m/s^2)."""
    out = {k: np.nan for k in RATTLE_FEATURES}
    x = np.asarray(x, dtype=float)
    if x.size < 64 or not a_ref > 0:
        return out
    x = x - np.median(x)
    rms = float(np.sqrt(np.mean(x ** 2)))
    ax = np.abs(x)
    peak = float(ax.max())
    if rms <= 0:
        return out
    out["lrms"] = float(np.log10(rms / a_ref + 1e-12))
    out["lpeak"] = float(np.log10(peak / a_ref + 1e-12))
    out["kurt"] = float(np.mean(x ** 4) / rms ** 4)
    pk, _ = find_peaks(ax, height=0.3 * peak, distance=max(int(0.002 * rate_hz), 1))
    out["rate"] = pk.size / (x.size / rate_hz)
    h_med = float(np.median(ax[pk])) if pk.size else np.nan
    out["lpeak_med"] = float(np.log10(h_med / a_ref + 1e-12)) if pk.size else np.nan
    if pk.size > 2:
        ival = float(np.median(np.diff(pk)) / rate_hz)
        out["ival_ms"] = 1e3 * ival
        out["lswing"] = float(np.log10(h_med * ival + 1e-12))
    P = np.abs(np.fft.rfft(x * np.hanning(x.size))) ** 2
    f = np.fft.rfftfreq(x.size, 1.0 / rate_hz)
    tot = float(P.sum())
    if tot > 0:
        out["cent_hz"] = float(np.sum(f * P) / tot)
        low = f < 700.0
        if P[low].sum() > 0:
            out["cent_low_hz"] = float(np.sum(f[low] * P[low]) / P[low].sum())
        for i in range(len(RATTLE_BANDS_HZ) - 1):
            sel = (f >= RATTLE_BANDS_HZ[i]) & (f < RATTLE_BANDS_HZ[i + 1])
            out[f"b{i}"] = float(P[sel].sum() / tot)
    return out
