"""An independent reference simulator for tests and benchmarks.

Written from the mill-config.md contract only -- numpy right-hand side, scipy's
``solve_ivp`` -- without using ``ident.model.dynamics`` or ``ident.model.laws``,
so that agreement with ident's compiled simulator is evidence, not tautology.
Torsional model only (no bearings, g1 laws, PI speed loop).
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp


def reference_rhs(mill):
    """Return ``f(t, x, load)`` for states [theta(n), omega(n), z]."""
    ids = [m.id for m in mill.masses]
    n = len(ids)
    J = np.array([m.J for m in mill.masses])
    fr = np.array([ids.index(e.from_) for e in mill.elements])
    to = np.array([ids.index(e.to) for e in mill.elements])
    k = np.array([e.k for e in mill.elements])
    c = np.array([e.c for e in mill.elements])
    a = np.array([e.gap - e.gap_open for e in mill.elements])
    b = np.array([e.gap_open for e in mill.elements])
    im = ids.index(mill.motor.mass)
    share = np.zeros(n)
    for mid, s in zip(mill.load.masses, mill.load.share):
        share[ids.index(mid)] += s
    kp, ki, lim = mill.motor.kp, mill.motor.ki, mill.motor.torque_limit

    def f(t, x, load):
        th, w, z = x[:n], x[n:2 * n], x[2 * n]
        d = th[fr] - th[to]
        dd = w[fr] - w[to]
        g = np.where(d > b, k * (d - b), np.where(d < -a, k * (d + a), 0.0))
        tau = g + c * dd
        Tm = -kp * w[im] + ki * z
        if lim is not None:
            Tm = min(max(Tm, -lim), lim)
        acc = np.zeros(n)
        np.add.at(acc, fr, -tau)
        np.add.at(acc, to, tau)
        acc[im] += Tm
        acc -= share * load(t)
        return np.concatenate([w, acc / J, [-w[im]]])

    def torques(x):
        th, w = x[:n], x[n:2 * n]
        d = th[fr] - th[to]
        dd = w[fr] - w[to]
        g = np.where(d > b, k * (d - b), np.where(d < -a, k * (d + a), 0.0))
        return g + c * dd

    return f, torques


def reference_simulate(mill, load, t_eval, *, rtol=1e-9, atol=1e-12, method="DOP853",
                       max_step=np.inf):
    """Integrate from rest with ``solve_ivp``; return element torques, shape (len(t_eval), ne)."""
    f, torques = reference_rhs(mill)
    n = len(mill.masses)
    x0 = np.zeros(2 * n + 1)
    sol = solve_ivp(lambda t, x: f(t, x, load), (t_eval[0], t_eval[-1]), x0, method=method,
                    t_eval=t_eval, rtol=rtol, atol=atol, max_step=max_step)
    if not sol.success:
        raise RuntimeError(sol.message)
    return np.array([torques(sol.y[:, i]) for i in range(sol.y.shape[1])]), sol
