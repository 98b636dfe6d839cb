"""Wear trends and when they reach a limit: weighted linear regression and Fieller's interval.

A gap (or clearance) identified recording after recording, ``y_i`` at times
``t_i`` with standard errors ``s_i``, is fitted by weighted least squares,
``y = a + b t``, with weights ``1/s_i**2`` taken as *relative*: the scale is
estimated from the scatter about the line (``n - 2`` degrees of freedom), so
that over- or under-confident intervals of single fits do not make the trend
over- or under-confident.

The time the *trend* reaches a limit ``L`` is ``t* = (L - a)/b``.  Its 95 %
interval is Fieller's: the times at which the 95 % confidence band of the line
(not the wider band for a single new fit, which mostly reflects identification
noise) crosses ``L``.  The earliest is where the upper band reaches ``L``, the
latest where the lower band does.  When the slope is not significantly positive
(one-sided ``p >= 0.05``) the interval is unbounded: the report says "no trend".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

__all__ = ["Trend", "Crossing", "fit_trend", "crossing"]


@dataclass(frozen=True)
class Trend:
    """A fitted linear trend ``y = intercept + slope * t``.

    Attributes
    ----------
    intercept, slope : float
        In the units of ``y`` and ``y`` per unit of ``t``.
    cov : ndarray, shape (2, 2)
        Covariance of ``(intercept, slope)``.
    n : int
        Number of points.
    dof : int
        Residual degrees of freedom, ``n - 2``.
    p_increasing : float
        One-sided p-value of ``slope <= 0``; NaN with fewer than 3 points.
    t_first, t_last : float
        Range of the data's times.
    """

    intercept: float
    slope: float
    cov: np.ndarray
    n: int
    dof: int
    p_increasing: float
    t_first: float
    t_last: float

    def significant(self, alpha: float = 0.05) -> bool:
        """Whether the slope is significantly positive at level ``alpha``."""
        return self.n >= 3 and math.isfinite(self.p_increasing) and self.p_increasing < alpha

    def predict(self, t: np.ndarray | float) -> np.ndarray:
        """The line at ``t``."""
        return self.intercept + self.slope * np.asarray(t, dtype=float)

    def band(self, t: np.ndarray | float, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper ``level`` confidence band of the line at ``t``."""
        t = np.asarray(t, dtype=float)
        var = self.cov[0, 0] + 2 * self.cov[0, 1] * t + self.cov[1, 1] * t ** 2
        q = _tq(self.dof, level)
        half = q * np.sqrt(np.maximum(var, 0.0))
        y = self.predict(t)
        return y - half, y + half


@dataclass(frozen=True)
class Crossing:
    """When a trend reaches a limit.

    Attributes
    ----------
    t : float
        Time the fitted line reaches the limit; NaN without a significant rising trend.
    t_early, t_late : float
        95 % interval (Fieller); ``t_late`` is inf when the lower band never reaches
        the limit, and both are NaN without a trend.
    reached : bool
        The line is at or above the limit at the last data time.
    trend : bool
        The slope is significantly positive.
    """

    t: float
    t_early: float
    t_late: float
    reached: bool
    trend: bool


def _tq(dof: int, level: float) -> float:
    return float(stats.t.ppf(0.5 + level / 2, dof)) if dof > 0 else math.inf


def fit_trend(t: np.ndarray, y: np.ndarray, *, sigma: np.ndarray | None = None) -> Trend | None:
    """Weighted least-squares line through ``(t, y)``.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Times (e.g. days).
    y : ndarray, shape (n,)
        Values (e.g. gap in mm).
    sigma : ndarray, shape (n,), optional
        Standard errors of ``y``, used as relative weights ``1/sigma**2``; missing,
        zero or non-finite entries get the median of the others.

    Returns
    -------
    Trend or None
        None with fewer than 2 points or a single distinct time.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = np.isfinite(t) & np.isfinite(y)
    t, y = t[ok], y[ok]
    n = t.size
    if n < 2 or np.ptp(t) == 0:
        return None
    if sigma is None:
        w = np.ones(n)
    else:
        s = np.asarray(sigma, dtype=float)[ok]
        good = np.isfinite(s) & (s > 0)
        fill = float(np.median(s[good])) if good.any() else 1.0
        s = np.where(good, s, fill)
        w = 1.0 / s ** 2
    w = w / w.mean()
    X = np.column_stack([np.ones(n), t])
    XtW = X.T * w
    A = XtW @ X
    beta = np.linalg.solve(A, XtW @ y)
    r = y - X @ beta
    dof = n - 2
    Ainv = np.linalg.inv(A)
    if dof > 0:
        s2 = float(np.sum(w * r ** 2) / dof)
        cov = s2 * Ainv
        se = math.sqrt(max(cov[1, 1], 0.0))
        if se > 0:
            p = float(stats.t.sf(beta[1] / se, dof))
        else:
            p = 0.0 if beta[1] > 0 else 1.0
    else:
        cov = np.full((2, 2), np.inf)
        p = math.nan
    return Trend(intercept=float(beta[0]), slope=float(beta[1]), cov=cov, n=n, dof=dof,
                 p_increasing=p, t_first=float(t.min()), t_last=float(t.max()))


def crossing(trend: Trend, limit: float, *, level: float = 0.95, alpha: float = 0.05) -> Crossing:
    """When ``trend`` reaches ``limit``, with Fieller's ``level`` interval.

    Solves ``(L - a - b t)**2 = q**2 var(a + b t)`` for ``t``, ``q`` the t quantile;
    the interval is bounded when ``b**2 > q**2 var(b)``, i.e. the slope is
    significant at ``1 - level`` (two-sided).
    """
    reached = bool(trend.predict(trend.t_last) >= limit)
    if not trend.significant(alpha):
        return Crossing(t=math.nan, t_early=math.nan, t_late=math.nan, reached=reached,
                        trend=False)
    a, b = trend.intercept, trend.slope
    c00, c01, c11 = trend.cov[0, 0], trend.cov[0, 1], trend.cov[1, 1]
    t_star = (limit - a) / b
    q2 = _tq(trend.dof, level) ** 2
    d = limit - a
    A = b * b - q2 * c11
    B = -2.0 * (b * d + q2 * c01)
    C = d * d - q2 * c00
    disc = B * B - 4 * A * C
    if A <= 0 or disc < 0:
        # the band's slope is not bounded away from zero at this level: only the
        # early side is defined (where the upper band reaches the limit)
        early = _upper_band_reach(trend, limit, level)
        return Crossing(t=t_star, t_early=early, t_late=math.inf, reached=reached, trend=True)
    r1 = (-B - math.sqrt(disc)) / (2 * A)
    r2 = (-B + math.sqrt(disc)) / (2 * A)
    return Crossing(t=t_star, t_early=min(r1, r2), t_late=max(r1, r2), reached=reached,
                    trend=True)


def _upper_band_reach(trend: Trend, limit: float, level: float) -> float:
    """First time at or after the first data time the upper band reaches ``limit``, or NaN."""
    def f(t: float) -> float:
        return float(trend.band(t, level)[1]) - limit

    span = max(trend.t_last - trend.t_first, 1.0)
    ts = np.linspace(trend.t_first, trend.t_last + 100 * span, 2001)
    vals = np.array([f(x) for x in ts])
    idx = np.nonzero(vals >= 0)[0]
    if idx.size == 0:
        return math.nan
    if idx[0] == 0:
        return float(ts[0])
    lo, hi = float(ts[idx[0] - 1]), float(ts[idx[0]])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if f(mid) >= 0 else (mid, hi)
    return hi
