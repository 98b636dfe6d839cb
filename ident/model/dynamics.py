"""Equations of motion of the branched torsional driveline, built once in CasADi.

The same symbolic model serves the simulator (compiled fixed-step integration),
the collocation fit (``ident.fit``) and the discrepancy workflow (added effect
terms).  It is a pure function of the :class:`~ident.description.Mill` and of
:class:`ModelOptions`.

States (in this order)
----------------------
* ``theta[i]`` -- angle of mass ``i`` relative to the nominal rotation
  ``Omega*t`` (rad, reduced), ``i`` in mill-file order;
* ``omega[i]`` -- speed deviation from ``Omega`` (rad/s, reduced);
* ``z`` -- the speed controller's integral state, ``dz/dt = -omega[motor]`` (rad);
* states added by effects (e.g. a lagging torque loop);
* per bearing (when ``bearings=True``): shaft ``x, y, vx, vy`` and housing
  ``x, y, vx, vy`` (m, m/s; ``x`` horizontal, ``y`` vertical up).

Input ``u = [T_load]``: the total rolling torque, N*m reduced, positive
against rotation, split over ``[load] masses`` by their shares.  ``t`` (s) is
an input too, for effects tied to the roll angle.

Equations (seed Fig. 2 structure, mill-config.md conventions)::

    J theta'' = -D^T tau + e_motor T_motor - s T_load
    tau_e     = g_e(delta_e) + c_e delta_e'          delta = D theta
    T_motor   = clip(kp (-omega_motor) + ki z, +-torque_limit)

Bearings (seed section 2.2, Fig. 8a): the shaft moves in its radial clearance
inside the housing, contact stiffness ``k_bearing`` once the clearance is
closed; the housing sits on the frame with stiffness ``k_housing`` that drops
to ``k_housing_open`` once the radial housing force exceeds
``housing_preload`` (seed Fig. 1b, softening); the mesh force
``tau_mesh * ratio / base_radius`` acts on the shaft along the line of action
at the pressure angle from the vertical (up for positive torque), gravity
pulls the shaft down.  The radial motion does not feed back into torsion.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence

import casadi as ca
import numpy as np

from ..description import Element, Mill, StiffnessKind
from . import laws
from .linear import incidence

__all__ = ["Family", "ModelOptions", "Driveline", "Effect", "EffectTerms", "build_driveline",
           "family_param_names", "default_family_params", "G0"]

G0 = 9.80665


class Family(str, enum.Enum):
    """Stiffness-law family used for the elements' restoring torque (seed 1.2)."""

    G1 = "g1"
    G2 = "g2"
    G3 = "g3"
    G4 = "g4"


def family_param_names(family: Family) -> tuple[str, ...]:
    """Per-element parameter names of a family.

    ``g1``: ``gap, gap_open`` (rad); ``g2``: ``a1, a2, a3``; ``g3``/``g4``:
    ``a0, sigma, shift`` (shift = centre of the gap, ``gap_open - gap/2``, rad).
    """
    return {
        Family.G1: ("gap", "gap_open"),
        Family.G2: ("a1", "a2", "a3"),
        Family.G3: ("a0", "sigma", "shift"),
        Family.G4: ("a0", "sigma", "shift"),
    }[Family(family)]


def default_family_params(element: Element, family: Family) -> tuple[float, ...]:
    """Parameters of ``family`` that imitate the element's mill-file g1 law.

    g2: least squares over +-(gap + 4 mrad); g3: far-field match (stiffness
    ``pi*a0/2 = k``, apparent half-gap ``2/(pi*sigma) = gap/2``); g4: ``a0 = k``,
    ``sigma = 2/gap`` (the tanh bend spans the gap).  A tight element gets a
    very sharp bend (``gap`` floored at 1e-5 rad).
    """
    family = Family(family)
    gap = max(element.gap, 1e-5)
    shift = element.gap_open - element.gap / 2.0
    if family is Family.G1:
        return (element.gap, element.gap_open)
    if family is Family.G2:
        if element.gap == 0.0:
            return (element.k, 0.0, 0.0)
        amp = element.gap + 4e-3
        d = np.linspace(-amp, amp, 201)
        y = laws.g1(d, element.a, element.b, element.k, element.k_gap, element.k)
        A = np.stack([d, d ** 2, d ** 3], axis=1)
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        return tuple(float(c) for c in coef)
    if family is Family.G3:
        return (2.0 * element.k / math.pi, 4.0 / (math.pi * gap), shift)
    return (element.k, 2.0 / gap, shift)


@dataclass(frozen=True)
class EffectTerms:
    """What an effect adds to the symbolic model (all optional).

    Attributes
    ----------
    element_torque : dict[int, SX]
        Extra torque transmitted by element ``i`` (adds to ``tau_i``: the
        element's torque channel reads it too).
    mass_torque : SX or None
        Extra external torque per mass, shape (n_masses,).
    gap_open_shift : dict[int, SX]
        Added to the open part ``b`` of element ``i`` (the total gap stays).
    motor_torque : SX or None
        Replaces the commanded motor torque (e.g. a lagging torque loop).
    states, state_derivatives, state_names : extra states of the effect.
    state_initial : initial values of the extra states.
    extra_elements : list of (from_index, to_index, torque_fn) where
        ``torque_fn(delta, ddelta) -> SX`` adds a new link between two masses.
    """

    element_torque: dict[int, Any] = field(default_factory=dict)
    mass_torque: Any = None
    gap_open_shift: dict[int, Any] = field(default_factory=dict)
    motor_torque: Any = None
    states: Any = None
    state_derivatives: Any = None
    state_names: tuple[str, ...] = ()
    state_initial: tuple[float, ...] = ()
    extra_elements: tuple = ()


class Effect(Protocol):
    """An effect the mill file leaves out (effects.md), as a model term.

    ``name`` and ``location`` follow effects.md; ``param_names`` are local
    names, prefixed with ``f"{name}@{location}."`` in the model's parameter
    vector; ``terms`` receives the symbolic context and the effect's parameter
    symbols and returns what it adds.
    """

    name: str
    location: str

    @property
    def param_names(self) -> tuple[str, ...]: ...

    @property
    def param_defaults(self) -> tuple[float, ...]: ...

    def terms(self, ctx: "SymbolicContext", p: Any) -> EffectTerms: ...


@dataclass(frozen=True)
class SymbolicContext:
    """Symbols an effect can build on (read-only).

    Attributes
    ----------
    contact_neg, contact_pos : tuple of SX, optional
        Per element (mill-file order), the deflections (rad, reduced) where the
        flanks meet on the negative (``-a``) and drive (``b``) side under the
        model's own law and parameters (g1: ``-(gap - gap_open)`` and
        ``gap_open``; g3/g4: ``shift`` -/+ the apparent half-gap; g2: the
        mill file's values).  Other effects' ``gap_open_shift`` is not included.
    smoothing : SX, float or None
        The g1 kink rounding width, rad (None: exact kinks), for effects that
        add kinks of their own.
    """

    mill: Mill
    theta: Any
    omega: Any
    t: Any
    T_load: Any
    T_motor_command: Any
    delta: Any
    ddelta: Any
    motor_index: int
    motor_speed: float
    contact_neg: tuple = ()
    contact_pos: tuple = ()
    smoothing: Any = None


@dataclass(frozen=True)
class ModelOptions:
    """How the driveline is modelled.

    Attributes
    ----------
    family : Family
        Stiffness law of every element.
    smoothing : float, None or "param"
        For g1: kink rounding width, rad (``None``: exact kinks, for simulation).
        ``"param"``: the width is the model's last parameter, ``"smoothing"``
        (rad, default 1e-4), so that a fit can continue on it without
        rebuilding the model.
    smoothing_kind : str
        How the g1 kinks are rounded: ``"sqrt"`` (``laws.smooth_max``) or
        ``"c1"`` (``laws.smooth_max_c1``, exact outside the width).
    effects : tuple of Effect
        Terms for effects the mill file leaves out (ident.model.effects).
    bearings : bool
        Include the bearings' radial model (simulation only).
    """

    family: Family = Family.G1
    smoothing: float | str | None = None
    smoothing_kind: str = "sqrt"
    effects: tuple = ()
    bearings: bool = False


@dataclass(frozen=True)
class Driveline:
    """The compiled symbolic model of one mill under given options.

    Attributes
    ----------
    rhs : casadi.Function
        ``rhs(x, u, p, t) -> xdot``.
    out : casadi.Function
        ``out(x, u, p, t) -> y`` with :attr:`output_names`: reduced element
        torques (``tau:ID``), motor torque (``T_motor``), the load
        (``T_load``) and, with bearings, housing accelerations
        (``acc:ID:h``/``acc:ID:v``, m/s^2), shaft positions relative to the
        housing (``shaft:ID:x``/``:y``, m) and bearing force (``F:ID``, N).
    """

    mill: Mill
    options: ModelOptions
    state_names: tuple[str, ...]
    param_names: tuple[str, ...]
    p_default: np.ndarray
    output_names: tuple[str, ...]
    rhs: Any
    out: Any
    x_idle: np.ndarray

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def param_index(self, name: str) -> int:
        return self.param_names.index(name)

    def output_index(self, name: str) -> int:
        return self.output_names.index(name)

    def params(self, overrides: dict[str, float] | None = None) -> np.ndarray:
        """Default parameter vector with ``{"C46.gap": ...}`` overrides."""
        p = self.p_default.copy()
        for k, v in (overrides or {}).items():
            p[self.param_index(k)] = v
        return p


def _element_torque(e: Element, delta: Any, ddelta: Any, p: dict[str, Any], family: Family,
                    smoothing: Any, b_shift: Any = 0.0, kind: str = "sqrt") -> Any:
    """Restoring torque g(delta) + c*ddelta of one element under a family."""
    if family is Family.G1:
        gap, b = p["gap"], p["gap_open"] + b_shift
        a = gap - b
        knee = e.knee if e.stiffness is not StiffnessKind.LINEAR else None
        k_after = e.k_after if knee is not None else None
        if smoothing is None:
            g = laws.piecewise(delta, a, b, e.k, e.k_gap, e.k, knee, k_after, xp=ca)
        else:
            g = laws.piecewise_smooth(delta, a, b, e.k, e.k_gap, e.k, smoothing, knee, k_after,
                                      xp=ca, kind=kind)
    elif family is Family.G2:
        g = laws.g2(delta, p["a1"], p["a2"], p["a3"], xp=ca)
    elif family is Family.G3:
        g = laws.g3(delta - p["shift"] - b_shift, p["a0"], p["sigma"], xp=ca)
    else:
        g = laws.g4(delta - p["shift"] - b_shift, p["a0"], p["sigma"], xp=ca)
    return g + e.c * ddelta


def _contacts(e: Element, p: dict[str, Any], family: Family) -> tuple[Any, Any]:
    """Deflections where the flanks meet, negative and drive side, rad (SymbolicContext)."""
    if family is Family.G1:
        return -(p["gap"] - p["gap_open"]), p["gap_open"]
    if family is Family.G3:
        half = 2.0 / (math.pi * p["sigma"])
        return p["shift"] - half, p["shift"] + half
    if family is Family.G4:
        half = 1.0 / p["sigma"]
        return p["shift"] - half, p["shift"] + half
    return -e.a, e.b


def build_driveline(mill: Mill, options: ModelOptions = ModelOptions()) -> Driveline:
    """Build the symbolic equations of motion of ``mill``.

    Parameters
    ----------
    mill : Mill
    options : ModelOptions

    Returns
    -------
    Driveline
        CasADi functions for the right-hand side and the outputs, the state
        and parameter names, and the mill file's parameter values as defaults.
    """
    family = Family(options.family)
    n = len(mill.masses)
    ne = len(mill.elements)
    D = incidence(mill)
    J = np.array([m.J for m in mill.masses])
    im = mill.mass_index(mill.motor.mass)
    load_vec = np.zeros(n)
    for mid, s in zip(mill.load.masses, mill.load.share):
        load_vec[mill.mass_index(mid)] += s

    theta = ca.SX.sym("theta", n)
    omega = ca.SX.sym("omega", n)
    z = ca.SX.sym("z")
    u = ca.SX.sym("u", 1)
    t = ca.SX.sym("t")
    T_load = u[0]

    # parameters: per element family params, then effect params
    pnames: list[str] = []
    pdefault: list[float] = []
    for e in mill.elements:
        for nm, v in zip(family_param_names(family), default_family_params(e, family)):
            pnames.append(f"{e.id}.{nm}")
            pdefault.append(v)
    for eff in options.effects:
        for nm, v in zip(eff.param_names, eff.param_defaults):
            pnames.append(f"{eff.name}@{eff.location}.{nm}")
            pdefault.append(float(v))
    if options.smoothing == "param":
        pnames.append("smoothing")
        pdefault.append(1e-4)
    p = ca.SX.sym("p", len(pnames))
    pidx = {nm: i for i, nm in enumerate(pnames)}
    smoothing = p[pidx["smoothing"]] if options.smoothing == "param" else options.smoothing

    delta = ca.mtimes(ca.DM(D), theta)
    ddelta = ca.mtimes(ca.DM(D), omega)

    # speed controller (ideal torque loop)
    T_cmd = -mill.motor.kp * omega[im] + mill.motor.ki * z
    if mill.motor.torque_limit is not None:
        lim = mill.motor.torque_limit
        T_cmd = ca.fmin(ca.fmax(T_cmd, -lim), lim)

    contact_neg, contact_pos = [], []
    for e in mill.elements:
        cn, cp = _contacts(e, {nm: p[pidx[f"{e.id}.{nm}"]] for nm in family_param_names(family)},
                           family)
        contact_neg.append(cn)
        contact_pos.append(cp)
    ctx = SymbolicContext(mill=mill, theta=theta, omega=omega, t=t, T_load=T_load,
                          T_motor_command=T_cmd, delta=delta, ddelta=ddelta, motor_index=im,
                          motor_speed=mill.motor_speed, contact_neg=tuple(contact_neg),
                          contact_pos=tuple(contact_pos), smoothing=smoothing)
    terms: list[EffectTerms] = []
    for eff in options.effects:
        local = ca.vertcat(*[p[pidx[f"{eff.name}@{eff.location}.{nm}"]]
                             for nm in eff.param_names]) if eff.param_names else ca.SX(0, 1)
        terms.append(eff.terms(ctx, local))

    b_shift = {i: 0.0 for i in range(ne)}
    for tm in terms:
        for i, s in tm.gap_open_shift.items():
            b_shift[i] = b_shift[i] + s

    tau = []
    for i, e in enumerate(mill.elements):
        ep = {nm: p[pidx[f"{e.id}.{nm}"]] for nm in family_param_names(family)}
        ti = _element_torque(e, delta[i], ddelta[i], ep, family, smoothing, b_shift[i],
                             options.smoothing_kind)
        for tm in terms:
            if i in tm.element_torque:
                ti = ti + tm.element_torque[i]
        tau.append(ti)
    tau_v = ca.vertcat(*tau)

    T_motor = T_cmd
    for tm in terms:
        if tm.motor_torque is not None:
            T_motor = tm.motor_torque

    e_motor = np.zeros(n)
    e_motor[im] = 1.0
    torque = -ca.mtimes(ca.DM(D.T), tau_v) + ca.DM(e_motor) * T_motor - ca.DM(load_vec) * T_load
    for tm in terms:
        if tm.mass_torque is not None:
            torque = torque + tm.mass_torque
        for (fi, ti_, fn) in tm.extra_elements:
            d_ = theta[fi] - theta[ti_]
            dd_ = omega[fi] - omega[ti_]
            f_ = fn(d_, dd_)
            torque[fi] = torque[fi] - f_
            torque[ti_] = torque[ti_] + f_
    acc = torque / ca.DM(J)

    x_parts = [theta, omega, z]
    xdot_parts = [omega, acc, -omega[im]]
    names = [f"theta:{m.id}" for m in mill.masses] + [f"omega:{m.id}" for m in mill.masses] + ["z"]
    x_idle = [0.0] * (2 * n + 1)
    for tm in terms:
        if tm.states is not None:
            x_parts.append(tm.states)
            xdot_parts.append(tm.state_derivatives)
            names.extend(tm.state_names)
            x_idle.extend(tm.state_initial)

    out_names = [f"tau:{e.id}" for e in mill.elements] + ["T_motor", "T_load"]
    outs = [tau_v, T_motor, T_load]

    if options.bearings and mill.bearings:
        for b in mill.bearings:
            s = ca.SX.sym(f"shaft_{b.id}", 4)
            h = ca.SX.sym(f"housing_{b.id}", 4)
            mesh_i = mill.element_ids.index(b.mesh)
            F_mesh = tau[mesh_i] * b.ratio / b.base_radius
            alpha = math.radians(b.pressure_angle_deg)
            Fx = F_mesh * math.sin(alpha)
            Fy = F_mesh * math.cos(alpha)
            # shaft in its clearance (relative to the housing)
            rx, ry = s[0] - h[0], s[1] - h[1]
            rvx, rvy = s[2] - h[2], s[3] - h[3]
            r = ca.sqrt(rx * rx + ry * ry + 1e-24)
            pen = ca.fmax(r - b.clearance, 0)
            nx, ny = rx / r, ry / r
            vn = rvx * nx + rvy * ny
            Fc = b.k_bearing * pen + ca.if_else(pen > 0, b.c_bearing * vn, 0)
            Fc = ca.fmax(Fc, 0)  # contact pushes only
            Fbx, Fby = Fc * nx, Fc * ny  # force on the shaft is -Fb, on the housing +Fb
            # housing on the frame, softening beyond its preload
            hr = ca.sqrt(h[0] * h[0] + h[1] * h[1] + 1e-24)
            k_open = b.k_housing if b.k_housing_open is None else b.k_housing_open
            d0 = b.housing_preload / b.k_housing if math.isfinite(b.housing_preload) else 1e9
            Fh = b.k_housing * ca.fmin(hr, d0) + k_open * ca.fmax(hr - d0, 0)
            Fhx = Fh * h[0] / hr + b.c_housing * h[2]
            Fhy = Fh * h[1] / hr + b.c_housing * h[3]
            ax_s = (Fx - Fbx) / b.shaft_mass
            ay_s = (Fy - Fby) / b.shaft_mass - G0
            ax_h = (Fbx - Fhx) / b.housing_mass
            ay_h = (Fby - Fhy) / b.housing_mass
            x_parts += [s, h]
            xdot_parts += [ca.vertcat(s[2], s[3], ax_s, ay_s), ca.vertcat(h[2], h[3], ax_h, ay_h)]
            names += [f"shaft:{b.id}:{k}" for k in ("x", "y", "vx", "vy")]
            names += [f"housing:{b.id}:{k}" for k in ("x", "y", "vx", "vy")]
            # static rest: shaft on the bottom of its clearance, housing sagging
            w = b.shaft_mass * G0
            hy0 = -w / b.k_housing
            sy0 = hy0 - b.clearance - w / b.k_bearing
            x_idle += [0.0, sy0, 0.0, 0.0, 0.0, hy0, 0.0, 0.0]
            out_names += [f"acc:{b.id}:h", f"acc:{b.id}:v", f"shaft:{b.id}:x", f"shaft:{b.id}:y",
                          f"F:{b.id}"]
            outs += [ax_h, ay_h, rx, ry, Fc]

    x = ca.vertcat(*x_parts)
    xdot = ca.vertcat(*xdot_parts)
    rhs = ca.Function("rhs", [x, u, p, t], [xdot], ["x", "u", "p", "t"], ["xdot"])
    out = ca.Function("out", [x, u, p, t], [ca.vertcat(*outs)], ["x", "u", "p", "t"], ["y"])
    return Driveline(mill=mill, options=options, state_names=tuple(names),
                     param_names=tuple(pnames), p_default=np.array(pdefault),
                     output_names=tuple(out_names), rhs=rhs, out=out,
                     x_idle=np.array(x_idle, dtype=float))
