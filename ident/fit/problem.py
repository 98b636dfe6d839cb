"""A fit problem (model + windows + weights) and a point in its parameter space.

Both strategies (``collocation``, ``shooting``) take a :class:`Problem` and an
:class:`Estimate` to start from and return an :class:`Estimate` with a
:class:`SolveInfo`.  Residuals are weighted per channel by the inverse of the
channel's standard deviation over all windows, so every torque counts alike.
"""

from __future__ import annotations

import math

from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from .model import RAMP_PARAMS, RAMP_WEIGHT_MAX, FitModel, static_state
from .windows import FitWindow

__all__ = ["Problem", "Estimate", "SolveInfo", "StageInfo", "make_problem", "initial_estimate",
           "OFFSET_MAX", "SKEW_MAX", "IDLE_LEVEL_TOL", "IDLE_SLOPE_MAX"]

#: Bound of a channel's offset over a window, as a fraction of the channel's largest
#: reading there: zero offsets of 0-2 % plus drift and random walk of 1-2 % are what
#: plants record (validation.plantsim draws up to 3.5 % of the rolling torque).
OFFSET_MAX = 0.05

#: Largest skew of a load ramp (1 would stop the warped time at one end).
SKEW_MAX = 0.9

#: On the idle side of a step the load stays within this fraction of the step of the
#: segmenter's idle level ...
IDLE_LEVEL_TOL = 0.1
#: ... and changes by at most this fraction of the step per second.
IDLE_SLOPE_MAX = 0.5


@dataclass(frozen=True, eq=False)
class Problem:
    """What is fitted.

    Attributes
    ----------
    model : FitModel
    windows : tuple of FitWindow
        Each window's columns reordered to ``model.measured``.
    y : tuple of ndarray
        Per window, shape (N_w, ny): measured reduced torques, N*m.
    y_scale : ndarray, shape (ny,)
        Per channel standard deviation over all windows, N*m (residual weights 1/y_scale).
    free_shared : ndarray of bool, shape (n_shared,)
        Shared parameters the fit may move (others stay at the start's value).
    """

    model: FitModel
    windows: tuple[FitWindow, ...]
    y: tuple[np.ndarray, ...]
    y_scale: np.ndarray
    free_shared: np.ndarray

    @property
    def n_windows(self) -> int:
        return len(self.windows)

    @property
    def dt(self) -> float:
        return self.windows[0].dt

    @property
    def lengths(self) -> tuple[int, ...]:
        return tuple(w.n_samples for w in self.windows)

    def with_free(self, free_shared: np.ndarray) -> "Problem":
        return replace(self, free_shared=np.asarray(free_shared, dtype=bool))

    def window_bounds(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lower and upper bounds and scales of window ``i``'s parameters (window-relative time)."""
        w = self.windows[i]
        tref = float(np.max(np.abs(self.y[i]))) if self.y[i].size else 1.0
        tref = max(tref, 1.0)
        ts = w.t_step - w.t[0]
        dur = w.t[-1] - w.t[0]
        lb = [-3 * tref, -3 * tref, max(ts - 0.08, -0.05), 2e-3, -2 * tref, -2 * tref]
        ub = [3 * tref, 3 * tref, min(ts + 0.08, dur), 0.12, 2 * tref, 2 * tref]
        sc = [tref, tref, 0.01, 0.01, 0.1 * tref, 0.1 * tref]
        if not self.model.nuisance:
            return self._extra_bounds(i, lb, ub, sc)
        # the idle side (before a bite, after a release): no bar in the stand, so the
        # rolls' load stays near the idle level the segmenter read off the plateau
        # and nearly constant.  Free, a fit can drive a floating roll through its gap
        # with a load no idle mill has (cold-s5: -9 kN*m rising at 3 steps/s).
        step = max(abs(w.level_after - w.level_before), 0.05 * tref)
        li, si = (0, 4) if w.kind == "bite" else (1, 5)
        idle = w.level_before if w.kind == "bite" else w.level_after
        lb[li], ub[li] = idle - IDLE_LEVEL_TOL * step, idle + IDLE_LEVEL_TOL * step
        lb[si], ub[si] = -IDLE_SLOPE_MAX * step, IDLE_SLOPE_MAX * step
        return self._extra_bounds(i, lb, ub, sc)

    def _extra_bounds(self, i: int, lb: list, ub: list, sc: list
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Append the bounds of window ``i``'s parameters after the load ramp's."""
        for _ in self.model.kgap_elements:
            lb.append(0.0)
            ub.append(1.0)
            sc.append(1.0)
        if "skew" in self.model.window_names:
            lb.append(-SKEW_MAX)  # the ramp's skew (ident.fit.model.skewed_cosine)
            ub.append(SKEW_MAX)
            sc.append(0.3)
        for nm in RAMP_PARAMS:
            if nm in self.model.window_names:
                lb.append(0.0)  # the ramp's shape weights (ident.fit.model.ramp_shape)
                ub.append(RAMP_WEIGHT_MAX)
                sc.append(1.0)
        for c, _ in enumerate(self.model.offset_index):
            # a strain gauge's zero and drift: a few per cent of the channel's largest reading
            ref = max(float(np.max(np.abs(self.y[i][:, c]))) if self.y[i].size else 1.0, 1.0)
            lb.append(-OFFSET_MAX * ref)
            ub.append(OFFSET_MAX * ref)
            sc.append(0.01 * ref)
        return np.array(lb), np.array(ub), np.array(sc)


@dataclass(frozen=True, eq=False)
class Estimate:
    """A point of the fit's parameter space.

    Attributes
    ----------
    shared : ndarray, shape (n_shared,)
    window : ndarray, shape (n_windows, n_window)
        Load parameters (``t_step`` relative to the window start, s).
    x0 : ndarray, shape (n_windows, nx)
        Initial states (motor angle 0).
    trajectories : tuple of ndarray or None
        Optional state trajectories per window, shape (N_w, nx), at the samples
        (collocation warm start).
    """

    shared: np.ndarray
    window: np.ndarray
    x0: np.ndarray
    trajectories: tuple[np.ndarray, ...] | None = None
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class StageInfo:
    """One continuation stage of a solve.

    ``infeasibility`` is the largest constraint violation at the stage's end
    (IPOPT's ``inf_pr``, scaled collocation defects; 0 for single shooting,
    NaN where the solver did not say).
    """

    width: float | None
    status: str
    success: bool
    iterations: int
    seconds: float
    cost: float
    infeasibility: float = math.nan


#: Status of a solve its ``cpu_s`` bound stopped (IPOPT's own for ``max_cpu_time``).
OUT_OF_TIME = "Maximum_CpuTime_Exceeded"


@dataclass(frozen=True)
class SolveInfo:
    """How a solve went (over its continuation stages).

    ``cost`` is half the sum of squared weighted residuals at the end.
    """

    method: str
    status: str
    success: bool
    iterations: int
    seconds: float
    cost: float
    stages: tuple[StageInfo, ...] = ()
    build_seconds: float = 0.0
    nlp: dict = field(default_factory=dict)


def make_problem(model: FitModel, windows: Sequence[FitWindow]) -> Problem:
    """Bind windows to a model: order channels, compute weights, check sampling.

    Raises
    ------
    ident.errors.FitError
        No window, windows at different sample rates, or a window missing one
        of the model's measured elements.
    """
    from ..errors import FitError

    windows = tuple(windows)
    if not windows:
        raise FitError("fit_gaps needs at least one FitWindow. Got none.")
    dt = windows[0].dt
    ys = []
    for w in windows:
        if abs(w.dt - dt) > 1e-6 * dt:
            raise FitError(f"all windows must share one sample rate. Got {1 / dt:.1f} Hz and "
                           f"{w.rate_hz:.1f} Hz ({w.label!r}).")
        missing = [e for e in model.measured if e not in w.elements]
        if missing:
            raise FitError(f"window {w.label!r} lacks torques of {missing}; expected all of "
                           f"{list(model.measured)} (the mill's torque channels).")
        ys.append(w.y[:, [w.elements.index(e) for e in model.measured]])
    allv = np.concatenate(ys, axis=0)
    scale = allv.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    return Problem(model=model, windows=windows, y=tuple(ys), y_scale=scale,
                   free_shared=np.ones(model.n_shared, dtype=bool))


def initial_estimate(problem: Problem, shared: np.ndarray, *, open_frac: float = 0.5,
                     window: np.ndarray | None = None) -> Estimate:
    """Start from the segmenter's load estimates and rest states under the level before the step.

    Parameters
    ----------
    shared : ndarray, shape (n_shared,)
    open_frac : float
        Where an unloaded element starts in its gap, as a fraction of the gap
        from the drive-side contact.
    window : ndarray, optional
        Load parameters to use instead of the segmenter's.
    """
    m = problem.model
    nw = problem.n_windows
    W = np.zeros((nw, m.n_window))
    X0 = np.zeros((nw, m.nx))
    for i, w in enumerate(problem.windows):
        if window is not None:
            W[i] = window[i]
        else:
            W[i, :6] = [w.level_before, w.level_after, w.t_step - w.t[0] - 0.003, 0.02, 0.0, 0.0]
            W[i, 6:6 + len(m.kgap_elements)] = 0.5
        lb, ub, _ = problem.window_bounds(i)
        W[i] = np.clip(W[i], lb, ub)
        X0[i] = static_state(m, float(W[i, 0]), shared, W[i], open_frac=open_frac)
    return Estimate(shared=np.asarray(shared, dtype=float).copy(), window=W, x0=X0)
