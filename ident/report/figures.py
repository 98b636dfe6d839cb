"""The report's plots: matplotlib (Agg, no pyplot state) figures as embedded PNG data URIs.

Every function takes plain arrays and returns ``data:image/png;base64,...`` so
that the HTML is one self-contained file.
"""

from __future__ import annotations

import base64
import io
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .trend import Crossing, Trend

__all__ = ["png_uri", "GapPanel", "gap_trends", "taf_vs_static", "mode_trends",
           "STATUS_COLORS"]

STATUS_COLORS = {"critical": "#c62828", "worn": "#ef8f00", "good": "#2e7d32",
                 "unknown": "#9e9e9e"}
_WORN, _CRIT = "#ef8f00", "#c62828"
#: A trend panel is drawn on to a limit crossing at most this far past the data, days.
_MAX_AHEAD_DAYS = 180.0


def png_uri(fig: Figure, *, dpi: int = 96) -> str:
    """Render ``fig`` to a PNG data URI (no metadata that names a web site)."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi,
                metadata={"Software": None})
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


@dataclass(frozen=True)
class GapPanel:
    """One element's (or bearing's) trend panel.

    Attributes
    ----------
    title : str
    unit : str
        Display unit of ``y`` (``mm``, ``mrad``).
    t, y, lo, hi : ndarray
        Days since the report's reference time; value and its 95 % interval (NaN
        where unknown).
    worn, critical : float
        Limits in the display unit.
    trend : Trend or None
    worn_at, critical_at : Crossing or None
    status : str
        ``good``, ``worn``, ``critical`` or ``unknown`` (frame colour).
    horizon : float
        Days the trend line is drawn past the last point.
    note : str
        A line under the title (e.g. "not identifiable").
    rejected_t, rejected_y : ndarray
        Fits that did not identify the gap (days, display unit): drawn hollow,
        never part of the trend.
    quantity : str
        What ``y`` is, for the axis label (e.g. "gap at r = 0.5 m").
    evidence : str
        Legend of the points: what they are (an identified gap, a regressed value).
    """

    title: str
    unit: str
    t: np.ndarray
    y: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    worn: float
    critical: float
    trend: Trend | None
    worn_at: Crossing | None
    critical_at: Crossing | None
    status: str
    horizon: float
    note: str = ""
    rejected_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rejected_y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    quantity: str = ""
    evidence: str = "identified (95 % CI)"


def _date_axis(ax, t0_ns: int) -> None:
    """Label a days axis with calendar dates (UTC)."""
    import datetime as dt

    from matplotlib.ticker import FuncFormatter, MaxNLocator

    base = dt.datetime.fromtimestamp(t0_ns / 1e9, dt.timezone.utc)

    def fmt(x, _pos):
        return (base + dt.timedelta(days=float(x))).strftime("%d %b\n%Y")

    ax.xaxis.set_major_locator(MaxNLocator(5))
    ax.xaxis.set_major_formatter(FuncFormatter(fmt))


def _y_range(p: GapPanel) -> tuple[float, float]:
    """Both limits, every identified value with its interval, rejected fits up to 2x critical."""
    top = [p.critical * 1.12]
    if np.isfinite(p.hi).any():
        top.append(float(np.nanmax(p.hi)))
    if np.isfinite(p.y).any():
        top.append(float(np.nanmax(p.y)) * 1.05)
    rej = p.rejected_y[np.isfinite(p.rejected_y)]
    if rej.size:
        top.append(min(float(rej.max()) * 1.05, 2.0 * p.critical))
    bottom = [0.0]
    if np.isfinite(p.lo).any():
        bottom.append(float(np.nanmin(p.lo)))
    return min(bottom), max(top)


def gap_trends(panels: Sequence[GapPanel], *, t0_ns: int, ncols: int = 2) -> str:
    """Small multiples of gap (or clearance) trends with limits and forecasts."""
    n = max(len(panels), 1)
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(5.2 * ncols, 3.1 * nrows), layout="constrained")
    for k, p in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        for side in ax.spines.values():
            side.set_edgecolor(STATUS_COLORS.get(p.status, "#9e9e9e"))
            side.set_linewidth(2.0)
        t_end = (p.t.max() if p.t.size else 0.0) + p.horizon
        t_max = (p.t.max() if p.t.size else 0.0) + _MAX_AHEAD_DAYS
        for c in (p.worn_at, p.critical_at):
            if c is not None and c.trend and t_end < c.t <= t_max:
                t_end = c.t + 0.1 * p.horizon
        if p.trend is not None and p.trend.n >= 3:
            tt = np.linspace(p.trend.t_first, t_end, 200)
            lo, hi = p.trend.band(tt)
            ax.fill_between(tt, lo, hi, color="#1565c0", alpha=0.15, lw=0,
                            label="trend, 95 % band")
            ax.plot(tt, p.trend.predict(tt), color="#1565c0", lw=1.2)
        # an estimate on its bound can sit a rounding error outside its interval
        err = np.maximum(np.vstack([p.y - p.lo, p.hi - p.y]), 0.0)
        has_err = np.isfinite(err).all(axis=0)
        if has_err.any():
            ax.errorbar(p.t[has_err], p.y[has_err], yerr=err[:, has_err], fmt="o", ms=3.5,
                        color="#263238", ecolor="#90a4ae", elinewidth=1, capsize=0,
                        label=p.evidence)
        if (~has_err).any():
            ax.plot(p.t[~has_err], p.y[~has_err], "o", ms=3.5, color="#263238",
                    label=None if has_err.any() else "value")
        rej = np.isfinite(p.rejected_t) & np.isfinite(p.rejected_y)
        if rej.any():
            ax.plot(p.rejected_t[rej], p.rejected_y[rej], "o", ms=4.5, mfc="none",
                    mec="#78909c", mew=1.0, label="not identified (not in the trend)")
        ax.axhline(p.worn, color=_WORN, ls="--", lw=1.2, label="worn limit")
        ax.axhline(p.critical, color=_CRIT, ls="--", lw=1.2, label="critical limit")
        for c, col in ((p.worn_at, _WORN), (p.critical_at, _CRIT)):
            if c is None or not c.trend or not math.isfinite(c.t) or c.t > t_end:
                continue
            late = c.t_late if math.isfinite(c.t_late) else t_end
            if math.isfinite(c.t_early):
                ax.axvspan(max(c.t_early, p.trend.t_first), min(late, t_end), color=col,
                           alpha=0.10, lw=0)
            ax.axvline(c.t, color=col, lw=1.0)
        ax.set_ylim(*_y_range(p))
        t_lo = min([0.0, *(p.t.tolist()), *(p.rejected_t[rej].tolist())])
        ax.set_xlim(t_lo - 0.5, t_end)
        ax.set_title(p.title + (f"\n{p.note}" if p.note else ""), fontsize=9.5, loc="left")
        ax.set_ylabel(f"{p.quantity or 'value'}, {p.unit}", fontsize=8.5)
        ax.set_xlabel("recording date (UTC)", fontsize=8.5)
        ax.grid(alpha=0.3)
        _date_axis(ax, t0_ns)
        ax.tick_params(labelsize=8)
        if k == 0:
            ax.legend(fontsize=7, loc="upper left")
    return png_uri(fig)


def taf_vs_static(static_knm: np.ndarray, peak_knm: np.ndarray, taf: np.ndarray,
                  days: np.ndarray, *, t0_ns: int, element: str) -> str:
    """Seed Fig. 4 from the measurements: peak torque and TAF against static torque.

    Points are coloured by recording date, so a drift with wear shows.
    """
    fig = Figure(figsize=(10.4, 3.6), layout="constrained")
    a1 = fig.add_subplot(1, 2, 1)
    a2 = fig.add_subplot(1, 2, 2)
    vmin = float(np.nanmin(days)) if days.size else 0.0
    vmax = float(np.nanmax(days)) if days.size else 1.0
    kw = dict(c=days, cmap="viridis", s=9, vmin=vmin, vmax=max(vmax, vmin + 1e-9), alpha=0.8,
              edgecolors="none")
    a1.scatter(static_knm, peak_knm, **kw)
    sc = a2.scatter(static_knm, taf, **kw)
    a1.set_xlabel("static torque $M_{st}$, kN·m (motor shaft)")
    a1.set_ylabel("peak torque $M_{max}$, kN·m")
    a2.set_xlabel("static torque $M_{st}$, kN·m (motor shaft)")
    a2.set_ylabel("TAF = $M_{max}/M_{st}$")
    a1.set_title(f"{element}: peak torque after the bite", fontsize=9.5, loc="left")
    a2.set_title(f"{element}: torque amplification factor", fontsize=9.5, loc="left")
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
    cb = fig.colorbar(sc, ax=[a1, a2], shrink=0.9, pad=0.01)
    cb.set_label("recording date", fontsize=8)
    import datetime as dt

    base = dt.datetime.fromtimestamp(t0_ns / 1e9, dt.timezone.utc)
    ticks = np.linspace(vmin, vmax, 4) if vmax > vmin else np.array([vmin])
    cb.set_ticks(ticks)
    cb.set_ticklabels([(base + dt.timedelta(days=float(x))).strftime("%d %b %Y") for x in ticks])
    cb.ax.tick_params(labelsize=7)
    return png_uri(fig)


def mode_trends(series: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray]], *,
                t0_ns: int) -> str:
    """Amplitude ratio and phase shift per natural frequency against time.

    ``series`` holds ``(label, days, amplitude_ratio, phase_shift_deg)`` per mode.
    """
    fig = Figure(figsize=(10.4, 3.4), layout="constrained")
    a1 = fig.add_subplot(1, 2, 1)
    a2 = fig.add_subplot(1, 2, 2)
    for label, d, amp, ph in series:
        order = np.argsort(d)
        a1.plot(d[order], amp[order], "o-", ms=3, lw=1, label=label)
        a2.plot(d[order], ph[order], "o-", ms=3, lw=1, label=label)
    a1.axhline(1.0, color="k", lw=0.8, alpha=0.5)
    a2.axhline(0.0, color="k", lw=0.8, alpha=0.5)
    # a ratio: on a log axis 2x and 1/2 look alike, and one recording at 300x (a mode the
    # linear baseline barely excites) no longer flattens every other point to the axis
    if any((np.asarray(amp, float) > 0).any() for _, _, amp, _ in series):
        a1.set_yscale("log")
    a1.set_ylabel("amplitude ratio (measured / linear)")
    a2.set_ylabel("phase shift, deg")
    a1.set_title("amplitude at the natural frequencies", fontsize=9.5, loc="left")
    a2.set_title("phase at the natural frequencies", fontsize=9.5, loc="left")
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
        _date_axis(ax, t0_ns)
        ax.set_xlabel("recording date (UTC)", fontsize=8.5)
        ax.tick_params(labelsize=8)
    if series:
        a2.legend(fontsize=7, ncol=2, loc="best")
    return png_uri(fig)
