"""Load steps in one level signal, with every threshold taken from the signal itself.

:func:`detect_steps` finds the bites (steps up) and releases (steps down) of a
signal ``x`` that sits at an idle level between bars and at a rolling level during
them (the total rolling torque nearest the rolls, or a vibration envelope).  Its
time scale is the period ``T1`` of the mill's lowest natural mode
(:mod:`.timescales`); its levels come from the recording:

1. *Smoothing.*  Two cascaded centred moving means of ``1.25 T1`` each (a
   triangle of ``2.5 T1``): the ring-down of the lowest mode leaks through by at
   most ~3 % of its amplitude, even when a gap lowers its frequency to 0.65 of
   ``f1`` (response ``sinc^2(f 1.25 T1)``), and every higher mode by less.
2. *Levels.*  Otsu's threshold splits the smoothed signal into an idle and a
   rolling class.  Of each class only its *plateaus* count (where the smoothed
   signal changes by less than a tenth of the class separation over ``2.5 T1``):
   the idle level is the median of the idle plateaus, the smallest bar the 2nd
   percentile of the rolling plateaus.  Their difference ``D`` is the smallest
   step the recording holds.
3. *Noise.*  The sample noise ``sigma`` of each channel (MAD of differences);
   there are steps only if ``D > 12 sigma`` (or ``min_step``).
4. *Detection.*  Hysteresis on the smoothed signal at ``idle + 0.5 D`` (up) and
   ``idle + 0.25 D`` (down); two changes closer than the smoothing's width
   (``2.5 T1``) are one disturbance, not a bar, and are dropped together.
5. *Checks and levels per step.*  The level before and after each change: medians
   of the smoothed signal over ``level_s`` windows that keep ``1.25 T1 + 50 ms``
   from the step and ``settle_s`` of ring-down after it, and stop short of the
   neighbouring changes.  A step must be at least ``max(12 sigma, D / 2)`` and at
   least 6 times the spread of the signal in those windows (slow drift is not a
   step), in the direction of the change.
6. *Timing.*  The first crossing of the half-way level by the smoothed signal near
   the change, then the first crossing by the lightly smoothed signal (``fine_s``)
   within ``1.25 T1 + 20 ms`` of it, interpolated between samples: cli.md's "the
   moment the step reaches half its height".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Event", "Levels", "detect_steps", "moving_mean", "noise_sigma"]

#: triangle half-width (each moving mean) in periods of the lowest mode
SMOOTH_PERIODS = 1.25
#: hysteresis thresholds as fractions of the smallest step above the idle level
UP_FRACTION, DOWN_FRACTION = 0.5, 0.25
#: smallest step in units of the sample noise
NOISE_FACTOR = 12.0
#: smallest step in units of the level windows' spread
FLATNESS_FACTOR = 6.0


# ---- signal helpers ------------------------------------------------------------------------
def moving_mean(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving mean over ``w`` samples (shorter at the ends); NaN where it holds a NaN."""
    n = x.size
    w = max(1, int(w))
    bad = np.isnan(x)
    cs = np.empty(n + 1)
    cs[0] = 0.0
    np.cumsum(np.where(bad, 0.0, x), out=cs[1:])
    cb = np.empty(n + 1, dtype=np.int64)
    cb[0] = 0
    np.cumsum(bad, out=cb[1:])
    i = np.arange(n)
    lo = np.clip(i - w // 2, 0, n)
    hi = np.clip(i - w // 2 + w, 0, n)
    cnt = hi - lo
    y = (cs[hi] - cs[lo]) / np.maximum(cnt, 1)
    y[(cb[hi] - cb[lo]) > 0] = np.nan
    return y


def noise_sigma(x: np.ndarray, lag: int = 1) -> float:
    """Robust sample noise: MAD of differences at ``lag`` (past the signal's own smoothing)."""
    lag = max(1, int(lag))
    if x.size <= lag:
        return 0.0
    d = x[lag:] - x[:-lag]
    d = d[:: max(1, d.size // 2_000_000)]
    d = d[np.isfinite(d)]
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d)) / math.sqrt(2.0))


def _robust(x: np.ndarray, a: int, b: int) -> tuple[float, float]:
    """Median and MAD-sigma of the finite samples of x[a:b] (NaN if fewer than 3)."""
    a, b = max(a, 0), min(b, x.size)
    if b - a < 3:
        return math.nan, math.nan
    seg = x[a:b]
    seg = seg[np.isfinite(seg)]
    if seg.size < 3:
        return math.nan, math.nan
    med = float(np.median(seg))
    return med, float(1.4826 * np.median(np.abs(seg - med)))


def _crossing(xs: np.ndarray, level: float, a: int, b: int, up: bool) -> float | None:
    """Fractional index of the first crossing of ``level`` in xs[a:b] (upwards if ``up``)."""
    a, b = max(a, 1), min(b, xs.size)
    if b - a < 2:
        return None
    seg = xs[a - 1:b]
    above = seg >= level if up else seg <= level
    below = seg < level if up else seg > level  # NaN is neither: no crossing through a gap
    k = np.flatnonzero(below[:-1] & above[1:])
    if k.size == 0:
        return None
    j = int(k[0])
    x0, x1 = seg[j], seg[j + 1]
    frac = 0.0 if x1 == x0 else (level - x0) / (x1 - x0)
    return a - 1 + j + float(np.clip(frac, 0.0, 1.0))


def _last_crossing(xs: np.ndarray, level: float, a: int, b: int, up: bool) -> float | None:
    """Fractional index of the last crossing of ``level`` in xs[a:b] (upwards if ``up``)."""
    a, b = max(a, 1), min(b, xs.size)
    if b - a < 2:
        return None
    seg = xs[a - 1:b]
    above = seg >= level if up else seg <= level
    below = seg < level if up else seg > level  # NaN is neither: no crossing through a gap
    k = np.flatnonzero(below[:-1] & above[1:])
    if k.size == 0:
        return None
    j = int(k[-1])
    x0, x1 = seg[j], seg[j + 1]
    frac = 0.0 if x1 == x0 else (level - x0) / (x1 - x0)
    return a - 1 + j + float(np.clip(frac, 0.0, 1.0))


def _otsu(v: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of the samples ``v`` (maximum between-class variance)."""
    hist, edges = np.histogram(v, bins=bins)
    p = hist / max(hist.sum(), 1)
    mids = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(p)
    mu = np.cumsum(p * mids)
    w1 = 1.0 - w0
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mu[-1] * w0 - mu) ** 2 / (w0 * w1)
    between[~np.isfinite(between) | (w0 <= 0) | (w1 <= 1e-12)] = -1.0
    return float(edges[int(np.argmax(between)) + 1])


# ---- the detection -------------------------------------------------------------------------
@dataclass(frozen=True)
class Event:
    """One detected step, in samples of the signal."""

    kind: str         # "bite" | "release"
    i_step: float     # fractional sample index of the half-height crossing
    pre: float        # level before
    post: float       # level after
    rise: float       # 10-90 % rise (fall) time, s


@dataclass(frozen=True)
class Levels:
    """What the detection took from the signal (same unit as the signal).

    ``sigma`` the sample noise, ``idle`` the idle level, ``step`` the smallest step
    (smallest bar above idle), ``floor`` the smallest step accepted, ``up`` and
    ``down`` the hysteresis thresholds; ``smooth_n`` the samples of each moving mean.
    """

    sigma: float
    idle: float
    step: float
    floor: float
    up: float
    down: float
    smooth_n: int


def _levels(y: np.ndarray, n: int, fs: float, sigma: float,
            min_step: float | None) -> Levels | None:
    """Idle level, smallest step and thresholds of the smoothed signal ``y``."""
    stride = max(1, y.size // 400_000)
    fin = y[::stride]
    fin = fin[np.isfinite(fin)]
    if fin.size < 10:
        return None
    lo, hi = np.percentile(fin, [0.1, 99.9])
    span = float(hi - lo)
    if not span > 0:
        return None
    # plateaus: the smoothed signal changes by less than span / 20 over the triangle's width
    at = np.arange(n, y.size - n, stride)
    with np.errstate(invalid="ignore"):
        flat_at = np.abs(y[at + n] - y[at - n]) < 0.05 * span  # False where NaN
    flat = np.sort(y[at[flat_at]])
    # levels: groups of plateau values separated by more than span / 10
    cuts = np.flatnonzero(np.diff(flat) > 0.1 * span) + 1
    groups = [g for g in np.split(flat, cuts) if g.size * stride >= 0.1 * fs and g.size >= 5]
    if len(groups) < 2:
        return None
    idle = float(np.median(groups[0]))
    step = float(np.percentile(groups[1], 10.0)) - idle  # the smallest bar
    floor = max(NOISE_FACTOR * sigma, min_step if min_step is not None else 0.0)
    if not step > floor:
        return None
    return Levels(sigma=sigma, idle=idle, step=step, floor=floor, up=idle + UP_FRACTION * step,
                  down=idle + DOWN_FRACTION * step, smooth_n=n)


def _changes(y: np.ndarray, lv: Levels, min_dwell: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample indices where the hysteresis state changes, and the state after each (+1/-1)."""
    n = y.size
    state = np.zeros(n, dtype=np.int8)
    state[y >= lv.up] = 1
    state[y <= lv.down] = -1
    last = np.where(state != 0, np.arange(n), 0)
    np.maximum.accumulate(last, out=last)
    filled = state[last]
    nz = np.flatnonzero(filled)
    if nz.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int8)
    filled[: nz[0]] = filled[nz[0]]  # leading samples before any decision
    ch = list((np.flatnonzero(np.diff(filled) != 0) + 1).tolist())
    # a pair of changes closer than the smoothing's width is one disturbance: drop both
    while len(ch) >= 2:
        gaps = np.diff(ch)
        k = int(np.argmin(gaps))
        if gaps[k] >= min_dwell:
            break
        del ch[k:k + 2]
    idx = np.asarray(ch, dtype=np.int64)
    return idx, filled[idx] if idx.size else np.zeros(0, dtype=np.int8)


def detect_steps(x: np.ndarray, fs: float, *, period_s: float, fine_s: float, level_s: float,
                 settle_s: float, min_step: float | None, x_detect: np.ndarray | None = None,
                 sigma_detect: float | None = None, noise_lag: int = 1,
                 smooth_s: float | None = None) -> tuple[list[Event], np.ndarray, Levels | None]:
    """Bites and releases in a level signal ``x`` sampled at ``fs`` Hz.

    Parameters
    ----------
    x : ndarray
        The signal the steps are timed and measured on.
    fs : float
        Its rate, Hz.
    period_s : float
        Period of the mill's lowest natural mode, s.
    fine_s, level_s, settle_s : float
        Timing smoother, level window and ring-down skipped after a step, s.
    min_step : float, optional
        Smallest step accepted (unit of ``x``); default from the noise.
    x_detect : ndarray, optional
        A less noisy estimate of the same level to detect on (default ``x``).
    sigma_detect : float, optional
        Sample noise of ``x_detect`` (default: measured).
    noise_lag : int
        Samples over which ``x`` is already smoothed (its noise is measured from
        differences that far apart).
    smooth_s : float, optional
        Length of each of the two moving means, s (default ``1.25 period_s``).

    Returns
    -------
    events : list of Event
    xs : ndarray
        ``x`` smoothed over ``fine_s`` (what the windows are judged on).
    levels : Levels or None
        None when the signal holds no step.
    """
    xd = x if x_detect is None else x_detect
    size = x.size
    n = int(round((smooth_s if smooth_s is not None else SMOOTH_PERIODS * period_s) * fs))
    n = max(3, n | 1)  # odd: a centred mean without half-sample shift
    y = moving_mean(moving_mean(xd, n), n)
    xs = moving_mean(x, max(1, int(round(fine_s * fs))))
    sigma = sigma_detect if sigma_detect is not None else noise_sigma(xd, noise_lag)
    lv = _levels(y, n, fs, sigma, min_step)
    if lv is None:
        return [], xs, None
    changes, states = _changes(y, lv, min_dwell=2 * n)
    yt = y if x_detect is None else moving_mean(moving_mean(x, n), n)
    edge = n + int(round(0.05 * fs))
    settle = max(int(round(settle_s * fs)), edge)
    lvl = int(round(level_s * fs))
    fine_reach = n + int(round(0.02 * fs))
    min_size = max(lv.floor, 0.5 * lv.step)
    events: list[Event] = []
    for j, c in enumerate(changes.tolist()):
        up = bool(states[j] == 1)
        left = int(changes[j - 1]) + edge if j > 0 else 0
        right = int(changes[j + 1]) - edge if j + 1 < changes.size else size
        # the smoothed signal's mid crossing: the step's centre to within a half ramp
        pre0, _ = _robust(yt, max(left, c - edge - lvl), c - edge)
        post0, _ = _robust(yt, c + edge, min(right, c + edge + lvl))
        if not (math.isfinite(pre0) and math.isfinite(post0)) or (post0 > pre0) != up:
            continue
        cm = _crossing(yt, 0.5 * (pre0 + post0), max(left, c - 2 * n), min(right, c + 2 * n),
                       up)
        m = int(round(cm)) if cm is not None else c
        # levels either side, clear of the step and (after it) of most of the ring-down
        pre, sp_pre = _robust(yt, max(left, m - edge - lvl), m - edge)
        e1 = m + settle if right - (m + settle) >= int(0.1 * fs) else m + edge
        post, sp_post = _robust(yt, e1, min(right, e1 + lvl))
        if not (math.isfinite(pre) and math.isfinite(post)):
            continue
        step = post - pre
        if (step > 0) != up or abs(step) < min_size:
            continue
        if abs(step) < FLATNESS_FACTOR * (sp_pre + sp_post):
            continue  # a slow drift, not a step
        a, b = max(left, m - fine_reach), min(right, m + fine_reach)
        if np.isnan(xs[max(a, 0):min(b, size)]).any():
            continue  # a dropout where the step is: it cannot be timed
        half = _crossing(xs, pre + 0.5 * step, a, b, up)
        if half is None:
            continue
        i10 = _last_crossing(xs, pre + 0.1 * step, a, int(half) + 1, up)
        i90 = _crossing(xs, pre + 0.9 * step, int(half), b, up)
        rise = (i90 - i10) / fs if i10 is not None and i90 is not None else math.nan
        events.append(Event("bite" if up else "release", half, pre, post, rise))
    return events, xs, lv
