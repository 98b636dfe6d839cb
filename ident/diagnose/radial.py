"""The bearings' radial model driven by a mesh torque, with its parameters free.

``ident.model.dynamics`` integrates the radial model of seed Fig. 8a together
with the torsion, with the mill file's bearing values compiled in as
constants.  The radial motion does not feed back into the torsion
(mill-config.md), so a library over many clearances can integrate the torsion
once and the radial model of each bearing separately, its clearance,
stiffnesses, damping and preload being *parameters* of one compiled
integrator.  The equations are the same as ``build_driveline``'s (shaft in its
clearance with contact stiffness and damping, housing on the frame softening
beyond its preload, mesh force along the line of action, gravity);
``tests/test_diagnose_radial.py`` checks the two agree.

Units: m, m/s, m/s^2, N; the input is the mesh element's reduced torque, N*m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Mapping

import casadi as ca
import numpy as np
import pandas as pd

from ..description import Bearing
from ..model.dynamics import G0
from ..model.integrate import Stepper, make_stepper

__all__ = ["RADIAL_PARAMS", "RadialModel", "radial_model", "radial_params", "simulate_radial"]

#: the bearing keys that are parameters of the radial model
RADIAL_PARAMS: tuple[str, ...] = ("clearance", "k_bearing", "c_bearing", "k_housing",
                                  "k_housing_open", "housing_preload", "c_housing", "shaft_mass",
                                  "housing_mass", "ratio_over_radius", "sin_alpha", "cos_alpha")

OUTPUTS: tuple[str, ...] = ("acc:h", "acc:v", "shaft:x", "shaft:y", "F")


@dataclass(frozen=True)
class RadialModel:
    """Symbolic radial model of one bearing (duck-types a Driveline for the integrator).

    ``rhs(x, u, p, t)``: states shaft ``x, y, vx, vy`` and housing ``x, y, vx, vy``;
    ``u`` the mesh torque (reduced N*m); ``p`` :data:`RADIAL_PARAMS`.
    ``out`` gives :data:`OUTPUTS`: housing accelerations (m/s^2), shaft position
    relative to the housing (m), contact force (N).
    """

    rhs: Any
    out: Any
    idle: Any
    n_states: int = 8
    n_params: int = len(RADIAL_PARAMS)


@lru_cache(maxsize=1)
def radial_model() -> RadialModel:
    """Build the radial model once (it has no constants of any mill)."""
    s = ca.SX.sym("s", 4)
    h = ca.SX.sym("h", 4)
    x = ca.vertcat(s, h)
    u = ca.SX.sym("u", 1)
    t = ca.SX.sym("t")
    p = ca.SX.sym("p", len(RADIAL_PARAMS))
    P = {k: p[i] for i, k in enumerate(RADIAL_PARAMS)}
    F_mesh = u[0] * P["ratio_over_radius"]
    Fx = F_mesh * P["sin_alpha"]
    Fy = F_mesh * P["cos_alpha"]
    rx, ry = s[0] - h[0], s[1] - h[1]
    rvx, rvy = s[2] - h[2], s[3] - h[3]
    r = ca.sqrt(rx * rx + ry * ry + 1e-24)
    pen = ca.fmax(r - P["clearance"], 0)
    nx, ny = rx / r, ry / r
    vn = rvx * nx + rvy * ny
    Fc = P["k_bearing"] * pen + ca.if_else(pen > 0, P["c_bearing"] * vn, 0)
    Fc = ca.fmax(Fc, 0)
    Fbx, Fby = Fc * nx, Fc * ny
    hr = ca.sqrt(h[0] * h[0] + h[1] * h[1] + 1e-24)
    d0 = P["housing_preload"] / P["k_housing"]
    Fh = P["k_housing"] * ca.fmin(hr, d0) + P["k_housing_open"] * ca.fmax(hr - d0, 0)
    Fhx = Fh * h[0] / hr + P["c_housing"] * h[2]
    Fhy = Fh * h[1] / hr + P["c_housing"] * h[3]
    ax_s = (Fx - Fbx) / P["shaft_mass"]
    ay_s = (Fy - Fby) / P["shaft_mass"] - G0
    ax_h = (Fbx - Fhx) / P["housing_mass"]
    ay_h = (Fby - Fhy) / P["housing_mass"]
    xdot = ca.vertcat(s[2], s[3], ax_s, ay_s, h[2], h[3], ax_h, ay_h)
    y = ca.vertcat(ax_h, ay_h, rx, ry, Fc)
    rhs = ca.Function("radial_rhs", [x, u, p, t], [xdot], ["x", "u", "p", "t"], ["xdot"])
    out = ca.Function("radial_out", [x, u, p, t], [y], ["x", "u", "p", "t"], ["y"])
    w = P["shaft_mass"] * G0
    hy0 = -w / P["k_housing"]
    sy0 = hy0 - P["clearance"] - w / P["k_bearing"]
    idle = ca.Function("radial_idle", [p], [ca.vertcat(0, sy0, 0, 0, 0, hy0, 0, 0)])
    return RadialModel(rhs=rhs, out=out, idle=idle)


def radial_params(bearing: Bearing, overrides: Mapping[str, float] | None = None) -> np.ndarray:
    """Parameter vector of a bearing (mill-file values, with ``{"clearance": ...}`` overrides)."""
    v: dict[str, float] = {
        "clearance": bearing.clearance, "k_bearing": bearing.k_bearing,
        "c_bearing": bearing.c_bearing, "k_housing": bearing.k_housing,
        "k_housing_open": (bearing.k_housing if bearing.k_housing_open is None
                           else bearing.k_housing_open),
        "housing_preload": (bearing.housing_preload if math.isfinite(bearing.housing_preload)
                            else 1e9 * bearing.k_housing),
        "c_housing": bearing.c_housing, "shaft_mass": bearing.shaft_mass,
        "housing_mass": bearing.housing_mass,
    }
    for k, val in (overrides or {}).items():
        if k not in v:
            raise KeyError(f"unknown radial parameter {k!r}; expected one of {sorted(v)}")
        v[k] = float(val)
    alpha = math.radians(bearing.pressure_angle_deg)
    v["ratio_over_radius"] = bearing.ratio / bearing.base_radius
    v["sin_alpha"] = math.sin(alpha)
    v["cos_alpha"] = math.cos(alpha)
    return np.array([v[k] for k in RADIAL_PARAMS], dtype=float)


@lru_cache(maxsize=8)
def _stepper(rate_hz: float, n_sub: int, compile: bool) -> Any:
    return make_stepper(radial_model(), interval=1.0 / rate_hz, n_sub=n_sub, compile=compile)  # type: ignore[arg-type]


def _integrate_outputs(st: Stepper, x0: np.ndarray, u: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Outputs at every sample (the first at ``x0``), shape (n, n_outputs).

    Like :func:`ident.model.integrate.integrate`, but the chunk function writes
    straight into numpy arrays (``Function.buffer``) and only the outputs are
    kept: converting CasADi matrices element by element dominated the cost.
    """
    model = radial_model()
    N = u.size
    C = st.chunk
    ny = len(OUTPUTS)
    nx = model.n_states
    Y = np.empty((N, ny))
    Y[0] = np.asarray(model.out(x0, u[:1], p, 0.0)).ravel()
    buf, trigger = st.fn.buffer()
    x = np.ascontiguousarray(x0, dtype=float)
    u0 = np.empty(C)
    u1 = np.empty(C)
    tt = np.empty(C)
    pp = np.ascontiguousarray(np.tile(np.asarray(p, dtype=float), (C, 1)))  # mapped, per interval
    Xc = np.empty((C, nx))  # column-major (nx x C) in CasADi's eyes
    Yc = np.empty((C, ny))
    buf.set_arg(1, memoryview(u0))
    buf.set_arg(2, memoryview(u1))
    buf.set_arg(3, memoryview(pp))
    buf.set_arg(4, memoryview(tt))
    buf.set_res(0, memoryview(Xc))
    buf.set_res(1, memoryview(Yc))
    k = 0
    T = st.interval
    while k < N - 1:
        n = min(C, N - 1 - k)
        u0[:n] = u[k:k + n]
        u1[:n] = u[k + 1:k + 1 + n]
        u0[n:] = u1[n:] = u[k + n]
        tt[:] = (k + np.arange(C)) * T
        buf.set_arg(0, memoryview(x))
        trigger()
        Y[k + 1:k + 1 + n] = Yc[:n]
        x = Xc[n - 1].copy()
        k += n
    return Y


def simulate_radial(bearing: Bearing, mesh_torque: np.ndarray, rate_hz: float, *,
                    params: Mapping[str, float] | None = None, max_step: float = 5e-5,
                    compile: bool = True) -> pd.DataFrame:
    """Integrate one bearing's radial model under a mesh torque history.

    Parameters
    ----------
    bearing : Bearing
    mesh_torque : ndarray, shape (n,)
        Reduced torque of the bearing's mesh element at ``rate_hz``, N*m,
        starting from rest (the shaft on the bottom of its clearance).
    rate_hz : float
        Sample rate of the input and the output, Hz.
    params : mapping, optional
        Overrides of the bearing's values (``clearance``, ``k_bearing``, ...).
    max_step : float
        Largest RK4 step, s (as the torsional simulator).

    Returns
    -------
    DataFrame
        Index ``time_s``; columns ``acc:h``, ``acc:v`` (m/s^2), ``shaft:x``,
        ``shaft:y`` (m, relative to the housing), ``F`` (N).
    """
    u = np.asarray(mesh_torque, dtype=float)
    p = radial_params(bearing, params)
    n_sub = max(1, math.ceil(1.0 / rate_hz / max_step - 1e-9))
    st = _stepper(float(rate_hz), n_sub, compile)
    model = radial_model()
    x0 = np.asarray(model.idle(p)).ravel()
    Y = _integrate_outputs(st, x0, u, p)
    idx = pd.Index(np.arange(u.size) / rate_hz, name="time_s")
    return pd.DataFrame(Y, index=idx, columns=list(OUTPUTS))
