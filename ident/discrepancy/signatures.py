"""Candidates and how well their signatures match the residuals (before any refit).

Every effect of effects.md at every place it can sit in the mill
(:func:`~ident.model.effects.candidate_locations`) is a candidate.  Its
*signature* is what switching it on does to the model's torques over the
windows: the finite-difference response to its gate (and to its probe
parameters: a few knee positions, two imbalance phases, strip stiffness and
damping, a few lag time constants, a few backlash gaps).  The score is the
share of the baseline residual that signature can take up once everything the
baseline can already do (its own Jacobian) is projected out, a Lagrange
multiplier (score) test::

    score = || P(J0-perp C) r ||^2 / sigma^2,   sigma^2 = ||r||^2 / (n - p)

with sign constraints where physics sets them (softening lowers, hardening
raises the stiffness; friction, lag and gaps are positive).  Knee stiffness
is probed both ways (``k_ratio`` 0.5 and 2) at knees spread over the whole
range of static deflections the windows reach (``knee_guesses`` of
``ident.model.effects``, scaled by :func:`peak_torque`): a large hardening is
far from a linear extension of a softening.  The same projection gives each
candidate's starting parameters for the refit.

A linearisation misses an effect the baseline has bent itself around (a
strong hardening, a gap the neighbours' gaps imitate), so the leading
candidates are also tried on a coarse grid of their parameters
(:func:`start_grid`, forward simulations only): :func:`rescore_on_grid`
keeps the larger of the two residual reductions.

Residuals are serially correlated, so the score is a ranking, not a p-value:
the decision is made on held-out windows (``ident.discrepancy.workflow``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..description import Mill
from ..model.effects import (CoulombFriction, SofteningStiffness, SpindleImbalance,
                             StripCoupling, TorqueLoopLag, candidate_locations, make_effect)
from ..model.scenario import nominal_torque
from .engine import Engine, FitOutcome, State, simulate_window
from .windows import Window

__all__ = ["Probe", "CandidateScore", "model_candidates", "score_candidates", "rescore_on_grid",
           "start_grid", "start_state", "peak_torque"]


def model_candidates(mill: Mill) -> tuple:
    """Every gated effect the scoring engine needs; no backlash.

    Backlash candidates free an element's own gap (see :class:`~.engine.Setup`);
    hardening shares the softening term (``k_ratio`` above 1).
    """
    out: list[Any] = []
    for e in candidate_locations(mill, "softening_stiffness"):
        out.append(SofteningStiffness(e))  # hardening is the same term with k_ratio > 1
    for e in candidate_locations(mill, "coulomb_friction"):
        out.append(CoulombFriction(e))
    for e in candidate_locations(mill, "spindle_imbalance"):
        out.append(SpindleImbalance(e))
    for loc in candidate_locations(mill, "strip_coupling"):
        out.append(StripCoupling(loc, k=0.0, c=0.0))
    for loc in candidate_locations(mill, "torque_loop_lag"):
        out.append(TorqueLoopLag(loc))
    return tuple(out)


@dataclass(frozen=True)
class Probe:
    """One signature column set: parameter values of a candidate, switched on a little.

    Attributes
    ----------
    key : str
        ``name@location`` of the engine candidate whose gate is probed (or
        ``backlash@E``: the element's gap).
    params : dict
        Candidate parameter values during the probe (local names).
    gate : float
        Gate step (or, for backlash, the gap in rad).
    """

    key: str
    params: tuple[tuple[str, float], ...]
    gate: float = 1.0


@dataclass(frozen=True)
class CandidateScore:
    """A candidate's score and its starting point for the refit.

    Attributes
    ----------
    effect, location : str
    score : float
        Residual sum of squares its signature takes up, in units of the
        residual variance (0 when the best fit has the wrong sign).
    fraction : float
        The same as a fraction of the baseline's residual sum of squares.
    start : dict
        Starting parameter values (local names) for the refit.
    step : ndarray or None
        The Gauss-Newton step of the baseline's own free variables (scaled, the
        baseline fit's :class:`~.engine.Layout`) that goes with ``start``: a
        candidate often takes over what the baseline bent its gaps for.
    """

    effect: str
    location: str
    score: float
    fraction: float
    start: dict = field(default_factory=dict)
    step: Any = field(default=None, compare=False, repr=False)

    @property
    def key(self) -> str:
        return f"{self.effect}@{self.location}"


def peak_torque(windows: Sequence[Window]) -> float:
    """Largest static rolling torque of the windows, N*m reduced (knee guesses scale with it)."""
    return max(max(abs(w.level_before), abs(w.level_after)) for w in windows)


def _probes(engine: Engine, torque: float | None = None) -> dict[str, list[list[Probe]]]:
    """Per candidate family key, alternative probe sets (each a list of columns)."""
    mill = engine.mill
    out: dict[str, list[list[Probe]]] = {}
    T = nominal_torque(mill)
    for c in engine.candidates:
        k = c.key
        if c.name in ("softening_stiffness", "hardening_stiffness"):
            # a large hardening is far from a linear extension of a softening: both ways
            out[k] = [[Probe(k, (("knee", kn), ("k_ratio", r)))]
                      for kn in c.knee_guesses(mill, torque=torque) for r in (0.5, 2.0)]
        elif c.name == "coulomb_friction":
            out[k] = [[Probe(k, (("force", 0.01 * T), ("v_smooth", c.v_smooth)))]]
        elif c.name == "spindle_imbalance":
            amp = 0.25 * max(mill.element(c.location).gap, 1e-3)
            out[k] = [[Probe(k, (("amplitude", amp), ("phase", 0.0))),
                       Probe(k, (("amplitude", amp), ("phase", math.pi / 2)))]]
        elif c.name == "strip_coupling":
            kref = float(np.median([e.k for e in mill.elements]))
            out[k] = [[Probe(k, (("k", 0.1 * kref), ("c", 0.0))),
                       Probe(k, (("k", 0.0), ("c", 2.5e-5 * kref)))]]
        elif c.name == "torque_loop_lag":
            out[k] = [[Probe(k, (("tau", tau),))] for tau in (0.004, 0.012, 0.035)]
    for eid in candidate_locations(mill, "backlash"):
        out[f"backlash@{eid}"] = [[Probe(f"backlash@{eid}", (), gate=g)] for g in (1e-3, 3e-3)]
    return out


def _column(engine: Engine, windows: Sequence[Window], state: State, probe: Probe,
            r0: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Finite-difference signature of one probe, weighted like the residuals."""
    p = state.p.copy()
    if probe.key.startswith("backlash@"):
        eid = probe.key.split("@", 1)[1]
        p[engine.p_index(f"{eid}.gap")] = probe.gate
        step = 1.0
    else:
        for name, v in probe.params:
            p[engine.p_index(f"{probe.key}.{name}")] = v
        p[engine.p_index(f"{probe.key}.gate")] = probe.gate
        step = probe.gate
    rs = []
    for i, w in enumerate(windows):
        s = simulate_window(engine, w, p, state.W[i])
        rs.append(((s - w.columns(engine.measured)) * weights).ravel())
    return (np.concatenate(rs) - r0) / step


def score_candidates(engine: Engine, windows: Sequence[Window], baseline: FitOutcome, *,
                     scales: np.ndarray) -> tuple[CandidateScore, ...]:
    """Score every candidate's signature against the baseline's residuals.

    Parameters
    ----------
    engine : Engine
    windows : sequence of Window
        The windows ``baseline`` was fitted on.
    baseline : FitOutcome
        The mill file's model fitted with ``keep_jac=True``.
    scales : ndarray
        Channel scales the baseline was weighted with, N*m.

    Returns
    -------
    tuple of CandidateScore
        Best first; softening and hardening share their probes (the sign decides).
    """
    r0 = baseline.residuals
    n = r0.size
    J0 = baseline.jac if baseline.jac is not None else np.zeros((n, 0))
    if J0.shape[1]:
        Q, R = np.linalg.qr(J0)
        R_pinv = np.linalg.pinv(R)  # J0's least-squares solutions: R_pinv @ Q.T @ b
    else:
        Q, R_pinv = np.zeros((n, 0)), np.zeros((0, 0))
    rp = r0 - Q @ (Q.T @ r0)
    ssr = float(r0 @ r0)
    sigma2 = ssr / max(n - J0.shape[1], 1)
    weights = 1.0 / scales
    state = baseline.state
    mill = engine.mill
    results: list[CandidateScore] = []
    for key, alternatives in _probes(engine, peak_torque(windows)).items():
        name, loc = key.split("@", 1)
        best: dict[str, tuple[float, dict]] = {}
        for probes in alternatives:
            C = np.stack([_column(engine, windows, state, pr, r0, weights) for pr in probes], 1)
            Cp = C - Q @ (Q.T @ C)
            beta, *_ = np.linalg.lstsq(Cp, -rp, rcond=None)
            gain = float(np.sum((Cp @ beta) ** 2))
            for eff, start in _interpret(mill, name, loc, probes, beta):
                g = gain if start is not None else 0.0
                if eff not in best or g > best[eff][0]:
                    step = None
                    if start is not None and J0.shape[1]:
                        step = -R_pinv @ (Q.T @ (r0 + C @ beta))
                    best[eff] = (g, start or {}, step)
        for eff, (g, start, step) in best.items():
            results.append(CandidateScore(effect=eff, location=loc, score=g / sigma2,
                                          fraction=g / ssr if ssr > 0 else 0.0, start=start,
                                          step=step))
    results.sort(key=lambda c: -c.score)
    return tuple(results)


def _interpret(mill: Mill, name: str, loc: str, probes: list[Probe], beta: np.ndarray
               ) -> list[tuple[str, dict | None]]:
    """Effect names and refit starting values a projection supports (None: wrong sign)."""
    b = [float(v) for v in beta]
    pr = dict(probes[0].params)
    if name in ("softening_stiffness", "hardening_stiffness"):
        # the probe adds gate * (k_ratio - 1) * k beyond the knee
        ratio = 1.0 + b[0] * (pr["k_ratio"] - 1.0)
        soft = {"knee": pr["knee"], "k_ratio": float(np.clip(ratio, 0.1, 0.95))}
        hard = {"knee": pr["knee"], "k_ratio": float(np.clip(ratio, 1.05, 6.0))}
        return [("softening_stiffness", soft if ratio < 1.0 else None),
                ("hardening_stiffness", hard if ratio > 1.0 else None)]
    if name == "coulomb_friction":
        f = b[0] * pr["force"]
        return [(name, {"force": f} if b[0] > 0 else None)]
    if name == "spindle_imbalance":
        amp = pr["amplitude"]
        # beta_c sin(x) + beta_s sin(x + pi/2) = A sin(x + phase)
        A = math.hypot(b[0], b[1]) * amp
        phase = math.atan2(b[1], b[0])
        return [(name, {"amplitude": A, "phase": phase})]
    if name == "strip_coupling":
        k = b[0] * dict(probes[0].params)["k"]
        c = max(b[1] * dict(probes[1].params)["c"], 0.0)
        return [(name, {"k": k, "c": c} if b[0] > 0 else None)]
    if name == "torque_loop_lag":
        return [(name, {"tau": pr["tau"]} if b[0] > 0 else None)]
    if name == "backlash":
        gap = b[0] * probes[0].gate
        return [(name, {"gap": float(np.clip(gap, 2e-4, 0.02))} if b[0] > 0 else None)]
    return [(name, None)]


def start_state(engine: Engine, state: State, cand: CandidateScore) -> State:
    """``state`` with the candidate's starting parameters set (gates left to the Setup)."""
    p = state.p.copy()
    key = cand.key
    if cand.effect == "backlash":
        p[engine.p_index(f"{cand.location}.gap")] = cand.start.get("gap", 1e-3)
        return State(p=p, W=state.W.copy())
    ekey = engine.candidate_key(key)
    specs = {s.name: s for s in make_effect(cand.effect, cand.location).specs(engine.mill)}
    for name, v in cand.start.items():
        s = specs.get(name)
        if s is not None:
            v = float(np.clip(v, s.lower, s.upper))
        p[engine.p_index(f"{ekey}.{name}")] = v
    return State(p=p, W=state.W.copy())


def start_grid(mill: Mill, cand: CandidateScore, *, fine: bool = False,
               torque: float | None = None) -> list[dict[str, float]]:
    """Starting points worth a look for a candidate's refit (local parameter names).

    A coarse grid over the parameters that make the fit non-convex (imbalance
    phase, knee position, lag time constant, gap size) around plausible
    magnitudes, plus the signature projection's own estimate.  The refit starts
    from the grid point with the lowest training cost (the baseline included),
    so it never starts worse than the mill file's model.  ``fine`` refines the
    gap sizes of backlash (whose basins are narrow) and the stiffness ratios of
    knees; ``torque`` (N*m reduced, the
    largest static rolling torque in the data) places the knees.
    """
    name, loc = cand.effect, cand.location
    grid: list[dict[str, float]] = [dict(cand.start)] if cand.start else []
    if name in ("softening_stiffness", "hardening_stiffness"):
        # the loaded stiffness makes a narrow valley in k_ratio: finer when asked
        knees = make_effect(name, loc).knee_guesses(mill, torque=torque)
        if name == "softening_stiffness":
            ratios = (0.15, 0.25, 0.35, 0.45, 0.55, 0.7, 0.85) if fine else (0.3, 0.6, 0.85)
        else:
            ratios = (1.2, 1.5, 1.9, 2.4, 3.0, 4.0, 5.5) if fine else (1.3, 2.0, 3.5)
        grid += [{"knee": kn, "k_ratio": r} for kn in knees for r in ratios]
    elif name == "coulomb_friction":
        T = nominal_torque(mill)
        grid += [{"force": f * T} for f in (0.004, 0.01, 0.02, 0.04)]
    elif name == "spindle_imbalance":
        gap = max(mill.element(loc).gap, 1e-3)
        grid += [{"amplitude": a * gap, "phase": ph} for a in (0.3, 0.6)
                 for ph in np.arange(8) * math.pi / 4]
    elif name == "strip_coupling":
        kref = float(np.median([e.k for e in mill.elements]))
        grid += [{"k": f * kref, "c": 2.5e-4 * f * kref} for f in (0.05, 0.15, 0.4)]
    elif name == "torque_loop_lag":
        grid += [{"tau": tau} for tau in (0.003, 0.006, 0.012, 0.025, 0.05)]
    elif name == "backlash":
        gaps = ((5e-4, 8e-4, 1.2e-3, 1.6e-3, 2e-3, 2.5e-3, 3.2e-3, 4e-3, 5e-3) if fine
                else (5e-4, 1e-3, 2e-3, 3.5e-3, 6e-3))
        grid += [{"gap": g} for g in gaps]
    return grid


def rescore_on_grid(engine: Engine, windows: Sequence[Window], baseline: FitOutcome,
                    scores: Sequence[CandidateScore], *, scales: np.ndarray,
                    top: int = 10) -> tuple[CandidateScore, ...]:
    """Scores of the ``top`` candidates raised to their best grid point's cost reduction.

    Parameters
    ----------
    engine : Engine
        With every candidate (as :func:`score_candidates`).
    windows, baseline, scales :
        As :func:`score_candidates`.
    scores : sequence of CandidateScore
        From :func:`score_candidates` (best first).
    top : int
        Candidates tried.

    Returns
    -------
    tuple of CandidateScore
        Best first; a candidate whose grid point beats its linear projection
        starts its refit from that point.
    """
    r0 = baseline.residuals
    n = r0.size
    p_free = baseline.jac.shape[1] if baseline.jac is not None else 0
    sigma2 = float(r0 @ r0) / max(n - p_free, 1)
    ssr0 = float(r0 @ r0)
    ys = [w.columns(engine.measured) for w in windows]
    out = list(scores)
    for k, c in enumerate(scores[:top]):
        best_gain, best_point = -math.inf, None
        for point in start_grid(engine.mill, c, torque=peak_torque(windows)):
            st = start_state(engine, baseline.state, CandidateScore(
                effect=c.effect, location=c.location, score=0.0, fraction=0.0, start=point))
            p = st.p.copy()
            if c.effect != "backlash":
                p[engine.p_index(f"{engine.candidate_key(c.key)}.gate")] = 1.0
            ssr = 0.0
            for i, w in enumerate(windows):
                ssr += float(np.sum(((simulate_window(engine, w, p, st.W[i]) - ys[i])
                                     / scales) ** 2))
            if ssr0 - ssr > best_gain:
                best_gain, best_point = ssr0 - ssr, point
        if best_point is not None and best_gain / sigma2 > c.score:
            out[k] = CandidateScore(effect=c.effect, location=c.location,
                                    score=best_gain / sigma2, fraction=best_gain / ssr0,
                                    start=dict(best_point), step=None)
    out.sort(key=lambda c: -c.score)
    return tuple(out)
