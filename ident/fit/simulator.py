"""Window simulation of a :class:`~ident.fit.model.FitModel`, symbolic in its parameters.

One fixed-step RK4 chain per window length (``n_sub`` steps per sample), the
load ramp evaluated at every stage, built with CasADi's ``mapaccum`` so that
forward sensitivities (the single-shooting Jacobian) come from the same graph.
Used to initialise collocation states, by single shooting, and to check the
identified model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from .model import FitModel

__all__ = ["WindowSimulator", "build_simulator"]


@dataclass(frozen=True, eq=False)
class WindowSimulator:
    """Simulation of one window length.

    Attributes
    ----------
    sim : casadi.Function
        ``sim(x0, shared, window, w) -> (Y, X)``: outputs (ny x N, reduced
        torques of the measured elements, N*m) and states (nx x N) at the
        samples, ``t`` counted from the window start.
    jac : casadi.Function
        ``jac(x0, shared, window, w) -> (Y, dy0, dY)``: outputs, the first
        sample's Jacobian and the later samples' (forward sensitivities carried
        as a dense matrix through the RK4 chain); see :meth:`jacobian`.
    """

    n_samples: int
    dt: float
    n_sub: int
    sim: Any
    jac: Any

    def simulate(self, x0: np.ndarray, shared: np.ndarray, window: np.ndarray,
                 w: float) -> tuple[np.ndarray, np.ndarray]:
        """Outputs (N, ny) and states (N, nx) of one window."""
        Y, X = self.sim(x0, shared, window, w)
        return np.asarray(Y).T, np.asarray(X).T

    def jacobian(self, x0: np.ndarray, shared: np.ndarray, window: np.ndarray,
                 w: float) -> tuple[np.ndarray, np.ndarray]:
        """Outputs (N, ny) and their Jacobian, shape (N*ny, nx + n_shared + n_window).

        Rows are sample-major (``row = k*ny + channel``).
        """
        Y, dy0, dY = self.jac(x0, shared, window, w)
        dy0 = np.asarray(dy0)
        ny, npar = dy0.shape
        # column k of dY is vec(dy_{k+1}) of the (ny x npar) block, column-major
        rest = np.asarray(dY).T.reshape(-1, npar, ny).transpose(0, 2, 1).reshape(-1, npar)
        return np.asarray(Y).T, np.vstack([dy0, rest])


def build_simulator(model: FitModel, n_samples: int, dt: float, *, n_sub: int = 1,
                    sensitivities: bool = True, compile: bool = False) -> WindowSimulator:
    """Build the window simulation of ``n_samples`` samples ``dt`` apart.

    Parameters
    ----------
    model : FitModel
    n_samples : int
    dt : float
        Sample interval, s.
    n_sub : int
        RK4 steps per sample.
    sensitivities : bool
        Also build :attr:`WindowSimulator.jac`.
    compile : bool
        Compile the sensitivity step to C (cached on disk; seconds once, then
        about three times faster).
    """
    drv = model.driveline
    nx = drv.n_states
    xs = ca.SX.sym("x", nx)
    tk = ca.SX.sym("t")
    p = ca.SX.sym("p", drv.n_params)
    win = ca.SX.sym("win", model.n_window)
    h = dt / n_sub
    x = xs
    for i in range(n_sub):
        t = tk + i * h
        k1 = drv.rhs(x, model.load(t, win), p, t)
        k2 = drv.rhs(x + 0.5 * h * k1, model.load(t + 0.5 * h, win), p, t + 0.5 * h)
        k3 = drv.rhs(x + 0.5 * h * k2, model.load(t + 0.5 * h, win), p, t + 0.5 * h)
        k4 = drv.rhs(x + h * k3, model.load(t + h, win), p, t + h)
        x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    y = model.y(x, model.load(tk + dt, win), p, tk + dt, win)
    step = ca.Function("step", [xs, tk, p, win], [x, y])
    acc = step.mapaccum("acc", n_samples - 1, [0], [0])

    x0 = ca.MX.sym("x0", nx)
    shared = ca.MX.sym("shared", model.n_shared)
    window = ca.MX.sym("window", model.n_window)
    w = ca.MX.sym("w")
    pp = model.pmap(shared, window, w)
    tgrid = ca.DM(np.arange(n_samples - 1)[None, :] * dt)
    Xn, Yn = acc(x0, tgrid, pp, window)
    y0 = model.y(x0, model.load(0.0, window), pp, 0.0, window)
    sim = ca.Function("sim", [x0, shared, window, w], [ca.horzcat(y0, Yn), ca.horzcat(x0, Xn)])
    if not sensitivities:
        return WindowSimulator(n_samples=n_samples, dt=dt, n_sub=n_sub, sim=sim, jac=None)

    # forward sensitivities carried as a dense matrix S = dx/d[x0; shared; window]
    sh = ca.SX.sym("shared", model.n_shared)
    ws = ca.SX.sym("w")
    theta = ca.vertcat(sh, win)
    npar = nx + theta.numel()
    Ssym = ca.SX.sym("S", nx, npar)
    ps = model.pmap(sh, win, ws)
    xn, yn = step(xs, tk, ps, win)
    Jx = ca.jacobian(xn, xs)
    Jt = ca.jacobian(xn, theta)
    Sn = ca.mtimes(Jx, Ssym) + ca.horzcat(ca.SX(nx, nx), Jt)
    xa = ca.SX.sym("xa", nx)
    ya = model.y(xa, model.load(tk + dt, win), ps, tk + dt, win)
    yjac = ca.Function("yjac", [xa, tk, sh, win, ws],
                       [ca.jacobian(ya, xa), ca.jacobian(ya, theta)])
    yx, yt = yjac(xn, tk, sh, win, ws)
    dyn = ca.mtimes(yx, Sn) + ca.horzcat(ca.SX(yn.numel(), nx), yt)
    step_s = ca.Function("step_s", [ca.vertcat(xs, ca.vec(Ssym)), tk, sh, win, ws],
                         [ca.vertcat(xn, ca.vec(Sn)), yn, ca.vec(dyn)])
    if compile:
        step_s = _compiled(step_s) or step_s
    acc_s = step_s.mapaccum("acc_s", n_samples - 1, [0], [0])
    S0 = ca.horzcat(ca.DM.eye(nx), ca.DM(nx, npar - nx))
    _, Yn_s, dY = acc_s(ca.vertcat(x0, ca.vec(S0)), tgrid, shared, window, w)
    y0s = model.y(x0, model.load(0.0, window), pp, 0.0, window)
    dy0 = ca.jacobian(y0s, ca.vertcat(x0, shared, window))
    jac = ca.Function("simjac", [x0, shared, window, w], [ca.horzcat(y0s, Yn_s), dy0, dY])
    return WindowSimulator(n_samples=n_samples, dt=dt, n_sub=n_sub, sim=sim, jac=jac)


def _compiled(fn: Any) -> Any:
    """``fn`` generated as C and compiled (cached on disk), or None without a compiler."""
    from ..model.integrate import _compile

    return _compile(fn, "ident_fit_" + fn.name())
