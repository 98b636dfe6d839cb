"""Single shooting: least squares over a simulated window (the fast alternative).

The decision vector holds the free shared parameters and, per window, the
load ramp and the initial state (motor angle fixed); each window is simulated
by the RK4 chain of :mod:`ident.fit.simulator` and its forward sensitivities
give the Jacobian for ``scipy.optimize.least_squares`` (trust-region
reflective, bounds respected).  Same continuation on the smoothing width as
:class:`~ident.fit.collocation.Collocation`.

Where it stands (``benchmarks/bench_fit.py``): cheap per iteration and as
accurate on a single bite; its sensitivities grow along long windows with
rattle, where it needs good starting values.  :func:`ident.fit.fit_gaps` uses
it as the quick mode (``method=SingleShooting()``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import scipy.optimize

from ..errors import FitError
from ..model.dynamics import Family
from .problem import OUT_OF_TIME, Estimate, Problem, SolveInfo, StageInfo
from .simulator import WindowSimulator, build_simulator

__all__ = ["SingleShooting"]


@dataclass(frozen=True)
class SingleShooting:
    """Single-shooting strategy for :func:`ident.fit.fit_gaps`.

    Parameters
    ----------
    n_sub : int
        RK4 steps per sample.
    widths : tuple of float
        Continuation on the g1 smoothing width, rad (last: the reported model's).
    max_nfev : int
        Residual evaluations per stage.
    ftol, xtol, gtol : float
        ``least_squares`` tolerances: relative cost change, relative step and
        first-order optimality (scaled gradient).
    compile : bool
        Compile the sensitivity step to C (cached on disk).
    settle : tuple of float
        Widths of the settling stages (shared parameters held, loads and
        initial states free) :func:`ident.fit.fit_gaps` runs first; see
        :class:`~ident.fit.collocation.Collocation`.
    horizons : tuple of float
        Continuation on the fitted horizon (s after each window's step) at the
        first width, as :class:`~ident.fit.collocation.Collocation`'s.
    """

    n_sub: int = 1
    widths: tuple[float, ...] = (1e-3, 3e-4, 1e-4, 3e-5)
    max_nfev: int = 200
    ftol: float = 1e-8
    xtol: float = 1e-8
    gtol: float = 1e-8
    compile: bool = True
    settle: tuple[float, ...] = (1e-3,)
    horizons: tuple[float, ...] = ()
    _cache: dict = field(default_factory=dict, compare=False, repr=False, hash=False)

    name = "shooting"

    def __post_init__(self) -> None:
        if self.n_sub < 1:
            raise FitError(f"SingleShooting n_sub must be >= 1. Got {self.n_sub}.")
        if not self.widths or any(w <= 0 for w in self.widths):
            raise FitError(f"SingleShooting widths must be positive. Got {self.widths}.")

    def simulator(self, problem: Problem, n_samples: int) -> WindowSimulator:
        m = problem.model
        key = (m.mill.content_hash(), m.family.value, m.shared_names, m.window_names,
               m.measured, tuple(e.name for e in m.effects), n_samples,
               round(problem.dt, 12), self.n_sub)
        got = self._cache.get(key)
        if got is None:
            got = build_simulator(m, n_samples, problem.dt, n_sub=self.n_sub,
                                  compile=self.compile)
            self._cache[key] = got
        return got

    def _layout(self, problem: Problem) -> dict:
        m = problem.model
        free = np.flatnonzero(problem.free_shared)
        x0_free = np.array([i for i in range(m.nx) if i not in m.x0_fixed])
        nper = m.n_window + len(x0_free)
        return {"free": free, "x0_free": x0_free, "nper": nper,
                "n": len(free) + nper * problem.n_windows}

    def _scales(self, problem: Problem, est: Estimate, w0: float) -> tuple[np.ndarray, np.ndarray]:
        m = problem.model
        L = self._layout(problem)
        from .collocation import simulate_estimate

        trajs = est.trajectories if est.trajectories is not None else simulate_estimate(
            problem, est, w=w0)
        mx = np.max(np.abs(np.concatenate(trajs, axis=0)), axis=0)
        n = len(m.mill.masses)
        floor = np.full(m.nx, 1e-6)
        floor[:n] = 1e-4
        floor[n:2 * n] = 1e-3
        floor[2 * n] = 1e-3
        xs = np.maximum(mx, floor)
        s = [m.shared_scale[L["free"]]]
        lb = [m.shared_lb[L["free"]]]
        ub = [m.shared_ub[L["free"]]]
        for i in range(problem.n_windows):
            wl, wu, ws = problem.window_bounds(i)
            s += [ws, xs[L["x0_free"]]]
            lb += [wl, np.full(len(L["x0_free"]), -np.inf)]
            ub += [wu, np.full(len(L["x0_free"]), np.inf)]
        return np.concatenate(s), np.stack([np.concatenate(lb), np.concatenate(ub)])

    def _to_theta(self, problem: Problem, est: Estimate) -> np.ndarray:
        L = self._layout(problem)
        parts = [est.shared[L["free"]]]
        for i in range(problem.n_windows):
            parts += [est.window[i], est.x0[i][L["x0_free"]]]
        return np.concatenate(parts)

    def _from_theta(self, problem: Problem, theta: np.ndarray, base: Estimate) -> Estimate:
        m = problem.model
        L = self._layout(problem)
        shared = base.shared.copy()
        nf = len(L["free"])
        shared[L["free"]] = theta[:nf]
        W = np.empty_like(base.window)
        X0 = base.x0.copy()
        o = nf
        for i in range(problem.n_windows):
            W[i] = theta[o:o + m.n_window]
            X0[i, L["x0_free"]] = theta[o + m.n_window:o + L["nper"]]
            X0[i, list(m.x0_fixed)] = 0.0
            o += L["nper"]
        return Estimate(shared=shared, window=W, x0=X0)

    def residuals(self, problem: Problem, est: Estimate, w: float, *,
                  jacobian: bool = False,
                  horizon: float | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Weighted residuals (sample-major per window) and, optionally, their Jacobian.

        The Jacobian's columns follow the unscaled decision vector: free shared
        parameters, then per window the load parameters and the free initial
        states.  ``horizon`` (s after each window's ``t_step``): later samples
        weigh nothing.
        """
        m = problem.model
        L = self._layout(problem)
        rs = []
        Js = []
        nf = len(L["free"])
        o = nf
        for i, win in enumerate(problem.windows):
            S = self.simulator(problem, win.n_samples)
            wy = 1.0 / problem.y_scale
            wrow = np.tile(wy, win.n_samples)
            if horizon is not None:
                t_rel = np.arange(win.n_samples) * problem.dt
                keep = t_rel <= (win.t_step - win.t[0]) + horizon
                wrow = wrow * np.repeat(keep.astype(float), m.ny)
            if jacobian:
                Y, J = S.jacobian(est.x0[i], est.shared, est.window[i], w)
                J = J * wrow[:, None]
                Jw = np.zeros((J.shape[0], L["n"]))
                Jw[:, :nf] = J[:, m.nx + L["free"]]
                Jw[:, o:o + m.n_window] = J[:, m.nx + m.n_shared:]
                Jw[:, o + m.n_window:o + L["nper"]] = J[:, L["x0_free"]]
                Js.append(Jw)
            else:
                Y, _ = S.simulate(est.x0[i], est.shared, est.window[i], w)
            rs.append((Y - problem.y[i]).ravel() * wrow)
            o += L["nper"]
        r = np.concatenate(rs)
        return r, (np.vstack(Js) if jacobian else None)

    def solve(self, problem: Problem, start: Estimate, *, widths: Sequence[float] | None = None,
              horizons: Sequence[float] | None = None,
              cpu_s: float | None = None) -> tuple[Estimate, SolveInfo]:
        """Fit ``problem`` from ``start``, continuing over the horizons and smoothing widths.

        ``cpu_s`` bounds the CPU seconds of the continuation: no stage begins
        after it ran out (the solve then stops unconverged,
        :data:`~ident.fit.problem.OUT_OF_TIME`).
        """
        t0 = time.perf_counter()
        cpu0 = time.thread_time()
        m = problem.model
        widths = tuple(widths if widths is not None else self.widths)
        if m.family is not Family.G1:
            widths = (widths[-1],)
        for win in problem.windows:
            self.simulator(problem, win.n_samples)
        t_built = time.perf_counter()
        scale, bounds = self._scales(problem, start, widths[0])
        theta = np.clip(self._to_theta(problem, start), bounds[0], bounds[1])
        stages = []
        total = 0
        status, success, cost = "Not_Started", False, math.nan
        est = start
        schedule = [(widths[0], h) for h in (self.horizons if horizons is None else horizons)]
        schedule += [(w, None) for w in widths]
        for w, hz in schedule:
            ts = time.perf_counter()
            if cpu_s is not None and time.thread_time() - cpu0 >= cpu_s:
                status, success = OUT_OF_TIME, False
                break

            def fun(th: np.ndarray) -> np.ndarray:
                r, _ = self.residuals(problem, self._from_theta(problem, th * scale, start), w,
                                      horizon=hz)
                if not np.all(np.isfinite(r)):
                    return np.full_like(r, 1e6)
                return r

            def jac(th: np.ndarray) -> np.ndarray:
                _, J = self.residuals(problem, self._from_theta(problem, th * scale, start), w,
                                      jacobian=True, horizon=hz)
                J = J * scale[None, :]
                return np.where(np.isfinite(J), J, 0.0)

            lb = bounds[0] / scale
            ub = bounds[1] / scale
            x0 = np.clip(theta / scale, lb, ub)
            # least_squares needs strictly feasible starts
            span = np.where(np.isfinite(ub - lb), ub - lb, 1.0)
            x0 = np.clip(x0, lb + 1e-9 * span, ub - 1e-9 * span)
            res = scipy.optimize.least_squares(fun, x0, jac=jac, bounds=(lb, ub),
                                               method="trf", x_scale=1.0, ftol=self.ftol,
                                               xtol=self.xtol, gtol=self.gtol,
                                               max_nfev=self.max_nfev)
            theta = res.x * scale
            cost = float(res.cost)
            success = bool(res.status > 0) and np.isfinite(cost)
            status = {1: "gtol", 2: "ftol", 3: "xtol", 4: "ftol_xtol", 0: "max_nfev",
                      -1: "failed"}.get(int(res.status), str(res.status))
            status = ("Solve_Succeeded" if success else "Maximum_Iterations_Exceeded"
                      if res.status == 0 else "Failed") + f" ({status})"
            it = int(res.njev or 0)
            total += it
            stages.append(StageInfo(width=float(w) if m.family is Family.G1 else None,
                                    status=status, success=success, iterations=it,
                                    seconds=time.perf_counter() - ts, cost=cost,
                                    infeasibility=0.0))
        est = self._from_theta(problem, theta, start)
        from .collocation import simulate_estimate

        trajs = simulate_estimate(problem, est, w=widths[-1], n_sub=self.n_sub)
        est = Estimate(shared=est.shared, window=est.window, x0=est.x0, trajectories=trajs,
                       extra={"width": float(widths[-1])})
        n_par = self._layout(problem)["n"]
        n_res = sum(w.n_samples for w in problem.windows) * m.ny
        info = SolveInfo(method=self.name, status=status, success=success, iterations=total,
                         seconds=time.perf_counter() - t0, cost=cost, stages=tuple(stages),
                         build_seconds=t_built - t0,
                         nlp={"variables": n_par, "residuals": n_res, "n_sub": self.n_sub})
        return est, info
