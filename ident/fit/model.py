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

With ``nuisance=True`` (:func:`build_fit_model`) the fit also carries what
plants record besides the driveline:

* **per-window channel offsets**: each torque channel reads its
  element's torque plus a constant over the window -- the strain gauge's zero,
  its slow drift and random walk.  Plants record offsets of a few per cent of
  the rolling torque, of either sign and different per channel; without them a
  floating spindle that reads 600 N*m between bars must be pulled onto a flank;
* **drag** (shared): a constant torque against rotation on one
  mass per measured element, where the losses of the masses between that
  element and the next measured ones act (:func:`drag_masses`).  Bearing and
  mesh losses make a motor-side channel read more than a roll-side one
  between bars and hold the gaps between them on their drive flanks; a load
  on the rolls alone cannot do either;
* the load ramp's **shape** (per window, :func:`ramp_shape`: a skew, and five
  weights that take the skewed cosine to linear, exponential or asymmetric
  ramps; the collocation frees the weights in a last solve only,
  :class:`ident.fit.collocation.Collocation`), and the idle side of each step
  held near the segmenter's idle level.

On plant recording cold-s5 seed 202 (``validation.plantsim``, gaps right) they
took the motor coupling's transient-band residual from 36 to 29 times its
noise (1.4 % of its transient), and on hsm-f1 seed 103 the motor coupling's
from 85 to 16 while others grew; the collocation solve took 2-4 times as
long (the offsets and the load are nearly interchangeable at rest).  Off by
default until a study shows what they buy (``ident fit --nuisance``).

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

Load ramp (``ident.model.scenario``): a ramp of duration ``rise`` centred on
``t_step``, from the level before, ``L0 + s0*(t - t_step)``, to the level after,
``L1 + s1*(t - t_step)``; the slopes take up the slow fluctuation of the rolling
torque (temperature, friction) over a window.  Without the nuisances the ramp
is the raised cosine (C1 in time and in its parameters); with them the cosine
skewed (:func:`skewed_cosine`) through the continuation, and in the
collocation's last solve :func:`ramp_shape`'s family (``load_shaped``), whose
weights free the rate at the ramp's ends and inside it: plants' bites and
releases are linear, exponential approaches or asymmetric S-curves as often as
cosines, and a cosine misses those by 4-12 % of the step, all of it at the
natural frequencies.  That shape is continuous in time but may start or stop at
full rate (a kink, as the plant's ramps have).  With ``ramp_weights`` the weights
are window parameters of the model, so that an estimate has one layout; the
skewed cosine does not read them.
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
from ..model.effects import Drag
from ..model.laws import smooth_max_c1
from ..model.linear import angles_from_deflections, incidence, stiffness_matrix
from ..model.scenario import nominal_torque

__all__ = ["FitModel", "build_fit_model", "drag_masses", "drag_groups", "LOAD_PARAMS", "GAP_MAX",
           "DRAG_MAX", "RAMP_PARAMS", "RAMP_KNOTS", "RAMP_WEIGHT_MAX", "ramp_shape",
           "raised_cosine", "skewed_cosine"]

#: Per-window load parameters, in order.
LOAD_PARAMS = ("L0", "L1", "t_step", "rise", "s0", "s1")

#: Knots of the load ramp's rate (:func:`ramp_shape`), as fractions of the ramp: Chebyshev
#: points, denser near the ends where plants' ramps change fastest (an exponential
#: approach starts at its steepest; a beta-shaped S rises steeply from one end).
RAMP_KNOTS = tuple(0.5 - 0.5 * math.cos(math.pi * k / 4) for k in range(5))

#: Rounding of a ramp's two ends, s (:func:`ramp_shape`'s ``corner``): below what a
#: plant's anti-alias filter resolves (half a sample at 1 kHz), and enough that the
#: load stays C1 in the ramp's timing where a weighted end starts at full rate.
RAMP_CORNER_S = 5e-4

#: Upper bound of a ramp weight (:func:`ramp_shape`): at this weight on every knot the
#: raised cosine keeps 1/(1 + 5 * 30) < 1 % of the ramp.
RAMP_WEIGHT_MAX = 30.0


#: Per-window weights of the load ramp's shape (:func:`ramp_shape`), one per knot, with the
#: nuisances.
RAMP_PARAMS = tuple(f"ramp{k}" for k in range(len(RAMP_KNOTS)))


#: Default upper bound of any gap, rad (reduced).
GAP_MAX = 0.03

#: Upper bound of a drag torque, as a fraction of the mill's nominal rolling torque
#: (:func:`ident.model.scenario.nominal_torque`): losses of a few per cent.
DRAG_MAX = 0.1

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
        Per-window parameters: :data:`LOAD_PARAMS`, ``"C46.open_frac"`` for
        g1 elements with ``k_gap > 0``, then with the nuisances the ramp's ``"skew"`` and
        shape weights (:data:`RAMP_PARAMS`) and ``"C46.offset"`` per measured element (N*m reduced,
        added to its output).
    measured : tuple of str
        Element ids with a torque channel, in output order.
    pmap : casadi.Function
        ``pmap(shared, window, w) -> p`` the driveline's parameter vector.
    load : casadi.Function
        ``load(t, window) -> T_load`` (N*m reduced), ``t`` relative to the window start:
        the skewed cosine (the ramp's shape weights, if any, are not read).
    load_shaped : casadi.Function or None
        With the nuisances, the same with the ramp's shape family (:func:`ramp_shape`,
        the weights :data:`RAMP_PARAMS` read): the collocation's last solve only
        (:class:`ident.fit.collocation.Collocation` ``ramp_polish``).
    y : casadi.Function
        ``y(x, u, p, t, window) -> reduced torques of the measured elements``
        (N*m), the window's channel offsets included.
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
    drag_masses: tuple[str, ...] = ()
    nuisance: bool = False
    drag_shares: tuple[tuple[tuple[str, float], ...], ...] = ()
    load_shaped: Any = None

    def drag(self, shared: np.ndarray) -> dict[str, float]:
        """Drag torque per group, N*m (reduced), keyed by the group's mass in
        :attr:`drag_masses` (the parameter ``"Q3.drag"``), from the shared vector."""
        return {mid: float(shared[self.shared_names.index(f"{mid}.drag")])
                for mid in self.drag_masses}

    def drag_torques(self, shared: np.ndarray) -> dict[str, float]:
        """Drag torque per mass, N*m (reduced): each group's spread over its masses
        (:func:`drag_groups`)."""
        out: dict[str, float] = {}
        for total, shares in zip(self.drag(shared).values(), self.drag_shares):
            for mid, w in shares:
                out[mid] = out.get(mid, 0.0) + w * total
        return out

    @property
    def offset_index(self) -> tuple[int, ...]:
        """Indices of the channel offsets in a window's parameter vector (measured order)."""
        return tuple(self.window_names.index(f"{eid}.offset") for eid in self.measured
                     if f"{eid}.offset" in self.window_names)

    @property
    def drag_index(self) -> tuple[int, ...]:
        """Indices of the drag parameters in the shared vector."""
        return tuple(self.shared_names.index(f"{mid}.drag") for mid in self.drag_masses)

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


def _hat_integral(s: Any, k: int, xp: Any) -> Any:
    """``int_0^s`` of the hat function on :data:`RAMP_KNOTS` peaking at knot ``k``, over its
    whole integral: 0 at ``s = 0``, 1 from the hat's last knot on; ``s`` in [0, 1]."""
    kn = RAMP_KNOTS
    out = 0.0
    area = 0.0
    if k > 0:  # rising flank on [kn[k-1], kn[k]]
        h = kn[k] - kn[k - 1]
        x = xp.fmin(xp.fmax(s - kn[k - 1], 0.0), h)
        out = out + x * x / (2.0 * h)
        area += 0.5 * h
    if k < len(kn) - 1:  # falling flank on [kn[k], kn[k+1]]
        h = kn[k + 1] - kn[k]
        x = xp.fmin(xp.fmax(s - kn[k], 0.0), h)
        out = out + x - x * x / (2.0 * h)
        area += 0.5 * h
    return out / area


def skewed_cosine(s: Any, skew: Any, xp: Any = np) -> Any:
    """The raised cosine over a warped time: ``(1 - cos(pi phi))/2``, ``phi = s + skew s (1 - s)``.

    ``s`` is clipped to [0, 1]; ``|skew| < 1`` keeps ``phi`` increasing, and the
    ramp's slope still vanishes at both ends (C1).  ``skew > 0`` front-loads the
    ramp (a bite whose torque rises fast and then approaches its level, as the
    exponential approach plants record), ``skew < 0`` back-loads it, 0 is the
    symmetric raised cosine.
    """
    sc = xp.fmin(xp.fmax(s, 0.0), 1.0)
    return 0.5 - 0.5 * xp.cos(math.pi * (sc + skew * sc * (1.0 - sc)))


def ramp_shape(s: Any, skew: Any = 0.0, weights: Sequence[Any] = (), xp: Any = np,
               corner: Any = 0.0) -> Any:
    """A load ramp's shape: 0 for ``s <= 0``, 1 for ``s >= 1``, monotone between.

    The weighted mean of the skewed cosine (weight 1, :func:`skewed_cosine`) and,
    with ``weights`` (each >= 0, one per knot of :data:`RAMP_KNOTS`), the ramps
    whose rate is a hat function on those knots:
    ``(sc(s) + sum_k w_k H_k(s)) / (1 + sum_k w_k)``, ``H_k`` the hat's integral
    over its whole.  The rate is then the cosine's bell plus a piecewise-linear
    function, free to be nonzero at either end: a linear ramp (large weights in
    proportion to the hats' areas), an exponential approach (the rate falling
    from its start), an asymmetric S.  All weights 0 is the skewed cosine.
    Fitted by least squares over shift, duration and weights, the linear,
    exponential (rate 2-5) and beta-shaped (exponents 1.3-3) ramps that plants
    record lie within 0.9 % of the step of this family; the skewed cosine alone
    misses the linear and exponential ones by 4-12 %
    (``tests/test_fit_nuisance.py``).  The rate may jump at the ends (a ramp
    that starts at full speed); ``corner`` rounds those two corners (C1, exact
    outside ``corner/2`` of each end) so that the fit's equations stay
    differentiable in the ramp's timing.

    Parameters
    ----------
    s : float or array or casadi.SX
        Time from the ramp's start over its duration (clipped to [0, 1]).
    skew : float or casadi.SX
        The cosine's skew (:func:`skewed_cosine`), in (-1, 1).
    weights : sequence
        One weight per knot of :data:`RAMP_KNOTS`, or none (the skewed cosine).
    xp : module
        ``numpy`` or ``casadi``.
    corner : float or casadi.SX
        Width of the rounding at each end, in units of ``s`` (0: sharp).
    """
    if isinstance(corner, (int, float)) and corner == 0:
        sc = xp.fmin(xp.fmax(s, 0.0), 1.0)
    else:
        sc = smooth_max_c1(s, corner, xp) - smooth_max_c1(s - 1.0, corner, xp)
    num = skewed_cosine(sc, skew, xp)
    den = 1.0
    for k, wk in enumerate(weights):
        num = num + wk * _hat_integral(sc, k, xp)
        den = den + wk
    return num / den


def build_fit_model(mill: Mill, *, family: Family | str = Family.G1, effects: Sequence = (),
                    gap_max: float = GAP_MAX, smoothing_kind: str = "c1",
                    nuisance: bool = False, ramp_weights: bool = False) -> FitModel:
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
    nuisance : bool
        Also fit the plant nuisances (module docstring): a drag torque on each
        of :func:`drag_masses`, a constant offset per window on every torque
        channel and the ramp's skew (:func:`skewed_cosine`); the windows' idle side is then
        bounded to the idle level (:meth:`ident.fit.problem.Problem.window_bounds`).
    ramp_weights : bool
        With ``nuisance``, also the ramp's shape weights (:data:`RAMP_PARAMS`, window
        parameters that ``load`` does not read) and ``load_shaped``, which reads them: for
        the collocation's polish (:class:`ident.fit.collocation.Collocation` ``ramp_polish``).

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
    groups = drag_groups(mill) if nuisance else ()
    dmasses = tuple(rep for rep, _ in groups)
    shares = tuple(tuple(sh) for _, sh in groups)
    dall = tuple(dict.fromkeys(mid for sh in shares for mid, _ in sh))
    drv = build_driveline(mill, ModelOptions(family=family, smoothing=smoothing,
                                             smoothing_kind=smoothing_kind,
                                             effects=tuple(effects) + tuple(
                                                 Drag(mid) for mid in dall)))
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
    t_nom = nominal_torque(mill)
    for mid in dmasses:
        names.append(f"{mid}.drag")
        lb.append(0.0)
        ub.append(DRAG_MAX * t_nom)
        scale.append(0.01 * t_nom)
    kgap = tuple(e.id for e in mill.elements if family is Family.G1 and e.k_gap > 0)
    wnames = list(LOAD_PARAMS) + [f"{eid}.open_frac" for eid in kgap]
    if nuisance:
        wnames += ["skew", *(RAMP_PARAMS if ramp_weights else ())]
        wnames += [f"{eid}.offset" for eid in measured]

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
    for mid in dall:
        p[pidx[Drag(mid).param_key("torque")]] = ca.SX(0.0)
    for rep, sh in zip(dmasses, shares):
        for mid, wgt in sh:
            p[pidx[Drag(mid).param_key("torque")]] += wgt * shared[names.index(f"{rep}.drag")]
    if "smoothing" in pidx:
        p[pidx["smoothing"]] = w
    pmap = ca.Function("pmap", [shared, win, w], [ca.vertcat(*p)], ["shared", "window", "w"],
                       ["p"])

    t = ca.SX.sym("t")
    L0, L1, t_step, rise, s0, s1 = (win[i] for i in range(6))
    skew = win[wnames.index("skew")] if nuisance else 0.0
    sc = (t - t_step) / rise + 0.5

    def ramp_load(r: Any) -> Any:
        return (L0 + s0 * (t - t_step)) * (1 - r) + (L1 + s1 * (t - t_step)) * r

    load = ca.Function("load", [t, win], [ramp_load(skewed_cosine(sc, skew, ca))],
                       ["t", "window"], ["T_load"])
    load_shaped = None
    if nuisance and ramp_weights:  # the shape family, used by the collocation's polish only
        weights = [win[wnames.index(nm)] for nm in RAMP_PARAMS]
        r = ramp_shape(sc, skew, weights, ca, corner=RAMP_CORNER_S / rise)
        load_shaped = ca.Function("load_shaped", [t, win], [ramp_load(r)], ["t", "window"],
                                  ["T_load"])

    x = ca.SX.sym("x", drv.n_states)
    uu = ca.SX.sym("u", 1)
    pp = ca.SX.sym("p", drv.n_params)
    tt = ca.SX.sym("t")
    yall = drv.out(x, uu, pp, tt)
    idx = [drv.output_index(f"tau:{eid}") for eid in measured]
    wy = ca.SX.sym("window", len(wnames))
    off = (ca.vertcat(*[wy[wnames.index(f"{eid}.offset")] for eid in measured]) if nuisance
           else ca.SX.zeros(len(measured)))
    y = ca.Function("y", [x, uu, pp, tt, wy], [yall[idx] + off],
                    ["x", "u", "p", "t", "window"], ["y"])
    im = mill.mass_index(mill.motor.mass)
    return FitModel(mill=mill, family=family, driveline=drv, shared_names=tuple(names),
                    shared_lb=np.array(lb), shared_ub=np.array(ub),
                    shared_scale=np.array(scale), window_names=tuple(wnames), measured=measured,
                    pmap=pmap, load=load, load_shaped=load_shaped, y=y, gap_max=gap_max,
                    x0_fixed=(im,),
                    motor_index=im, kgap_elements=kgap, effects=tuple(effects),
                    drag_masses=dmasses, nuisance=bool(nuisance), drag_shares=shares)


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
    for mid, d in model.drag_torques(shared).items():  # the motor supplies the losses too
        f[mill.mass_index(mid)] -= d
        f[im] += d
    theta_lin = np.linalg.lstsq(K, f, rcond=None)[0]
    tau = np.array([e.k for e in mill.elements]) * (D @ theta_lin)
    fracs = np.broadcast_to(np.asarray(open_frac, dtype=float), (len(mill.elements),))
    gaps, contact = _gaps_and_contacts(model, shared)
    tol = 1e-3 * max(abs(level), float(np.max(np.abs(tau), initial=0.0)), 1.0)
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
    x[2 * n] = float(f[im]) / mill.motor.ki if mill.motor.ki else 0.0
    x[2 * n + 1:] = model.driveline.x_idle[2 * n + 1:]
    return x


def drag_masses(mill: Mill) -> tuple[str, ...]:
    """Where the fit's drag parameters are named: one mass per group of :func:`drag_groups`
    (the group's mass farthest from the motor), in the order of the measured elements."""
    return tuple(rep for rep, _ in drag_groups(mill))


def drag_groups(mill: Mill) -> tuple[tuple[str, tuple[tuple[str, float], ...]], ...]:
    """The fit's drag torques: one per measured element that has losses to carry.

    For each measured element (torque channel), its *group* is the masses on
    its side away from the motor that are neither load masses nor beyond a
    further measured element: the masses whose losses it alone carries among
    the channels.  Static torques tell the groups apart, not the masses within
    one, so each group gets one drag torque, spread over its masses in
    proportion to their inertia: bearing and windage losses grow with the
    size of the rotating parts.  (Concentrated on one mass instead, a plant
    recording whose losses sat on every shaft -- ``validation.plantsim``,
    hsm-f1 seed 1000 -- kept twice the noise in the spindles' transient band.)
    A group of no mass (a channel next to the rolls) gets none.

    Returns
    -------
    tuple of (str, tuple of (str, float))
        Per group, in the order of the measured elements: the mass that names
        its parameter (``"Q3.drag"``: the group's mass farthest from the
        motor) and each member mass with its share of the torque (summing to 1).
    """
    im = mill.mass_index(mill.motor.mass)
    n = len(mill.masses)
    adj: dict[int, list[tuple[int, int]]] = {i: [] for i in range(n)}
    for j, e in enumerate(mill.elements):
        a, b = mill.mass_index(e.from_), mill.mass_index(e.to)
        adj[a].append((b, j))
        adj[b].append((a, j))
    depth = {im: 0}
    parent_el: dict[int, int] = {}
    order = [im]
    for i in order:  # breadth first from the motor
        for k, j in adj[i]:
            if k not in depth:
                depth[k] = depth[i] + 1
                parent_el[k] = j
                order.append(k)

    def beyond(j: int) -> set[int]:
        e = mill.elements[j]
        a, b = mill.mass_index(e.from_), mill.mass_index(e.to)
        root = b if depth.get(b, -1) > depth.get(a, -1) else a
        out, todo = set(), [root]
        while todo:
            i = todo.pop()
            out.add(i)
            todo += [k for k, jj in adj[i] if depth.get(k, -1) > depth[i] and parent_el.get(k) == jj]
        return out

    measured = list(dict.fromkeys(c.element for c in mill.torque_channels()))
    idx = {e.id: j for j, e in enumerate(mill.elements)}
    sides = {eid: beyond(idx[eid]) for eid in measured}
    loads = {mill.mass_index(m) for m in mill.load.masses}
    out: dict[str, tuple[tuple[str, float], ...]] = {}
    for eid in measured:
        group = set(sides[eid]) - loads
        for other in measured:
            if other != eid and sides[other] < sides[eid]:
                group -= sides[other]
        if group:
            far = max(group, key=lambda i: (depth[i], i))
            members = sorted(group)
            J = np.array([mill.masses[i].J for i in members])
            out.setdefault(mill.masses[far].id, tuple(
                (mill.masses[i].id, float(w)) for i, w in zip(members, J / J.sum())))
    return tuple(out.items())




def _gaps_and_contacts(model: FitModel, shared: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    g = np.empty(len(model.mill.elements))
    c = np.empty(len(model.mill.elements))
    for j, e in enumerate(model.mill.elements):
        g[j], c[j] = model.equivalent_gap(e.id, shared)
        if not np.isfinite(g[j]):
            g[j], c[j] = 0.0, 0.0
    return g, c


