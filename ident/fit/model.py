"""The symbolic model a fit adjusts: driveline, load ramp, parameter layout.

The fit's unknowns split into

* **shared** parameters, the same for every transient window: per element the
  family's characteristic (g1: the total gap; g2: ``a1, a2, a3``; g3/g4: an
  apparent gap and a stiffness factor, mapped to ``a0, sigma``);
* **per-window** parameters: the load ramp (level before, level after,
  half-height time, rise time) and, for g1 elements with stiffness inside the
  gap (``k_gap > 0``), where the gap sits (``gap_open`` as a fraction of the gap);
* **per-window initial states** (angles, speeds, speed-controller integral),
  the motor angle fixed at 0 (the rigid-body angle is unobservable).

Gap position convention
-----------------------
With no stiffness inside the gap (``k_gap = 0``) an element's torque depends
only on where the deflection is relative to the contact points, so the
element's open part and its initial deflection cannot both be free.  The fit
puts the drive-side contact at ``delta = 0`` (``b = 0``, ``a = gap``) and
leaves the initial deflection free: a window that starts at rest inside the
gap has ``gap_open = -delta(t0)`` (mill-config.md's ``b`` with the deflection
counted from its start).  g3/g4 are fitted with ``shift = 0`` the same way, the
gap centred on ``delta = 0``: ``gap_open = gap/2 - delta(t0)``.

Load ramp (``ident.model.scenario``): a raised cosine of duration ``rise``
centred on ``t_step`` from the level before, ``L0 + s0*(t - t_step)``, to the
level after, ``L1 + s1*(t - t_step)``; the slopes take up the slow fluctuation
of the rolling torque (temperature, friction) over a window.  C1 in time and in
its parameters because the cosine's slope vanishes where it is clipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import casadi as ca
import numpy as np

from ..description import Mill
from ..errors import FitError
from ..model.dynamics import Driveline, Family, ModelOptions, build_driveline, default_family_params
from ..model.linear import angles_from_deflections, incidence, stiffness_matrix

__all__ = ["FitModel", "build_fit_model", "LOAD_PARAMS", "GAP_MAX"]

#: Per-window load parameters, in order.
LOAD_PARAMS = ("L0", "L1", "t_step", "rise", "s0", "s1")

#: Default upper bound of any gap, rad (reduced).
GAP_MAX = 0.03

#: Smallest apparent gap of g3/g4 (a nearly tight element), rad.
_GAP_MIN_SMOOTH = 2e-5


@dataclass(frozen=True)
class FitModel:
    """The model of one mill under one family, laid out for a fit.

    Attributes
    ----------
    mill : Mill
    family : Family
    driveline : Driveline
        Built with ``smoothing="param"`` for g1.
    shared_names : tuple of str
        Shared decision parameters, ``"C46.gap"`` (g1); ``"C46.a1"`` ... (g2);
        ``"C46.gap_app"``, ``"C46.stiffness"`` (g3/g4: apparent gap, rad, and
        stiffness relative to the mill file's ``k``).
    shared_lb, shared_ub, shared_scale : ndarray
        Bounds and typical magnitude of the shared parameters.
    window_names : tuple of str
        Per-window parameters: :data:`LOAD_PARAMS` then ``"C46.open_frac"`` for
        g1 elements with ``k_gap > 0``.
    measured : tuple of str
        Element ids with a torque channel, in output order.
    pmap : casadi.Function
        ``pmap(shared, window, w) -> p`` the driveline's parameter vector.
    load : casadi.Function
        ``load(t, window) -> T_load`` (N*m reduced), ``t`` relative to the window start.
    y : casadi.Function
        ``y(x, u, p, t) -> reduced torques of the measured elements`` (N*m).
    """

    mill: Mill
    family: Family
    driveline: Driveline
    shared_names: tuple[str, ...]
    shared_lb: np.ndarray
    shared_ub: np.ndarray
    shared_scale: np.ndarray
    window_names: tuple[str, ...]
    measured: tuple[str, ...]
    pmap: Any
    load: Any
    y: Any
    gap_max: float
    x0_fixed: tuple[int, ...]
    motor_index: int
    kgap_elements: tuple[str, ...] = ()
    effects: tuple = field(default=())

    # ---- sizes ---------------------------------------------------------------------
    @property
    def nx(self) -> int:
        return self.driveline.n_states

    @property
    def n_shared(self) -> int:
        return len(self.shared_names)

    @property
    def n_window(self) -> int:
        return len(self.window_names)

    @property
    def ny(self) -> int:
        return len(self.measured)

    # ---- the family's reported quantities --------------------------------------------
    def element_shared(self, element_id: str) -> tuple[int, ...]:
        """Indices of an element's shared parameters."""
        pre = element_id + "."
        return tuple(i for i, n in enumerate(self.shared_names) if n.startswith(pre))

    def family_params(self, shared: np.ndarray) -> dict[str, dict[str, float]]:
        """Per element the family's own parameters (``a0, sigma`` ...) from the shared vector."""
        out: dict[str, dict[str, float]] = {}
        for e in self.mill.elements:
            v = {self.shared_names[i].split(".", 1)[1]: float(shared[i])
                 for i in self.element_shared(e.id)}
            if self.family is Family.G1:
                out[e.id] = {}
            elif self.family is Family.G2:
                out[e.id] = {"a1": v["a1"], "a2": v["a2"], "a3": v["a3"]}
            else:
                a0, sigma = _smooth_a0_sigma(self.family, e.k, v["gap_app"], v["stiffness"])
                out[e.id] = {"a0": a0, "sigma": sigma}
        return out

    def equivalent_gap(self, element_id: str, shared: np.ndarray) -> tuple[float, float]:
        """Total gap and drive-side contact position of an element's characteristic, rad.

        g1: ``(gap, 0)``.  g3: apparent gap ``4/(pi*sigma)`` (twice the
        far-field asymptote's offset), contact at ``+gap/2``.  g4: ``2/sigma``
        (the deflection span over which ``tanh`` bends, as in
        ``ident.model.dynamics.default_family_params``), contact at ``+gap/2``.
        g2: the span between the two deflections where the local stiffness
        ``g2'`` equals half the mill file's ``k`` (0 when it never falls that
        low), contact at the upper one.
        """
        e = self.mill.element(element_id)
        v = {self.shared_names[i].split(".", 1)[1]: float(shared[i])
             for i in self.element_shared(element_id)}
        if self.family is Family.G1:
            return v["gap"], 0.0
        if self.family in (Family.G3, Family.G4):
            return v["gap_app"], 0.5 * v["gap_app"]
        return g2_equivalent_gap(v["a1"], v["a2"], v["a3"], e.k)


def g2_equivalent_gap(a1: float, a2: float, a3: float, k: float) -> tuple[float, float]:
    """Span and upper end of ``{d : a1 + 2 a2 d + 3 a3 d**2 < k/2}``, rad.

    Returns ``(0, d_min)`` when the local stiffness never drops below ``k/2``
    (``d_min`` the deflection of least stiffness) and ``(inf, nan)`` for ``a3 <= 0``.
    """
    if a3 <= 0:
        return math.inf, math.nan
    disc = 4 * a2 * a2 - 12 * a3 * (a1 - 0.5 * k)
    centre = -a2 / (3 * a3)
    if disc <= 0:
        return 0.0, centre
    r = math.sqrt(disc) / (6 * a3)
    return 2 * r, centre + r


def _smooth_a0_sigma(family: Family, k: float, gap_app: Any, stiffness: Any) -> tuple[Any, Any]:
    """``(a0, sigma)`` of g3/g4 from an apparent gap (rad) and relative stiffness."""
    if family is Family.G3:
        return 2.0 * k * stiffness / math.pi, 4.0 / (math.pi * gap_app)
    return k * stiffness, 2.0 / gap_app


def raised_cosine(s: Any, xp: Any = np) -> Any:
    """0 for ``s <= 0``, ``(1 - cos(pi s))/2`` between, 1 for ``s >= 1``."""
    return 0.5 - 0.5 * xp.cos(math.pi * xp.fmin(xp.fmax(s, 0.0), 1.0))


def build_fit_model(mill: Mill, *, family: Family | str = Family.G1, effects: Sequence = (),
                    gap_max: float = GAP_MAX, smoothing_kind: str = "c1") -> FitModel:
    """Lay out the fit's parameters over the driveline of ``mill``.

    Parameters
    ----------
    mill : Mill
    family : Family or str
        ``g1`` (smoothed logical law with explicit gaps), ``g2``, ``g3`` or ``g4``.
    effects : sequence of Effect
        Extra model terms (discrepancy workflow); their parameters stay at defaults.
    gap_max : float
        Upper bound of every gap, rad (reduced).
    smoothing_kind : str
        Rounding of the g1 kinks (``ident.model.laws``): ``"c1"`` (default,
        exact outside the width: a third of the sqrt rounding's bias in a
        release's rattle at the same width) or ``"sqrt"``.

    Raises
    ------
    FitError
        The mill has no torque channel.
    """
    family = Family(family)
    measured = tuple(dict.fromkeys(c.element for c in mill.torque_channels()))
    if not measured:
        raise FitError(f"mill '{mill.name}' has no torque channel: nothing to fit. Expected at "
                       "least one [[channel]] with quantity = \"torque\".")
    smoothing = "param" if family is Family.G1 else None
    drv = build_driveline(mill, ModelOptions(family=family, smoothing=smoothing,
                                             smoothing_kind=smoothing_kind,
                                             effects=tuple(effects)))
    names: list[str] = []
    lb: list[float] = []
    ub: list[float] = []
    scale: list[float] = []
    for e in mill.elements:
        if family is Family.G1:
            names.append(f"{e.id}.gap")
            lb.append(0.0)
            ub.append(gap_max)
            scale.append(1e-3)
        elif family is Family.G2:
            a1, a2, a3 = default_family_params(_widened(e), family)
            for nm, v in (("a1", a1), ("a2", a2), ("a3", a3)):
                names.append(f"{e.id}.{nm}")
                s = max(abs(v), {"a1": 0.05 * e.k, "a2": e.k / 1e-2, "a3": e.k / 1e-4}[nm])
                scale.append(s)
                lb.append(0.0 if nm != "a2" else -math.inf)
                ub.append(math.inf)
        else:
            names += [f"{e.id}.gap_app", f"{e.id}.stiffness"]
            lb += [_GAP_MIN_SMOOTH, 0.3]
            ub += [gap_max, 3.0]
            scale += [1e-3, 1.0]
    kgap = tuple(e.id for e in mill.elements if family is Family.G1 and e.k_gap > 0)
    wnames = list(LOAD_PARAMS) + [f"{eid}.open_frac" for eid in kgap]

    shared = ca.SX.sym("shared", len(names))
    win = ca.SX.sym("window", len(wnames))
    w = ca.SX.sym("w")
    p = [ca.SX(v) for v in drv.p_default]
    pidx = {n: i for i, n in enumerate(drv.param_names)}
    for j, e in enumerate(mill.elements):
        if family is Family.G1:
            gap = shared[names.index(f"{e.id}.gap")]
            p[pidx[f"{e.id}.gap"]] = gap
            if e.id in kgap:
                p[pidx[f"{e.id}.gap_open"]] = win[wnames.index(f"{e.id}.open_frac")] * gap
            else:
                p[pidx[f"{e.id}.gap_open"]] = ca.SX(0.0)
        elif family is Family.G2:
            for nm in ("a1", "a2", "a3"):
                p[pidx[f"{e.id}.{nm}"]] = shared[names.index(f"{e.id}.{nm}")]
        else:
            a0, sigma = _smooth_a0_sigma(family, e.k, shared[names.index(f"{e.id}.gap_app")],
                                         shared[names.index(f"{e.id}.stiffness")])
            p[pidx[f"{e.id}.a0"]] = a0
            p[pidx[f"{e.id}.sigma"]] = sigma
            p[pidx[f"{e.id}.shift"]] = ca.SX(0.0)
    if "smoothing" in pidx:
        p[pidx["smoothing"]] = w
    pmap = ca.Function("pmap", [shared, win, w], [ca.vertcat(*p)], ["shared", "window", "w"],
                       ["p"])

    t = ca.SX.sym("t")
    L0, L1, t_step, rise, s0, s1 = (win[i] for i in range(6))
    r = raised_cosine((t - t_step) / rise + 0.5, ca)
    u = (L0 + s0 * (t - t_step)) * (1 - r) + (L1 + s1 * (t - t_step)) * r
    load = ca.Function("load", [t, win], [u], ["t", "window"], ["T_load"])

    x = ca.SX.sym("x", drv.n_states)
    uu = ca.SX.sym("u", 1)
    pp = ca.SX.sym("p", drv.n_params)
    tt = ca.SX.sym("t")
    yall = drv.out(x, uu, pp, tt)
    idx = [drv.output_index(f"tau:{eid}") for eid in measured]
    y = ca.Function("y", [x, uu, pp, tt], [yall[idx]], ["x", "u", "p", "t"], ["y"])
    im = mill.mass_index(mill.motor.mass)
    return FitModel(mill=mill, family=family, driveline=drv, shared_names=tuple(names),
                    shared_lb=np.array(lb), shared_ub=np.array(ub),
                    shared_scale=np.array(scale), window_names=tuple(wnames), measured=measured,
                    pmap=pmap, load=load, y=y, gap_max=gap_max, x0_fixed=(im,),
                    motor_index=im, kgap_elements=kgap, effects=tuple(effects))


def _widened(e: Any) -> Any:
    """The element with a gap of at least 1 mrad (a g2 start that can still bend)."""
    import dataclasses
    if e.gap >= 1e-3:
        return e
    return dataclasses.replace(e, gap=1e-3, gap_open=0.5e-3)


def static_state(model: FitModel, level: float, shared: np.ndarray, window: np.ndarray, *,
                 open_frac: float | Sequence[float] = 0.5, w: float = 1e-4) -> np.ndarray:
    """A rest state under a constant load ``level`` (N*m): speeds 0, loop integral holding it.

    Element torques come from the static (gaps closed) equilibrium; a loaded
    element sits ``tau/k`` beyond its contact, an element carrying (nearly) no
    torque sits ``open_frac`` of its gap away from its drive-side contact.
    Angles are built from the deflections along a spanning tree from the motor
    (motor angle 0).

    Returns
    -------
    ndarray, shape (nx,)
    """
    mill = model.mill
    n = len(mill.masses)
    D = incidence(mill)
    K = stiffness_matrix(mill)
    im = model.motor_index
    f = np.zeros(n)
    for mid, s in zip(mill.load.masses, mill.load.share):
        f[mill.mass_index(mid)] -= s * level
    f[im] += level
    theta_lin = np.linalg.lstsq(K, f, rcond=None)[0]
    tau = np.array([e.k for e in mill.elements]) * (D @ theta_lin)
    fracs = np.broadcast_to(np.asarray(open_frac, dtype=float), (len(mill.elements),))
    gaps, contact = _gaps_and_contacts(model, shared)
    tol = 1e-3 * max(abs(level), 1.0)
    delta = np.empty(len(mill.elements))
    for j, e in enumerate(mill.elements):
        if tau[j] > tol:
            delta[j] = contact[j] + tau[j] / e.k
        elif tau[j] < -tol:
            delta[j] = contact[j] - gaps[j] + tau[j] / e.k
        else:
            delta[j] = contact[j] - fracs[j] * gaps[j]
    theta = angles_from_deflections(mill, delta, im)
    x = np.zeros(model.nx)
    x[:n] = theta
    x[2 * n] = level / mill.motor.ki if mill.motor.ki else 0.0
    x[2 * n + 1:] = model.driveline.x_idle[2 * n + 1:]
    return x


def _gaps_and_contacts(model: FitModel, shared: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    g = np.empty(len(model.mill.elements))
    c = np.empty(len(model.mill.elements))
    for j, e in enumerate(model.mill.elements):
        g[j], c[j] = model.equivalent_gap(e.id, shared)
        if not np.isfinite(g[j]):
            g[j], c[j] = 0.0, 0.0
    return g, c


