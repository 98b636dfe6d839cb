"""Window simulation and least-squares refits of the model with candidate effects.

Why not ``ident.fit``: the collocation fit identifies gaps with every window's
state trajectory as decision variables, which is the right tool for one model.
The discrepancy workflow refits many models (the mill file's and one per
candidate effect, on every cross-validation fold) and needs effect parameters
as decision variables, so it uses single shooting on the model's public
building blocks (``build_driveline`` and the compiled RK4 of
``ident.model.integrate``) with scipy's trust-region least squares.

One compiled model per mill and candidate set
---------------------------------------------
:func:`build_engine` builds the driveline with *every* candidate, each wrapped
in :class:`~ident.model.effects.Gated`; a candidate is switched on by its gate
(1) and off (0).  Gated off, the model is exactly the mill file's, so a single
compiled integrator (cached on disk by ``ident.model.integrate``) serves the
baseline, every candidate and the signature scores.

Parameters
----------
* **shared** (one value for all windows): the gap of every element the mill
  file gives a gap (g1 with the fit's convention: drive-side contact at
  ``delta = 0``, the whole gap on the negative side), plus the active
  candidate's free parameters; a backlash candidate frees its tight element's
  gap;
* **per window** (:data:`WINDOW_PARAMS`): the load ramp ``L0, L1, t_step,
  rise`` (a raised cosine centred on ``t_step``, as ``ident.model.scenario``),
  ``frac`` (where unloaded elements sit in their gaps at the start of a bite
  from idle: 0 on the drive flank, 1 on the back flank) and ``slope``
  (N*m/s, a slow drift of the rolling load on the loaded side: the load's
  fluctuation) and ``history`` (1: a bite after a release starts where the
  model's own run through the idle time leaves it, see below; 0: at rest at
  ``frac``); then offsets of every mass's angle (rad) and speed (rad/s)
  from the rest state, free for bites from idle (``free_x0``): an idling
  driveline is not at rest (ring-down of the last release, rattle of a
  swinging spindle gap), and where its elements float in their gaps is not
  observable before the bite.

The per-window parameters make local minima: the ramp's duration and instant
and the gap positions set when flanks meet, so the timing of every impact.
The segmenter times the step in the measured torque, which lags the load, and
its 10-90 % rise of a ringing torque can be far off, so fits start from the
best rows of a grid over ``rise``, ``t_step`` and ``frac``
(:func:`ramp_starts`) rather than from the segmenter's estimates alone.

Initial states are rest states: loaded elements in contact, found by a
damped Newton solve of the model's own statics (knees, strip loop, gap shifts
and the lag state included); unloaded elements placed by ``frac``.  With a
candidate tied to the roll angle (``needs_history``: spindle imbalance) a bite
after a release can start instead where the model itself leaves the driveline:
simulated from the loaded rest before that release (segmenter's estimates of
its load step) through the idle time, because the idle rattle and so the bite
depend on the roll angle (effects.md: "the bite transient changes from bar to
bar with the roll angle at bite").  A rattle is sensitive (a few impacts over
a second of idling), so the simulated start is one of the starts each such
window chooses from (``history`` 1 or 0), not forced on it.  Idle elements are
placed within their gaps as the candidate shifts them at the window's start.

The g1 kinks are rounded over ``smoothing`` (10 urad) in windows, over
``idle_smoothing`` (0.1 urad) in runs through the idle time: the rounding's
tail is a faint spring across every open gap, harmless over a window but
enough over a second of idling to float the rolls by a good part of their
gaps (the width is a model parameter, so one compiled integrator does both).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import casadi as ca
import numpy as np

from ..description import Mill
from ..errors import FitError
from ..model.dynamics import Driveline, Family, ModelOptions, build_driveline
from ..model.effects import Gated
from ..model.integrate import Stepper, make_stepper, stage_times
from ..model.linear import angles_from_deflections
from .windows import Window

__all__ = ["WINDOW_PARAMS", "Engine", "Setup", "State", "Layout", "FitOutcome", "build_engine",
           "simulate_windows", "fit", "fit_nuisance", "nrmse", "channel_scales", "scan_frac",
           "scan_ramp", "ramp_starts", "RAMP_GRID_S", "SHIFT_GRID_S"]

#: Per-window nuisance parameters, in order.
WINDOW_PARAMS = ("L0", "L1", "t_step", "rise", "frac", "slope", "history")

_TOL_LOADED = 0.05  # an element carries load when |tau| > 5 % of the step
_I_HISTORY = WINDOW_PARAMS.index("history")
_I_FRAC = WINDOW_PARAMS.index("frac")


@dataclass(frozen=True, eq=False)
class Engine:
    """The compiled model of one mill with its candidates, for one window shape.

    Attributes
    ----------
    mill : Mill
    candidates : tuple of Effect
        Inner (ungated) effects; index ``i`` is switched on by
        :meth:`Setup.for_candidate`.
    driveline : Driveline
    stepper : Stepper
        Compiled RK4 over one window.
    dt : float
        Sample interval, s.
    n_samples : int
    measured : tuple of str
        Element ids compared with data (output order of :func:`simulate_windows`).
    gapped : tuple of str
        Elements whose gap the mill file gives (free in every fit).
    smoothing, idle_smoothing : float
        Kink rounding widths in windows and in runs through the idle time, rad
        (the driveline's ``smoothing`` parameter; see :func:`build_engine`).
    """

    mill: Mill
    candidates: tuple
    driveline: Driveline
    stepper: Stepper
    dt: float
    n_samples: int
    measured: tuple[str, ...]
    gapped: tuple[str, ...]
    y_index: np.ndarray
    statics: Any
    n_sub: int
    smoothing: float
    idle_smoothing: float
    _cache: dict = field(default_factory=dict, repr=False)

    def candidate_index(self, key: str) -> int:
        """Index of the candidate ``name@location``.

        Softening and hardening share one term (stiffness ``k_ratio * k`` beyond a
        knee), so either name finds an engine holding the other at that element.
        """
        keys = [f"{c.name}@{c.location}" for c in self.candidates]
        if key in keys:
            return keys.index(key)
        name, loc = key.split("@", 1)
        twin = {"softening_stiffness": "hardening_stiffness",
                "hardening_stiffness": "softening_stiffness"}.get(name)
        if twin is not None and f"{twin}@{loc}" in keys:
            return keys.index(f"{twin}@{loc}")
        raise KeyError(key)

    def candidate_key(self, key: str) -> str:
        """The engine's own key for candidate ``key`` (see :meth:`candidate_index`)."""
        return self.candidates[self.candidate_index(key)].key

    def p_index(self, name: str) -> int:
        """Index of the driveline parameter ``name`` (as ``Driveline.param_index``, cached)."""
        idx = self._cache.get("p_index")
        if idx is None:
            idx = self._cache["p_index"] = {nm: i for i, nm in
                                            enumerate(self.driveline.param_names)}
        try:
            return idx[name]
        except KeyError:
            return self.driveline.param_index(name)  # raises the driveline's own error

    def base_params(self) -> np.ndarray:
        """Mill-file gaps (fit convention), every candidate gated off at its neutral values."""
        drv = self.driveline
        p = drv.p_default.copy()
        p[self.p_index("smoothing")] = self.smoothing
        for e in self.mill.elements:
            p[self.p_index(f"{e.id}.gap")] = e.gap
            p[self.p_index(f"{e.id}.gap_open")] = 0.0
        for c in self.candidates:
            for k, v in c.neutral(self.mill).items():
                p[self.p_index(f"{c.key}.{k}")] = v
            p[self.p_index(f"{c.key}.gate")] = 0.0
        return p


def build_engine(mill: Mill, candidates: Sequence[Any], *, dt: float, n_samples: int,
                 n_sub: int = 1, smoothing: float = 1e-5, idle_smoothing: float = 1e-7,
                 compile: bool = True) -> Engine:
    """Build (and compile, once per mill and candidate set) the window model.

    Parameters
    ----------
    mill : Mill
    candidates : sequence of Effect
        Effects of ``ident.model.effects`` (backlash candidates are handled by
        freeing the element's gap and need not be listed).
    dt : float
        Sample interval of the windows, s.
    n_samples : int
        Samples per window (the integrator's length; shorter windows are padded).
    n_sub : int
        RK4 steps per sample.
    smoothing : float
        g1 kink rounding width, rad.
    idle_smoothing : float
        Kink rounding width for runs through the idle time before a bite, rad.
        The rounding's tail leaves a faint spring across every open gap (about
        ``k w**2 / 4|d|``: 0.5 N*m for a spindle at 10 urad), harmless over a
        window but enough over a second of idling to float the rolls by a good
        part of their gaps, and so to move every impact of the next bite.  (A
        tail-free rounding would do too, but the fits need the tail's gradient.)
    """
    cands = tuple(candidates)
    drv = build_driveline(mill, ModelOptions(family=Family.G1, smoothing="param",
                                             effects=tuple(Gated(c, 0.0) for c in cands)))
    stepper = make_stepper(drv, interval=dt, n_sub=n_sub, chunk=n_samples - 1, compile=compile,
                           stage_inputs=True)
    measured = tuple(dict.fromkeys(c.element for c in mill.torque_channels()))
    if not measured:
        raise FitError(f"mill '{mill.name}' has no torque channel: nothing to compare.")
    y_index = np.array([drv.output_index(f"tau:{e}") for e in measured])
    gapped = tuple(e.id for e in mill.elements if e.gap > 0)
    return Engine(mill=mill, candidates=cands, driveline=drv, stepper=stepper, dt=dt,
                  n_samples=n_samples, measured=measured, gapped=gapped, y_index=y_index,
                  statics=_statics_function(drv, mill), n_sub=n_sub, smoothing=smoothing,
                  idle_smoothing=idle_smoothing)


def _statics_function(drv: Driveline, mill: Mill) -> Any:
    """``F(v, theta_m, p, u, t) -> (res, jac)``: rest residual over the angles (motor's given), z, extras."""
    n = len(mill.masses)
    im = mill.mass_index(mill.motor.mass)
    nx = drv.n_states
    n_extra = nx - (2 * n + 1)
    v = ca.SX.sym("v", (n - 1) + 1 + n_extra)
    p = ca.SX.sym("p", drv.n_params)
    u = ca.SX.sym("u")
    t = ca.SX.sym("t")
    tm = ca.SX.sym("theta_m")
    others = [i for i in range(n) if i != im]
    theta = [tm] * n
    for k, i in enumerate(others):
        theta[i] = v[k]
    x = ca.vertcat(ca.vertcat(*theta), ca.SX.zeros(n), v[n - 1], v[n:])
    xdot = drv.rhs(x, u, p, t)
    J = np.array([m.J for m in mill.masses])
    res = ca.vertcat(xdot[n:2 * n] * ca.DM(J / J.max()), xdot[2 * n + 1:])
    return ca.Function("statics", [v, tm, p, u, t], [res, ca.jacobian(res, v)])


# ---- states of a fit --------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class State:
    """A point of the refit's parameter space.

    Attributes
    ----------
    p : ndarray, shape (n_params,)
        The driveline's full parameter vector (gates included).
    W : ndarray, shape (n_windows, len(WINDOW_PARAMS) + 2 * n_masses)
        Per-window load parameters (``t_step`` absolute, s), then the initial
        angle and speed offsets of every mass (rad, rad/s).
    """

    p: np.ndarray
    W: np.ndarray

    def subset(self, idx: Sequence[int]) -> "State":
        """The same parameters with the window rows ``idx``."""
        return State(p=self.p.copy(), W=self.W[list(idx)].copy())

    def moved(self, src: "Engine", dst: "Engine") -> "State":
        """This state (of engine ``src``) in engine ``dst``'s parameter layout.

        Parameters both drivelines know keep their values; the rest take
        ``dst``'s :meth:`Engine.base_params` (candidates off).
        """
        p = dst.base_params()
        names = src.driveline.param_names
        for i, nm in enumerate(dst.driveline.param_names):
            if nm in names:
                p[i] = self.p[names.index(nm)]
        return State(p=p, W=self.W.copy())


@dataclass(frozen=True)
class Setup:
    """Which parameters a fit frees, with bounds and scales.

    Attributes
    ----------
    shared : tuple of int
        Driveline parameter indices that are free.
    lower, upper, scale : ndarray
        Bounds and scales of the free shared parameters.
    active : int or None
        Index of the candidate switched on (gate 1), None for the mill file's model.
    """

    shared: tuple[int, ...]
    lower: np.ndarray
    upper: np.ndarray
    scale: np.ndarray
    active: int | None = None

    @staticmethod
    def baseline(engine: Engine) -> "Setup":
        """The mill file's model: gaps of the gapped elements free."""
        idx, lo, hi, sc = [], [], [], []
        for eid in engine.gapped:
            idx.append(engine.p_index(f"{eid}.gap"))
            lo.append(0.0)
            hi.append(0.03)
            sc.append(1e-3)
        return Setup(shared=tuple(idx), lower=np.array(lo), upper=np.array(hi),
                     scale=np.array(sc), active=None)

    @staticmethod
    def for_candidate(engine: Engine, key: str) -> "Setup":
        """The mill file's model plus candidate ``name@location`` with its free parameters.

        ``backlash@E`` frees the gap of element ``E`` instead (no gate).
        """
        base = Setup.baseline(engine)
        name, loc = key.split("@", 1)
        if name == "backlash":
            i = engine.p_index(f"{loc}.gap")
            return Setup(shared=base.shared + (i,), lower=np.append(base.lower, 0.0),
                         upper=np.append(base.upper, 0.03), scale=np.append(base.scale, 1e-3),
                         active=None)
        from ..model.effects import make_effect

        ci = engine.candidate_index(key)
        ekey = engine.candidates[ci].key
        idx, lo, hi, sc = list(base.shared), list(base.lower), list(base.upper), list(base.scale)
        for s in make_effect(name, loc).specs(engine.mill):
            if s.free:
                idx.append(engine.p_index(f"{ekey}.{s.name}"))
                lo.append(s.lower)
                hi.append(s.upper)
                sc.append(s.scale)
        return Setup(shared=tuple(idx), lower=np.array(lo), upper=np.array(hi),
                     scale=np.array(sc), active=ci)

    def with_active(self, active: int | None) -> "Setup":
        """The same free parameters with candidate ``active`` switched on."""
        return replace(self, active=active)

    def apply_gates(self, engine: Engine, p: np.ndarray) -> np.ndarray:
        """``p`` with the active candidate's gate 1 and every other gate 0."""
        p = p.copy()
        for i, c in enumerate(engine.candidates):
            p[engine.p_index(f"{c.key}.gate")] = 1.0 if i == self.active else 0.0
        return p

    @property
    def n_shared(self) -> int:
        return len(self.shared)


# ---- simulation of windows ------------------------------------------------------------------
def _load(w: Window, wp: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Total rolling torque at times ``t`` (s, absolute), N*m reduced."""
    L0, L1, ts, rise, _, slope = wp[:6]
    s = np.clip((t - ts) / rise + 0.5, 0.0, 1.0)
    r = 0.5 - 0.5 * np.cos(np.pi * s)
    loaded = r if w.kind == "bite" else 1.0 - r
    return L0 + (L1 - L0) * r + slope * (t - ts) * loaded


def starts_idle(w: Window) -> bool:
    """A bite from (nearly) no load: elements start somewhere in their gaps."""
    return w.kind == "bite" and abs(w.level_before) < _TOL_LOADED * abs(
        w.level_after - w.level_before)


def _layout(engine: Engine) -> dict:
    """Per-engine constants of :func:`initial_state` (computed once)."""
    got = engine._cache.get("layout")
    if got is None:
        mill = engine.mill
        n = len(mill.masses)
        im = mill.mass_index(mill.motor.mass)
        ne = len(mill.elements)
        # angles are linear in the deflections (spanning tree, motor angle 0)
        M = np.stack([angles_from_deflections(mill, np.eye(ne)[j], im) for j in range(ne)],
                     axis=1)
        got = engine._cache["layout"] = {
            "n": n, "im": im, "angles": M, "k": np.array([e.k for e in mill.elements]),
            "gap_index": _gap_index(engine), "shares": _shares(engine)}
    return got


def initial_state(engine: Engine, w: Window, p: np.ndarray, wp: np.ndarray) -> np.ndarray:
    """Rest state at the window's start under the load ``L0`` (see the module docstring)."""
    mill = engine.mill
    drv = engine.driveline
    lay = _layout(engine)
    n, im = lay["n"], lay["im"]
    L0 = float(wp[0])
    t0 = float(w.t[0])
    tau = lay["shares"] * L0
    idle = starts_idle(w)
    frac = float(wp[_I_FRAC])
    gaps = p[lay["gap_index"]]
    k_el = lay["k"]
    shift = _open_shifts(engine, p, t0)
    if idle:
        delta = shift - frac * gaps
    else:
        delta = shift + np.where(tau > 0, tau / k_el, -gaps + tau / k_el)
        delta = np.where(tau == 0.0, shift - frac * gaps, delta)
    z = L0 / mill.motor.ki if mill.motor.ki else 0.0
    # absolute angles: the speed loop's integral z = -(motor angle) for a recording that
    # started at rest (roll-angle effects see it; a constant offset goes into their phase)
    theta = lay["angles"] @ delta - z
    x = drv.x_idle.copy()
    x[:n] = theta
    x[n:2 * n] = 0.0
    x[2 * n] = z
    k = 2 * n + 1
    for c in engine.candidates:
        st = c.static_states(mill, L0)
        x[k:k + len(st)] = st
        k += len(st)
    if _needs_statics(engine, p) and not idle:
        cache = engine._cache.setdefault("statics", {})
        key = (p.tobytes(), x.tobytes(), L0, t0)
        got = cache.get(key)
        if got is None:
            if len(cache) > 256:
                cache.clear()
            got = cache[key] = _refine_statics(engine, x, p, L0, t0, im)
        x = got.copy()
    off = wp[len(WINDOW_PARAMS):]
    if off.size:
        x[:n] += off[:n]
        x[n:2 * n] += off[n:2 * n]
    return x


def _open_shifts(engine: Engine, p: np.ndarray, t: float) -> np.ndarray:
    """Per element, how far active candidates shift the gap's open part at ``t``, rad.

    A swinging spindle gap (imbalance) moves both flanks: an element placed at
    ``frac`` of its gap must be placed within the shifted gap, or it starts
    pressed into a flank.  The roll angle's own offset (mrad) is neglected.
    """
    out = np.zeros(len(engine.mill.elements))
    for c in engine.candidates:
        if not hasattr(c, "open_shift"):
            continue
        g = float(p[engine.p_index(f"{c.key}.gate")])
        if g == 0.0:
            continue
        a = float(p[engine.p_index(f"{c.key}.amplitude")])
        ph = float(p[engine.p_index(f"{c.key}.phase")])
        out[engine.mill.element_ids.index(c.location)] += g * c.open_shift(engine.mill, a, ph, t)
    return out


#: Candidates whose rest state under load differs from the contact solution.
_STATIC_EFFECTS = ("softening_stiffness", "hardening_stiffness", "strip_coupling",
                   "spindle_imbalance")


def _needs_statics(engine: Engine, p: np.ndarray) -> bool:
    for c in engine.candidates:
        if c.name in _STATIC_EFFECTS and p[engine.p_index(f"{c.key}.gate")] != 0.0:
            return True
    return False


def _refine_statics(engine: Engine, x: np.ndarray, p: np.ndarray, L0: float, t0: float,
                    im: int) -> np.ndarray:
    """Damped Newton on the rest equations, from ``x``."""
    n = len(engine.mill.masses)
    others = [i for i in range(n) if i != im]
    v = np.concatenate([x[others], [x[2 * n]], x[2 * n + 1:]])
    scale = max(abs(L0), 1.0)
    jmax = max(m.J for m in engine.mill.masses)
    lam = 1e-6
    for _ in range(30):
        r, J = engine.statics(v, x[im], p, L0, t0)
        r = np.asarray(r).ravel()
        J = np.asarray(J)
        if np.max(np.abs(r)) * jmax < 1e-7 * scale:
            break
        JTJ = J.T @ J
        step = np.linalg.solve(JTJ + lam * np.diag(np.diag(JTJ) + 1e-30), -J.T @ r)
        v_new = v + step
        r_new = np.asarray(engine.statics(v_new, x[im], p, L0, t0)[0]).ravel()
        if np.sum(r_new ** 2) < np.sum(r ** 2):
            v = v_new
            lam = max(lam / 10, 1e-12)
        else:
            lam *= 10
            if lam > 1e6:
                break
    out = x.copy()
    out[others] = v[: n - 1]
    out[2 * n] = v[n - 1]
    out[2 * n + 1:] = v[n:]
    return out


def _gap_index(engine: Engine) -> np.ndarray:
    got = engine._cache.get("gap_index")
    if got is None:
        got = engine._cache["gap_index"] = np.array(
            [engine.p_index(f"{e.id}.gap") for e in engine.mill.elements])
    return got


def _shares(engine: Engine) -> np.ndarray:
    got = engine._cache.get("shares")
    if got is None:
        from ..segment.loadshare import load_fractions

        fr = load_fractions(engine.mill)
        got = np.array([fr[e.id] for e in engine.mill.elements])
        engine._cache["shares"] = got
    return got


def needs_history(engine: Engine, p: np.ndarray) -> bool:
    """An active candidate makes the idle state depend on the roll angle's history."""
    return any(getattr(c, "needs_history", False) and p[engine.p_index(f"{c.key}.gate")] != 0
               for c in engine.candidates)


def can_use_history(engine: Engine, w: Window, p: np.ndarray) -> bool:
    """Window ``w`` may start from the model's own run through the idle time before it."""
    return w.history is not None and starts_idle(w) and needs_history(engine, p)


def uses_history(engine: Engine, w: Window, p: np.ndarray, wp: np.ndarray) -> bool:
    """Window ``w`` with row ``wp`` starts from the simulated idle (else at rest at ``frac``).

    The ``history`` column chooses (1 simulated, 0 at rest): an idle rattle is
    sensitive (impacts), and where the simulation loses it the bite is better
    started like any other model's, at rest somewhere in the gaps.
    """
    return can_use_history(engine, w, p) and float(wp[_I_HISTORY]) > 0.5


def _run(engine: Engine, x0: np.ndarray, U: np.ndarray, p: np.ndarray, t0: float
         ) -> tuple[np.ndarray, np.ndarray]:
    """Chunks of the compiled integrator over stage loads ``U`` (n_intervals, 2*n_sub+1)."""
    st = engine.stepper
    C = st.chunk
    xs, ys = [], []
    x = x0
    k = 0
    pd = ca.DM(p)
    while k < U.shape[0]:
        m = min(C, U.shape[0] - k)
        Uc = U[k:k + m]
        if m < C:
            Uc = np.vstack([Uc, np.full((C - m, U.shape[1]), Uc[-1, -1])])
        tt = t0 + (k + np.arange(C)) * st.interval
        X, Y = st.fn(x, Uc.T, pd, tt[None, :])
        X = np.asarray(X)
        xs.append(X[:, :m])
        ys.append(np.asarray(Y)[:, :m])
        x = X[:, m - 1]
        k += m
    return np.hstack(xs), np.hstack(ys)


def _history_state(engine: Engine, w: Window, p: np.ndarray, wp: np.ndarray) -> np.ndarray:
    """State at the window's start, run from the loaded rest before the previous release."""
    key = ("history", w.label, float(w.t[0]), p.tobytes())
    got = engine._cache.get(key)
    if got is not None:
        return got
    t_rel, before, after, rise = w.history
    st = engine.stepper
    t_pre = t_rel - 0.1
    n_int = int(round((w.t[0] - t_pre) / st.interval))
    t_pre = float(w.t[0]) - n_int * st.interval
    fake = Window(t=t_pre + np.arange(16) * st.interval, elements=w.elements,
                  y=np.zeros((16, len(w.elements))), t_step=t_rel, kind="release",
                  level_before=before, level_after=after, bar=w.bar)
    wr = np.zeros_like(wp)
    wr[:6] = [before, after, t_rel, rise, 0.0, 0.0]  # a loaded release: no history
    x = initial_state(engine, fake, p, wr)
    T = stage_times(st, n_int + 1, t_pre)
    U = _load(fake, wr, T)
    idle = T >= t_rel + rise
    U[idle] = after  # the segmenter's idle level: the long idle run must not follow the
    # bite's fitted level (a rattle is sensitive, and the history would move with it)
    ph = p.copy()
    ph[engine.p_index("smoothing")] = engine.idle_smoothing
    X, _ = _run(engine, x, U, ph, t_pre)
    x0 = X[:, -1]
    if len(engine._cache) > 64:
        for k in [k for k in engine._cache if isinstance(k, tuple)]:
            del engine._cache[k]
    engine._cache[key] = x0
    return x0


def simulate_window(engine: Engine, w: Window, p: np.ndarray, wp: np.ndarray) -> np.ndarray:
    """Model torques of the measured elements over one window, shape (N, ny), N*m reduced."""
    st = engine.stepper
    N = w.n_samples
    if uses_history(engine, w, p, wp):
        x0 = _history_state(engine, w, p, wp)
    else:
        x0 = initial_state(engine, w, p, wp)
    T = stage_times(st, N, float(w.t[0]))
    U = _load(w, wp, T)
    C = st.chunk
    if N - 1 > C:
        raise FitError(f"window {w.label!r} has {N} samples; the engine was built for at most "
                       f"{C + 1}.")
    if U.shape[0] < C:
        U = np.vstack([U, np.full((C - U.shape[0], U.shape[1]), U[-1, -1])])
    tt = float(w.t[0]) + np.arange(C) * st.interval
    X, Y = st.fn(x0, U[:C].T, ca.DM(p), tt[None, :])
    Y = np.asarray(Y)[engine.y_index, : N - 1].T
    y0 = np.asarray(engine.driveline.out(x0, U[0, 0], p, float(w.t[0]))).ravel()[engine.y_index]
    return np.vstack([y0[None, :], Y])


def simulate_windows(engine: Engine, windows: Sequence[Window], state: State) -> list[np.ndarray]:
    """Model torques over every window (list of (N, ny) arrays, N*m reduced)."""
    return [simulate_window(engine, w, state.p, state.W[i]) for i, w in enumerate(windows)]


# ---- residuals and error measures -----------------------------------------------------------
def channel_scales(engine: Engine, windows: Sequence[Window]) -> np.ndarray:
    """Per measured element, the RMS of the torque about each window's mean, N*m."""
    ys = [w.columns(engine.measured) for w in windows]
    dev = np.concatenate([y - y.mean(axis=0) for y in ys], axis=0)
    s = np.sqrt(np.mean(dev ** 2, axis=0))
    return np.where(s > 0, s, 1.0)


def nrmse(engine: Engine, windows: Sequence[Window], sims: Sequence[np.ndarray],
          scales: np.ndarray | None = None) -> float:
    """Normalised RMS error: ``sqrt(mean over channels of mean(r**2) / scale**2)``.

    ``scale`` per channel is :func:`channel_scales` of the same windows (the
    torque's RMS about each window's mean), so 1 is as bad as predicting the mean.
    """
    if scales is None:
        scales = channel_scales(engine, windows)
    r = np.concatenate([s - w.columns(engine.measured) for w, s in zip(windows, sims)], axis=0)
    return float(np.sqrt(np.mean(np.mean(r ** 2, axis=0) / scales ** 2)))


# ---- least squares -----------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Layout:
    """Where a fit's free (scaled) variables sit in a :class:`State`.

    Attributes
    ----------
    shared : ndarray of int
        Driveline parameter indices of the free shared parameters.
    window : tuple of (int, int)
        ``(window row, column)`` of each free per-window parameter.
    scale, lower, upper : ndarray
        Scales of all free variables and their bounds (scaled).
    """

    shared: np.ndarray
    window: tuple
    scale: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def pack(self, state: State) -> np.ndarray:
        """The scaled free variables of ``state``."""
        v = np.concatenate([state.p[self.shared],
                            np.array([state.W[i, k] for i, k in self.window])])
        return v / self.scale

    def unpack(self, z: np.ndarray, like: State) -> State:
        """``like`` with the free variables set from ``z`` (scaled)."""
        v = np.asarray(z) * self.scale
        p = like.p.copy()
        n = len(self.shared)
        p[self.shared] = v[:n]
        W = like.W.copy()
        for (i, k), val in zip(self.window, v[n:]):
            W[i, k] = val
        return State(p=p, W=W)

    def stepped(self, state: State, dz: np.ndarray) -> State:
        """``state`` moved by the scaled step ``dz``, clipped to the bounds."""
        return self.unpack(np.clip(self.pack(state) + dz, self.lower, self.upper), state)


@dataclass(frozen=True, eq=False)
class FitOutcome:
    """Result of :func:`fit` / :func:`fit_nuisance`.

    Attributes
    ----------
    state : State
    cost : float
        Half the sum of squared weighted residuals.
    nrmse : float
        Over the fitted windows.
    n_free : int
        Free parameters (shared and per window).
    n_residuals : int
    residuals : ndarray
        Weighted residuals at the end (window-major, then sample, then channel).
    jac : ndarray or None
        Their Jacobian with respect to the scaled free parameters.
    nfev : int
    success : bool
    """

    state: State
    cost: float
    nrmse: float
    n_free: int
    n_residuals: int
    residuals: np.ndarray
    jac: np.ndarray | None
    nfev: int
    success: bool
    sims: tuple = ()
    layout: Layout | None = None


def _window_bounds(w: Window, ref: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lo = np.r_[-3 * ref, -3 * ref, w.t_step - 0.05, 2e-3, 0.0, -0.5 * ref, 0.0,
               np.full(n, -0.02), np.full(n, -3.0)]
    hi = np.r_[3 * ref, 3 * ref, w.t_step + 0.05, 0.15, 1.0, 0.5 * ref, 1.0,
               np.full(n, 0.02), np.full(n, 3.0)]
    sc = np.r_[0.05 * ref, 0.05 * ref, 0.005, 0.01, 0.3, 0.05 * ref, 1.0,
               np.full(n, 1e-3), np.full(n, 0.05)]
    return lo, hi, sc


def _window_free(engine: Engine, w: Window, free_slope: bool, free_x0: bool,
                 history: bool) -> np.ndarray:
    """Which entries of the window's row a fit moves (``history``: it starts from its idle run)."""
    n = len(engine.mill.masses)
    free = np.zeros(len(WINDOW_PARAMS) + 2 * n, dtype=bool)
    free[:4] = True
    idle = starts_idle(w)
    free[_I_FRAC] = idle and not free_x0 and not history
    free[5] = free_slope and w.kind == "bite"
    if idle and free_x0:
        free[len(WINDOW_PARAMS):] = True
        free[len(WINDOW_PARAMS) + engine.mill.mass_index(engine.mill.motor.mass)] = False
    return free


def initial_window_params(engine: Engine, windows: Sequence[Window]) -> np.ndarray:
    """Load parameters from the segmenter's estimates, no state offsets.

    Returns
    -------
    ndarray, shape (n_windows, len(WINDOW_PARAMS) + 2 * n_masses)
    """
    n = len(engine.mill.masses)
    W = np.zeros((len(windows), len(WINDOW_PARAMS) + 2 * n))
    for i, w in enumerate(windows):
        W[i, :7] = [w.level_before, w.level_after, w.t_step, w.rise,
                    1.0 if w.kind == "bite" else 0.0, 0.0, 1.0]
    return W


def fit(engine: Engine, windows: Sequence[Window], setup: Setup, start: State, *,
        free_shared: bool = True, free_slope: bool = True, free_x0: bool = False,
        max_nfev: int = 30,
        scales: np.ndarray | None = None, fd_step: float = 1e-6, ftol: float = 1e-3,
        keep_jac: bool = False) -> FitOutcome:
    """Least-squares fit of the free shared and per-window parameters (single shooting).

    Parameters
    ----------
    engine : Engine
    windows : sequence of Window
    setup : Setup
        Free shared parameters and the active candidate.
    start : State
        Starting point (``start.W`` one row per window).
    free_shared : bool
        False: only the per-window parameters move (held-out evaluation).
    free_slope : bool
        Let the load drift per window.
    free_x0 : bool
        Free the initial angle and speed offsets of bites from idle (else their
        elements start at rest at ``frac`` of their gaps).
    max_nfev : int
        Residual evaluations the trust-region solver may spend (about one
        Jacobian each).
    scales : ndarray, optional
        Channel weights' scales, N*m (default :func:`channel_scales` of ``windows``).
    fd_step : float
        Finite-difference step on the scaled parameters.
    ftol : float
        Stop when a step lowers the cost by less than this fraction.
    keep_jac : bool
        Return the final Jacobian (for signature scores).

    Returns
    -------
    FitOutcome
    """
    windows = tuple(windows)
    nw = len(windows)
    if start.W.shape[0] != nw:
        raise FitError(f"start has {start.W.shape[0]} window rows for {nw} windows.")
    if scales is None:
        scales = channel_scales(engine, windows)
    weights = 1.0 / scales
    ys = [w.columns(engine.measured) for w in windows]
    ref = max(max(abs(w.level_after), abs(w.level_before)) for w in windows)
    p0 = setup.apply_gates(engine, start.p)
    sh_idx = np.array(setup.shared if free_shared else (), dtype=int)
    sh_lo = setup.lower if free_shared else np.zeros(0)
    sh_hi = setup.upper if free_shared else np.zeros(0)
    sh_sc = setup.scale if free_shared else np.zeros(0)
    # per-window free entries
    w_entries: list[tuple[int, int]] = []
    w_lo, w_hi, w_sc = [], [], []
    n_m = len(engine.mill.masses)
    for i, w in enumerate(windows):
        lo, hi, sc = _window_bounds(w, ref, n_m)
        hist = uses_history(engine, w, p0, start.W[i])
        for k in np.flatnonzero(_window_free(engine, w, free_slope, free_x0, hist)):
            w_entries.append((i, int(k)))
            w_lo.append(lo[k])
            w_hi.append(hi[k])
            w_sc.append(sc[k])
    n_sh = len(sh_idx)
    scale = np.concatenate([sh_sc, np.array(w_sc)])
    lower = np.concatenate([sh_lo, np.array(w_lo)]) / scale
    upper = np.concatenate([sh_hi, np.array(w_hi)]) / scale

    def unpack(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = z * scale
        p = p0.copy()
        p[sh_idx] = v[:n_sh]
        W = start.W.copy()
        for (i, k), val in zip(w_entries, v[n_sh:]):
            W[i, k] = val
        return p, W

    z0 = np.concatenate([p0[sh_idx], np.array([start.W[i, k] for i, k in w_entries])]) / scale
    z0 = np.clip(z0, lower, upper)
    n_per = windows[0].n_samples * len(engine.measured)
    cache: dict[bytes, tuple[np.ndarray, list]] = {}

    def window_res(i: int, p: np.ndarray, wp: np.ndarray) -> np.ndarray:
        s = simulate_window(engine, windows[i], p, wp)
        return ((s - ys[i]) * weights).ravel()

    def fun(z: np.ndarray) -> np.ndarray:
        key = z.tobytes()
        got = cache.get(key)
        if got is not None:
            return got[0]
        p, W = unpack(z)
        r = np.concatenate([window_res(i, p, W[i]) for i in range(nw)])
        if not np.all(np.isfinite(r)):
            r = np.where(np.isfinite(r), r, 1e3)
        cache.clear()
        cache[key] = (r, [])
        return r

    # window columns grouped by parameter name: one simulation per name covers every window
    groups: dict[int, list[int]] = {}
    for col, (i, k) in enumerate(w_entries):
        groups.setdefault(k, []).append(n_sh + col)

    def jac(z: np.ndarray) -> np.ndarray:
        r0 = fun(z)
        Jm = np.zeros((r0.size, z.size))
        for c in range(n_sh):
            h = fd_step * max(1.0, abs(z[c]))
            zz = z.copy()
            zz[c] = z[c] + h if z[c] + h <= upper[c] else z[c] - h
            d = zz[c] - z[c]
            p, W = unpack(zz)
            r = np.concatenate([window_res(i, p, W[i]) for i in range(nw)])
            Jm[:, c] = (r - r0) / d
        for k, cols in groups.items():
            zz = z.copy()
            steps = {}
            for c in cols:
                h = fd_step * max(1.0, abs(z[c])) * 10
                zz[c] = z[c] + h if z[c] + h <= upper[c] else z[c] - h
                steps[c] = zz[c] - z[c]
            p, W = unpack(zz)
            for c in cols:
                i, _ = w_entries[c - n_sh]
                r = window_res(i, p, W[i])
                Jm[i * n_per:(i + 1) * n_per, c] = (r - r0[i * n_per:(i + 1) * n_per]) / steps[c]
        return Jm

    if z0.size and max_nfev > 0:
        z, nfev, success, J = _solve(fun, jac, z0, lower, upper, max_iter=max_nfev,
                                     ftol=ftol)
        if not keep_jac:
            J = None
    else:
        z, nfev, success, J = z0, 0, True, None
    p, W = unpack(z)
    state = State(p=p, W=W)
    sims = simulate_windows(engine, windows, state)
    r = np.concatenate([((s - y) * weights).ravel() for s, y in zip(sims, ys)])
    return FitOutcome(state=state, cost=0.5 * float(r @ r),
                      nrmse=nrmse(engine, windows, sims, scales), n_free=int(z.size),
                      n_residuals=int(r.size), residuals=r, jac=J, nfev=nfev, success=success,
                      sims=tuple(sims),
                      layout=Layout(shared=sh_idx, window=tuple(w_entries), scale=scale,
                                    lower=lower, upper=upper))


def scan_frac(engine: Engine, windows: Sequence[Window], state: State, *,
              values: Sequence[float] = (0.0, 0.5, 1.0),
              scales: np.ndarray | None = None) -> State:
    """Start each bite from idle at the best of a few gap positions ``frac`` (others kept).

    Where the model runs through the idle time before a bite
    (:func:`can_use_history`) that start is tried too.  The window's current
    start is among those tried, so the cost never rises.  ``state.p`` must
    have its gates applied.
    """
    if scales is None:
        scales = channel_scales(engine, windows)
    W = state.W.copy()
    for i, w in enumerate(windows):
        if not starts_idle(w):
            continue
        y = w.columns(engine.measured)
        best = None
        for h, v in _start_modes(engine, w, state.p, W[i], values):
            wp = W[i].copy()
            wp[_I_HISTORY], wp[_I_FRAC] = h, v
            r = (simulate_window(engine, w, state.p, wp) - y) / scales
            c = float(np.sum(r ** 2))
            if best is None or c < best[0]:
                best = (c, h, v)
        W[i, _I_HISTORY], W[i, _I_FRAC] = best[1], best[2]
    return State(p=state.p, W=W)


def _start_modes(engine: Engine, w: Window, p: np.ndarray, wp: np.ndarray,
                 fracs: Sequence[float]) -> list[tuple[float, float]]:
    """``(history, frac)`` starts worth trying for a bite from idle, the row's own first."""
    own = (1.0 if uses_history(engine, w, p, wp) else 0.0, float(wp[_I_FRAC]))
    modes = [own] + [(0.0, float(f)) for f in fracs]
    if can_use_history(engine, w, p):
        modes.append((1.0, own[1]))
    return list(dict.fromkeys(modes))


#: Load-ramp durations :func:`ramp_starts` tries, s (about geometric, 4-60 ms: real mills
#: ramp over 10-40 ms; the segmenter's 10-90 % estimate on a ringing torque can be far off).
RAMP_GRID_S = (0.004, 0.007, 0.012, 0.02, 0.035, 0.06)
#: Shifts of the load's half-height instant from the segmenter's, s: the segmenter times
#: the measured torque, which lags the load by up to a quarter of the lowest period.
SHIFT_GRID_S = (-0.024, -0.016, -0.008, 0.0, 0.008)


def ramp_starts(engine: Engine, w: Window, p: np.ndarray, wp: np.ndarray, *, k: int = 2,
                rises: Sequence[float] = RAMP_GRID_S, shifts: Sequence[float] = SHIFT_GRID_S,
                fracs: Sequence[float] = (0.0, 0.5, 1.0),
                scales: np.ndarray | None = None) -> list[np.ndarray]:
    """The ``k`` best window rows over a grid of ramp durations and gap positions.

    The ramp's duration sets when the flanks meet and so the timing of every
    impact: the cost has a local minimum per impact pattern, and a gradient
    fit from a wrong duration stays in the wrong one.  So does one from a wrong
    instant, and the segmenter's ``t_step`` is that of the measured torque,
    which lags the load.  ``wp`` itself is among the rows tried; bites from
    idle also try gap positions ``frac`` (0 drive flank, 1 back flank) and,
    where the model runs through the idle time before them
    (:func:`can_use_history`), that simulated start.

    Parameters
    ----------
    engine : Engine
    w : Window
    p : ndarray
        Driveline parameters (gates applied).
    wp : ndarray
        The window's row (:data:`WINDOW_PARAMS` and offsets).
    k : int
        Rows returned, best first, each with another ramp duration.
    rises : sequence of float
        Ramp durations tried, s.
    shifts : sequence of float
        Shifts of ``t_step`` tried, s (within the fit's bounds, 50 ms).
    fracs : sequence of float
        Gap positions tried.
    scales : ndarray, optional
        Channel scales, N*m (default: of ``w``).

    Returns
    -------
    list of ndarray
        The ``k`` best (each with another ramp duration), then, for a window that
        can start from its simulated idle, the best row of the start kind
        (simulated or at rest) missing from them.
    """
    if scales is None:
        scales = channel_scales(engine, [w])
    i_rise = WINDOW_PARAMS.index("rise")
    y = w.columns(engine.measured)
    modes = (_start_modes(engine, w, p, wp, fracs) if starts_idle(w)
             else [(float(wp[_I_HISTORY]), float(wp[_I_FRAC]))])
    i_t = WINDOW_PARAMS.index("t_step")
    rs = tuple(dict.fromkeys((float(wp[i_rise]),) + tuple(rises)))
    ts = tuple(dict.fromkeys(
        (float(wp[i_t]),) + tuple(w.t_step + d for d in shifts if abs(d) < 0.05)))
    # best row per (start kind, ramp duration): a simulated idle start and one at rest
    # are different basins, so each kind keeps its best row among those returned
    best: dict[tuple[bool, float], tuple[float, np.ndarray]] = {}
    for r in rs:
        for t in ts:
            for h, f in modes:
                row = np.array(wp, dtype=float)
                row[i_rise], row[i_t], row[_I_HISTORY], row[_I_FRAC] = r, t, h, f
                c = float(np.sum(((simulate_window(engine, w, p, row) - y) / scales) ** 2))
                key = (uses_history(engine, w, p, row), r)
                if key not in best or c < best[key][0]:
                    best[key] = (c, row)
    ranked = sorted(best.items(), key=lambda kv: kv[1][0])
    out, rises_kept = [], set()
    for (_, r), cr in ranked:  # the k best, each with another ramp duration
        if r not in rises_kept and len(out) < k:
            out.append(cr)
            rises_kept.add(r)
    kinds = {uses_history(engine, w, p, row) for _, row in out}
    for (h, _), cr in ranked:  # and the best of a start kind not among them
        if h not in kinds:
            out.append(cr)
            kinds.add(h)
    return [row for _, row in out]


def scan_ramp(engine: Engine, windows: Sequence[Window], state: State, *,
              rises: Sequence[float] = RAMP_GRID_S, shifts: Sequence[float] = SHIFT_GRID_S,
              fracs: Sequence[float] = (0.0, 0.5, 1.0),
              scales: np.ndarray | None = None) -> State:
    """Each window's row at the best of :func:`ramp_starts` (the cost never rises)."""
    if scales is None:
        scales = channel_scales(engine, windows)
    W = state.W.copy()
    for i, w in enumerate(windows):
        W[i] = ramp_starts(engine, w, state.p, W[i], k=1, rises=rises, shifts=shifts,
                           fracs=fracs, scales=scales)[0]
    return State(p=state.p, W=W)


def fit_nuisance(engine: Engine, windows: Sequence[Window], setup: Setup, shared: State, *,
                 start_W: np.ndarray | None = None, max_nfev: int = 15,
                 scales: np.ndarray | None = None) -> FitOutcome:
    """Fit only the per-window load parameters with the shared ones fixed (held-out windows)."""
    W = initial_window_params(engine, windows) if start_W is None else start_W
    return fit(engine, windows, setup, State(p=shared.p, W=W), free_shared=False,
               max_nfev=max_nfev, scales=scales)



def _solve(fun: Any, jac: Any, z0: np.ndarray, lower: np.ndarray, upper: np.ndarray, *,
           max_iter: int, ftol: float) -> tuple[np.ndarray, int, bool, np.ndarray]:
    """scipy's bounded trust-region least squares, one BLAS thread (the machine is shared)."""
    from scipy.optimize import least_squares
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        res = least_squares(fun, z0, jac=jac, bounds=(lower, upper), method="trf",
                            tr_solver="exact", x_scale=1.0, max_nfev=max_iter, ftol=ftol,
                            xtol=1e-5, gtol=1e-8)
    return res.x, int(res.njev or res.nfev), bool(res.status > 0), res.jac
