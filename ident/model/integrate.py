"""Fixed-step RK4 integration of a :class:`~ident.model.dynamics.Driveline`, compiled to C.

One output interval ``T`` is integrated in ``n_sub`` classical RK4 steps, the
input interpolated linearly between the interval's end points.  The step is
chained over a chunk of samples with CasADi's ``mapaccum``, generated as C and
compiled once with the system C compiler (cached under
``$IDENT_CACHE`` or ``~/.cache/ident/jit``); without a compiler CasADi's
virtual machine runs the same function, only slower.

Accuracy: RK4 is 4th order on smooth laws; at the kinks of g1 the local error
is lower order, so the step is chosen by the step-halving test in
``tests/test_simulate.py`` rather than assumed.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from .dynamics import Driveline

__all__ = ["Stepper", "make_stepper", "integrate", "cache_dir"]


def cache_dir() -> Path:
    """Directory of compiled integrators (``$IDENT_CACHE/jit`` or ``~/.cache/ident/jit``)."""
    base = os.environ.get("IDENT_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "ident")
    return Path(base) / "jit"


@dataclass(frozen=True)
class Stepper:
    """A compiled chunk integrator.

    ``fn(x0, u0[1xN], u1[1xN], p, t0[1xN]) -> (X[nx x N], Y[ny x N])``: state
    and outputs at the end of each of ``N = chunk`` output intervals.
    """

    fn: Any
    chunk: int
    interval: float
    n_sub: int
    compiled: bool
    stage_inputs: bool = False


def _rk4_interval(drv: Driveline, T: float, n_sub: int, stage_inputs: bool = False) -> ca.Function:
    if stage_inputs:
        return _rk4_interval_stages(drv, T, n_sub)
    nx = drv.n_states
    x0 = ca.SX.sym("x0", nx)
    u0 = ca.SX.sym("u0", 1)
    u1 = ca.SX.sym("u1", 1)
    p = ca.SX.sym("p", drv.n_params)
    t0 = ca.SX.sym("t0")
    h = T / n_sub
    # one RK4 step as a function, called n_sub times (keeps the C code small)
    xs = ca.SX.sym("xs", nx)
    ts = ca.SX.sym("ts")
    s = ca.SX.sym("s")  # fraction of the interval at the step start

    def u_at(frac: Any) -> Any:
        return u0 + (u1 - u0) * frac

    k1 = drv.rhs(xs, u_at(s), p, ts)
    k2 = drv.rhs(xs + 0.5 * h * k1, u_at(s + 0.5 / n_sub), p, ts + 0.5 * h)
    k3 = drv.rhs(xs + 0.5 * h * k2, u_at(s + 0.5 / n_sub), p, ts + 0.5 * h)
    k4 = drv.rhs(xs + h * k3, u_at(s + 1.0 / n_sub), p, ts + h)
    step = ca.Function("rk4", [xs, u0, u1, p, ts, s],
                       [xs + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)])
    x = x0
    for i in range(n_sub):
        x = step(x, u0, u1, p, t0 + i * h, i / n_sub)
    y = drv.out(x, u1, p, t0 + T)
    return ca.Function("interval", [x0, u0, u1, p, t0], [x, y])


def _rk4_interval_stages(drv: Driveline, T: float, n_sub: int) -> ca.Function:
    """RK4 over one interval with the load given at every stage point (2*n_sub + 1 values)."""
    nx = drv.n_states
    x0 = ca.SX.sym("x0", nx)
    U = ca.SX.sym("U", 2 * n_sub + 1)
    p = ca.SX.sym("p", drv.n_params)
    t0 = ca.SX.sym("t0")
    h = T / n_sub
    xs = ca.SX.sym("xs", nx)
    ts = ca.SX.sym("ts")
    ua, um, ub = ca.SX.sym("ua"), ca.SX.sym("um"), ca.SX.sym("ub")
    k1 = drv.rhs(xs, ua, p, ts)
    k2 = drv.rhs(xs + 0.5 * h * k1, um, p, ts + 0.5 * h)
    k3 = drv.rhs(xs + 0.5 * h * k2, um, p, ts + 0.5 * h)
    k4 = drv.rhs(xs + h * k3, ub, p, ts + h)
    step = ca.Function("rk4s", [xs, ua, um, ub, p, ts],
                       [xs + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)])
    x = x0
    for i in range(n_sub):
        x = step(x, U[2 * i], U[2 * i + 1], U[2 * i + 2], p, t0 + i * h)
    y = drv.out(x, U[2 * n_sub], p, t0 + T)
    return ca.Function("interval_stages", [x0, U, p, t0], [x, y])


def _compile(fn: ca.Function, name: str) -> Any:
    """Generate C for ``fn``, compile it with cc (cached), return an external Function."""
    cc = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if cc is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        cg.add(fn)
        cg.generate(tmp + os.sep)
        src = (Path(tmp) / f"{name}.c").read_text()
    key = hashlib.sha256(src.encode()).hexdigest()[:20]
    d = cache_dir()
    so = d / f"{name}_{key}.so"
    if not so.exists():
        d.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=d) as tmp:
            c_path = Path(tmp) / f"{name}.c"
            c_path.write_text(src)
            tmp_so = Path(tmp) / "out.so"
            res = subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", str(tmp_so), str(c_path)],
                                 capture_output=True, text=True)
            if res.returncode != 0:
                return None
            os.replace(tmp_so, so)  # atomic: parallel workers never load a half-written file
    return ca.external(fn.name(), str(so))


def make_stepper(drv: Driveline, *, interval: float, n_sub: int, chunk: int = 2000,
                 compile: bool = True, stage_inputs: bool = False) -> Stepper:
    """Build (and compile) the chunk integrator of a driveline.

    Parameters
    ----------
    drv : Driveline
    interval : float
        Output sample interval ``T``, s.
    n_sub : int
        RK4 steps per interval (step ``T / n_sub``).
    chunk : int
        Intervals per call.
    compile : bool
        Compile to C (falls back to CasADi's VM when no compiler works).
    stage_inputs : bool
        Take the load at every RK4 stage point (``2*n_sub + 1`` values per
        interval, see :func:`stage_times`) instead of interpolating it linearly
        between samples: exact for any load shape.
    """
    f = _rk4_interval(drv, interval, n_sub, stage_inputs)
    # mapaccum: x accumulated; inputs mapped; p broadcast
    F = f.mapaccum("sim_stages" if stage_inputs else "sim", chunk, [0], [0])
    if compile:
        ext = _compile(F, "ident_sim")
        if ext is not None:
            return Stepper(fn=ext, chunk=chunk, interval=interval, n_sub=n_sub, compiled=True,
                           stage_inputs=stage_inputs)
    return Stepper(fn=F, chunk=chunk, interval=interval, n_sub=n_sub, compiled=False,
                   stage_inputs=stage_inputs)


def stage_times(stepper: Stepper, n_samples: int, t0: float = 0.0) -> np.ndarray:
    """Times of the RK4 stage points, shape (n_samples - 1, 2*n_sub + 1), s."""
    h2 = stepper.interval / stepper.n_sub / 2.0
    k = np.arange(n_samples - 1)[:, None] * stepper.interval
    return t0 + k + np.arange(2 * stepper.n_sub + 1)[None, :] * h2


def integrate(stepper: Stepper, x0: np.ndarray, u: np.ndarray, p: np.ndarray,
              t0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Integrate over the samples of ``u``.

    Parameters
    ----------
    stepper : Stepper
    x0 : ndarray, shape (nx,)
        State at the first sample.
    u : ndarray, shape (N,) or (N - 1, 2*n_sub + 1)
        Load torque (N*m) at each output sample, or, for a stepper with
        ``stage_inputs``, at the stage points of each interval (:func:`stage_times`).
    p : ndarray, shape (np,)
    t0 : float
        Time of the first sample, s.

    Returns
    -------
    X : ndarray, shape (N, nx)
        States at the samples (``X[0] = x0``).
    Y_end : ndarray, shape (N - 1, ny)
        Outputs at samples 1..N-1 (the caller evaluates sample 0).
    """
    if stepper.stage_inputs:
        return _integrate_stages(stepper, x0, np.asarray(u, dtype=float), p, t0)
    N = len(u)
    C = stepper.chunk
    T = stepper.interval
    nx = len(x0)
    X = np.empty((N, nx))
    X[0] = x0
    ys = []
    x = np.asarray(x0, dtype=float)
    k = 0
    pd = ca.DM(p)
    while k < N - 1:
        n = min(C, N - 1 - k)
        u0 = np.empty(C)
        u1 = np.empty(C)
        u0[:n] = u[k:k + n]
        u1[:n] = u[k + 1:k + 1 + n]
        u0[n:] = u1[n:] = u[k + n]
        tt = t0 + (k + np.arange(C)) * T
        Xc, Yc = stepper.fn(x, u0[None, :], u1[None, :], pd, tt[None, :])
        Xc = np.asarray(Xc)
        Yc = np.asarray(Yc)
        X[k + 1:k + 1 + n] = Xc[:, :n].T
        ys.append(Yc[:, :n].T)
        x = Xc[:, n - 1]
        k += n
    Y = np.concatenate(ys, axis=0) if ys else np.empty((0, 0))
    return X, Y


def _integrate_stages(stepper: Stepper, x0: np.ndarray, U: np.ndarray, p: np.ndarray,
                      t0: float) -> tuple[np.ndarray, np.ndarray]:
    N = U.shape[0] + 1
    C = stepper.chunk
    T = stepper.interval
    X = np.empty((N, len(x0)))
    X[0] = x0
    ys = []
    x = np.asarray(x0, dtype=float)
    pd = ca.DM(p)
    k = 0
    while k < N - 1:
        n = min(C, N - 1 - k)
        Uc = np.empty((C, U.shape[1]))
        Uc[:n] = U[k:k + n]
        Uc[n:] = U[k + n - 1, -1]
        tt = t0 + (k + np.arange(C)) * T
        Xc, Yc = stepper.fn(x, Uc.T, pd, tt[None, :])
        Xc = np.asarray(Xc)
        Yc = np.asarray(Yc)
        X[k + 1:k + 1 + n] = Xc[:, :n].T
        ys.append(Yc[:, :n].T)
        x = Xc[:, n - 1]
        k += n
    return X, (np.concatenate(ys, axis=0) if ys else np.empty((0, 0)))
