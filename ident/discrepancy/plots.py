"""Figures of a discrepancy result, saved as PNG beside the JSON.

* ``residuals.png``: held-out residuals per torque channel, every window in
  time order, of the mill file's model (before) and of the model with the
  named (or best refitted) effect (after), as shares of the channel's scale;
* ``spectra.png``: their mean power spectra with the linear baseline's natural
  frequencies and the sidebands at twice the roll speed marked;
* ``candidates.png``: the leading candidates' signature scores and the
  held-out improvement of those refitted;
* ``window.png``: the window the mill file's model misses most, measured
  against both models.

Figures are built on :class:`matplotlib.figure.Figure` with the Agg canvas
(no pyplot state).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..model.linear import natural_modes
from .residuals import residual_spectrum
from .workflow import DiscrepancyResult

__all__ = ["save_plots", "residual_figure", "spectrum_figure", "candidate_figure",
           "window_figure"]


def _figure(w: float, h: float) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _residuals(result: DiscrepancyResult, sims: tuple) -> dict[int, np.ndarray]:
    scales = _scales(result)
    return {i: (s - result.windows[i].columns(result.measured)) / scales for i, s in sims}


def _scales(result: DiscrepancyResult) -> np.ndarray:
    ys = [w.columns(result.measured) for w in result.windows]
    dev = np.concatenate([y - y.mean(axis=0) for y in ys], axis=0)
    s = np.sqrt(np.mean(dev ** 2, axis=0))
    return np.where(s > 0, s, 1.0)


def _title(result: DiscrepancyResult) -> str:
    if result.explained:
        return (f"{result.effect} at {result.location}: held-out nrmse {result.before:.3f} -> "
                f"{result.after:.3f}")
    best = result.best_refit()
    extra = f" (best candidate {best.key}: {best.nrmse:.3f})" if best else ""
    return f"nothing named: held-out nrmse {result.before:.3f}{extra}"


def residual_figure(result: DiscrepancyResult) -> Any:
    """Held-out residuals before and after, per channel (see the module docstring)."""
    before = _residuals(result, result.sims_before)
    best = result.best_refit()
    after = _residuals(result, best.sims) if best is not None else {}
    ny = len(result.measured)
    fig = _figure(11, 1.9 * ny + 0.8)
    axes = fig.subplots(ny, 1, sharex=True, squeeze=False)[:, 0]
    order = sorted(before)
    n = result.windows[0].n_samples
    x = np.arange(n) * result.windows[0].dt
    for j, (ax, e) in enumerate(zip(axes, result.measured)):
        for k, i in enumerate(order):
            off = k * (x[-1] + 0.08)
            ax.plot(off + x, before[i][:, j], color="0.55", lw=0.7,
                    label="mill file's model" if k == 0 else None)
            if i in after:
                ax.plot(off + x, after[i][:, j], color="C3", lw=0.7,
                        label=(f"with {best.key}" if k == 0 else None))
            if j == 0:
                ax.text(off + 0.01, 1.0, result.windows[i].label, transform=ax.get_xaxis_transform(),
                        fontsize=7, va="bottom")
        ax.set_ylabel(f"{e}\n(share)")
        ax.axhline(0, color="k", lw=0.4)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("held-out windows, s from each window's start")
    fig.suptitle("Held-out residuals: " + _title(result), fontsize=10)
    return fig


def spectrum_figure(result: DiscrepancyResult) -> Any:
    """Mean residual power spectra before and after, modes and 2x roll sidebands marked."""
    fig = _figure(9, 4)
    ax = fig.subplots()
    before = _residuals(result, result.sims_before)
    idx = sorted(before)
    wins = [result.windows[i] for i in idx]
    f, P = residual_spectrum(wins, [before[i] for i in idx])
    ax.semilogy(f, P, color="0.4", lw=1, label="mill file's model")
    best = result.best_refit()
    if best is not None:
        after = _residuals(result, best.sims)
        f2, P2 = residual_spectrum(wins, [after[i] for i in idx])
        ax.semilogy(f2, P2, color="C3", lw=1, label=f"with {best.key}")
    mill = result.mill
    load = set(mill.load.masses)
    ratios = [e.ratio for e in mill.elements if e.to in load or e.from_ in load] or [1.0]
    roll2 = 2 * mill.motor_speed / (2 * math.pi) / float(np.median(ratios))
    for k, fm in enumerate(natural_modes(mill).frequencies_hz):
        ax.axvline(fm, color="C0", lw=0.8, ls="--", label="linear modes" if k == 0 else None)
        if k < 2:
            for s in (-1, 1):
                ax.axvline(fm + s * roll2, color="C2", lw=0.6, ls=":",
                           label="mode +- 2x roll speed" if (k == 0 and s < 0) else None)
    ax.set_xlim(0, min(150.0, float(f[-1])))
    ax.set_xlabel("frequency, Hz")
    ax.set_ylabel("residual power (normalised)")
    ax.legend(fontsize=8)
    ax.set_title("Residual spectra on held-out windows: " + _title(result), fontsize=10)
    return fig


def candidate_figure(result: DiscrepancyResult, *, top: int = 12) -> Any:
    """Signature scores of the leading candidates and the refits' held-out improvement."""
    fig = _figure(9, 4.5)
    ax1, ax2 = fig.subplots(1, 2, width_ratios=[3, 2])
    cands = list(result.candidates[:top])[::-1]
    ax1.barh([c.key for c in cands], [max(c.score, 1e-3) for c in cands], color="C0")
    ax1.set_xscale("log")
    ax1.set_xlabel("signature score")
    ax1.tick_params(axis="y", labelsize=7)
    refs = list(result.refits)[::-1]
    ax2.barh([r.key for r in refs], [100 * r.improvement for r in refs],
             color=["C3" if (r.effect, r.location) == (result.effect, result.location) else "0.6"
                    for r in refs])
    ax2.axvline(100 * result.rule.min_improvement, color="k", ls="--", lw=0.8,
                label="naming threshold")
    ax2.set_xlabel("held-out nrmse drop, %")
    ax2.tick_params(axis="y", labelsize=7)
    ax2.legend(fontsize=7)
    fig.suptitle(_title(result), fontsize=10)
    return fig


def window_figure(result: DiscrepancyResult) -> Any:
    """The window and channel the mill file's model misses most: data, before, after."""
    before = dict(result.sims_before)
    scales = _scales(result)
    worst, wj, wv = None, 0, -1.0
    for i, s in before.items():
        r = (s - result.windows[i].columns(result.measured)) / scales
        v = np.sqrt(np.mean(r ** 2, axis=0))
        if v.max() > wv:
            worst, wj, wv = i, int(np.argmax(v)), float(v.max())
    w = result.windows[worst]
    fig = _figure(9, 4)
    ax = fig.subplots()
    ax.plot(w.t, w.columns(result.measured)[:, wj] / 1e3, color="k", lw=0.8, label="measured")
    ax.plot(w.t, before[worst][:, wj] / 1e3, color="0.55", lw=1, label="mill file's model")
    best = result.best_refit()
    if best is not None:
        after = dict(best.sims)
        ax.plot(w.t, after[worst][:, wj] / 1e3, color="C3", lw=1, label=f"with {best.key}")
    ax.set_xlabel("time, s")
    ax.set_ylabel(f"torque {result.measured[wj]}, kN*m (reduced)")
    ax.legend(fontsize=8)
    ax.set_title(f"{w.label}, held out: " + _title(result), fontsize=10)
    return fig


def save_plots(result: DiscrepancyResult, directory: str | Path, *,
               prefix: str = "") -> tuple[Path, ...]:
    """Write ``residuals.png``, ``spectra.png``, ``candidates.png`` and ``window.png``.

    Parameters
    ----------
    result : DiscrepancyResult
    directory : str or Path
        Created if missing.
    prefix : str
        Prepended to every file name (e.g. the recording's stem and ``_``).

    Returns
    -------
    tuple of Path
        The files written.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for name, make in (("residuals", residual_figure), ("spectra", spectrum_figure),
                       ("candidates", candidate_figure), ("window", window_figure)):
        fig = make(result)
        path = d / f"{prefix}{name}.png"
        fig.savefig(path, dpi=110)
        out.append(path)
    return tuple(out)
