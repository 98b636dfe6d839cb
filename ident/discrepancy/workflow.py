"""The discrepancy workflow: find what the model is missing, name it, add it, show the gap shrink.

:func:`discrepancy` runs, on the transient windows of a recording:

1. **Cross-validation folds across bars** (:func:`fold_bars`): bars alternate
   between two folds (three bars: one fold per bar, so that every fold trains
   on two); each fold's model is fitted on the other bars and judged on its own.
2. **Baseline**: the model the mill file describes (gaps identified) fitted on
   each fold (:mod:`.engine`), its residuals on the *held-out* bars analysed by
   window, transient phase, frequency, load level and roll angle
   (:mod:`.residuals`).
3. **Candidates**: every effect of effects.md at every location it can take,
   ranked by how much of the training residual its signature takes up
   (:mod:`.signatures`, scores summed over the folds).
4. **Refit** of the ``n_refit`` leading candidates: each added to the model as
   a term with its own parameters (``ident.model.effects``), refitted on each
   fold's bars from two starts (the baseline's optimum moved by the signature's
   step or the best grid point, and afresh from the mill file's gaps, because
   the baseline bends its gaps around what it misses), each with the loads
   refitted first; its held-out nrmse is measured on the other bars, the
   loads of every window fitted alike for every model.
5. **Decision** (:class:`DecisionRule`): the best candidate is named only when
   it lowers the held-out nrmse by at least ``min_improvement`` overall and by
   ``min_fold_improvement`` on every fold, beats every candidate of another
   name or location by ``min_margin`` and leads the same effect elsewhere in
   signature score (``min_location_lead``); otherwise the answer is ``null`` with
   ``explained: false`` ("a wrong name is worse than none", effects.md).  The
   held-out measure is itself the penalty for added parameters (a candidate
   that only fits noise does worse on unseen bars); the training BIC is
   reported too.

``before`` and ``after`` in the result are held-out nrmse over every window
(each window is held out by exactly one fold): the mill file's model, and the
model with the named effect (``after = before`` when nothing is named).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np

from ..description import Mill
from ..errors import FitError
from ..model.effects import make_effect
from .engine import (WINDOW_PARAMS, Engine, FitOutcome, Setup, State, build_engine,
                     channel_scales, fit, initial_window_params, nrmse, ramp_starts, scan_frac,
                     simulate_window)
from .residuals import ResidualReport, analyse_residuals
from .signatures import (CandidateScore, model_candidates, peak_torque, rescore_on_grid,
                         score_candidates, start_grid, start_state)
from .windows import Window, as_windows, windows_from_recording

__all__ = ["DecisionRule", "Refit", "DiscrepancyResult", "discrepancy", "fold_bars"]


@dataclass(frozen=True)
class DecisionRule:
    """When a candidate is named (thresholds on held-out nrmse).

    Calibrated on controls with nothing missing and with a sensor-chain filter
    (``benchmarks/bench_discrepancy.py``): there the best candidate lowered the
    held-out nrmse by at most a few per cent, well below ``min_improvement``,
    which also is the issue's bar for a named effect (30 %).

    Attributes
    ----------
    min_improvement : float
        Least relative drop of the pooled held-out nrmse, ``1 - after/before``.
    min_fold_improvement : float
        Least relative drop on every fold.
    min_margin : float
        Least lead, in relative held-out nrmse, over the best candidate with a
        different effect or location.
    max_bic : float
        Largest training BIC difference (candidate minus baseline, summed over
        folds) still accepted.
    min_location_lead : float
        Least relative lead in signature score over the same effect at another
        refitted location.  Where two locations match the residuals alike (the
        two spindles of a symmetric stand), a refit on a few bars can land the
        effect at the wrong one and still generalise (the bench's one wrong name
        was such an imbalance), so the location is not named.
    """

    min_improvement: float = 0.3
    min_fold_improvement: float = 0.15
    min_margin: float = 0.05
    max_bic: float = 0.0
    min_location_lead: float = 0.1

    def decide(self, refits: Sequence["Refit"]) -> tuple[str | None, str | None, bool, str]:
        """``(effect, location, explained, reason)`` for refits sorted best first."""
        if not refits:
            return None, None, False, "no candidate's signature matches the residuals"
        best = refits[0]
        if best.improvement < self.min_improvement:
            return None, None, False, (f"best candidate {best.key} lowers the held-out nrmse "
                                       f"by {100 * best.improvement:.1f} % < "
                                       f"{100 * self.min_improvement:.0f} %")
        worst_fold = min(best.fold_improvements)
        if worst_fold < self.min_fold_improvement:
            return None, None, False, (f"best candidate {best.key} does not help on every "
                                       f"fold ({100 * worst_fold:.1f} % on one)")
        if best.delta_bic > self.max_bic:
            return None, None, False, (f"best candidate {best.key} does not pay for its "
                                       f"parameters (training BIC {best.delta_bic:+.0f})")
        for other in refits[1:]:
            if other.key != best.key and best.improvement - other.improvement < self.min_margin:
                return None, None, False, (f"{best.key} and {other.key} explain the "
                                           f"disagreement alike ({100 * best.improvement:.1f} % "
                                           f"and {100 * other.improvement:.1f} %)")
        for other in refits[1:]:
            if (other.effect == best.effect and other.location != best.location
                    and other.score > (1.0 - self.min_location_lead) * best.score):
                return None, None, False, (f"the signatures cannot tell {best.key} from "
                                           f"{other.key} (scores {best.score:.0f} and "
                                           f"{other.score:.0f})")
        return best.effect, best.location, True, (
            f"held-out nrmse {100 * best.improvement:.1f} % lower, every fold at least "
            f"{100 * worst_fold:.1f} %")


@dataclass(frozen=True)
class Refit:
    """One candidate added to the model and refitted on every fold.

    Attributes
    ----------
    effect, location : str
    score : float
        Signature score (sum over folds).
    params : dict
        Fitted parameters per fold (effect's local names; knee effects add ``k_after``, N*m/rad).
    nrmse : float
        Held-out nrmse over every window.
    improvement : float
        ``1 - nrmse / before``.
    fold_improvements : tuple of float
    train_nrmse : tuple of float
        Per fold, on its own bars.
    delta_bic : float
        Training BIC of the candidate minus the baseline's, summed over folds.
    """

    effect: str
    location: str
    score: float
    params: tuple
    nrmse: float
    improvement: float
    fold_improvements: tuple
    train_nrmse: tuple
    delta_bic: float
    sims: tuple = field(default=(), repr=False, compare=False)

    @property
    def key(self) -> str:
        return f"{self.effect}@{self.location}"

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "location": self.location, "score": self.score,
                "nrmse": self.nrmse, "improvement": self.improvement,
                "fold_improvements": list(self.fold_improvements),
                "train_nrmse": list(self.train_nrmse), "delta_bic": self.delta_bic,
                "params": list(self.params)}


@dataclass(frozen=True, eq=False)
class DiscrepancyResult:
    """What the workflow found.

    Attributes
    ----------
    effect, location : str or None
        The named effect (effects.md) and where, or None.
    explained : bool
    before, after : float
        Held-out nrmse over every window without and with the named effect.
    candidates : tuple of CandidateScore
        Every candidate, best signature score first.
    refits : tuple of Refit
        The candidates added and refitted, best held-out nrmse first.
    reason : str
        Why this answer (which rule decided).
    residuals_before, residuals_after : ResidualReport
        Held-out residuals of the mill file's model and of the model with the
        named (or, when none is named, the best refitted) candidate.
    windows : tuple of Window
    mill : Mill
    """

    effect: str | None
    location: str | None
    explained: bool
    before: float
    after: float
    candidates: tuple[CandidateScore, ...]
    refits: tuple[Refit, ...]
    reason: str
    residuals_before: ResidualReport
    residuals_after: ResidualReport | None
    windows: tuple[Window, ...]
    mill: Mill
    folds: tuple[tuple[int, ...], ...]
    rule: DecisionRule
    seconds: float
    sims_before: tuple = field(default=(), repr=False)
    measured: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """cli.md's ``discrepancy`` JSON, plus ``reason``, ``refits``, ``residuals`` and more."""
        refitted = {r.key: r for r in self.refits}
        cands = []
        for c in self.candidates:
            d = {"effect": c.effect, "location": c.location, "score": c.score,
                 "fraction": c.fraction}
            if c.key in refitted:
                r = refitted[c.key]
                d["heldout_nrmse"] = r.nrmse
                d["improvement"] = r.improvement
            cands.append(d)
        return {
            "effect": self.effect, "location": self.location, "explained": self.explained,
            "before": {"nrmse": self.before}, "after": {"nrmse": self.after},
            "candidates": cands,
            "reason": self.reason,
            "refits": [r.to_dict() for r in self.refits],
            "residuals": {"before": self.residuals_before.to_dict(),
                          "after": (self.residuals_after.to_dict()
                                    if self.residuals_after is not None else None)},
            "rule": {"min_improvement": self.rule.min_improvement,
                     "min_fold_improvement": self.rule.min_fold_improvement,
                     "min_margin": self.rule.min_margin, "max_bic": self.rule.max_bic,
                     "min_location_lead": self.rule.min_location_lead},
            "windows": [{"label": w.label, "bar": w.bar, "kind": w.kind} for w in self.windows],
            "folds": [list(f) for f in self.folds],
            "mill": self.mill.name,
            "seconds": self.seconds,
        }

    def best_refit(self) -> Refit | None:
        """The named candidate's refit, or the best refitted one."""
        for r in self.refits:
            if r.effect == self.effect and r.location == self.location:
                return r
        return self.refits[0] if self.refits else None


@dataclass
class _Fold:
    train: tuple[int, ...]
    test: tuple[int, ...]
    base: FitOutcome | None = None
    heldout: list | None = None


def _fit_train(engine: Engine, windows: Sequence[Window], setup: Setup, start: State, *,
               scales: np.ndarray, max_nfev: int, keep_jac: bool = False,
               nuisance_first: bool = True) -> FitOutcome:
    if nuisance_first:
        # a start for the joint fit, which moves the loads again: one start per window
        start = _nuisance(engine, windows, setup,
                          State(p=setup.apply_gates(engine, start.p), W=start.W),
                          scales=scales, n_starts=1, max_nfev=6).state
    out = fit(engine, windows, setup, start, max_nfev=max_nfev, scales=scales,
              keep_jac=keep_jac)
    # where bites start in their gaps is nearly discrete (drive or back flanks): look again
    # with the fitted gaps and refit if another position is better
    again = scan_frac(engine, windows, out.state, scales=scales)
    if not np.array_equal(again.W[:, [4, 6]], out.state.W[:, [4, 6]]):  # frac, history
        out2 = fit(engine, windows, setup, again, max_nfev=max_nfev, scales=scales,
                   keep_jac=keep_jac)
        if out2.cost < out.cost:
            out = out2
    return out


def _heldout(engine: Engine, windows: Sequence[Window], setup: Setup, shared: State, *,
             scales: np.ndarray) -> FitOutcome:
    """Nuisance-only fit on held-out windows (shared parameters fixed).

    Every model gets the same treatment (so that no model wins by a luckier
    start): :func:`_nuisance` from the segmenter's estimates.
    """
    p = setup.apply_gates(engine, shared.p)
    return _nuisance(engine, windows, setup, State(p=p, W=initial_window_params(engine, windows)),
                     scales=scales)


def _nuisance(engine: Engine, windows: Sequence[Window], setup: Setup, start: State, *,
              scales: np.ndarray, n_starts: int = 2, max_nfev: int = 10) -> FitOutcome:
    """Per-window loads with the shared parameters held, window by window.

    The load ramp's duration and the gap positions of bites make local minima
    (the timing of flank impacts), so each window is fitted from the
    ``n_starts`` best rows of a grid of ramp durations and gap positions
    (:func:`~.engine.ramp_starts`) and keeps the best.  Windows do not
    share anything here, so each gets its own trust region.
    """
    p = setup.apply_gates(engine, start.p)
    W = start.W.copy()
    for i, w in enumerate(windows):
        best = None
        for row in ramp_starts(engine, w, p, W[i], k=n_starts, scales=scales):
            out = fit(engine, [w], setup, State(p=p, W=row[None, :]), free_shared=False,
                      max_nfev=max_nfev, scales=scales, ftol=1e-4)
            if best is None or out.cost < best.cost:
                best = out
        W[i] = best.state.W[0]
    return fit(engine, windows, setup, State(p=p, W=W), free_shared=False, max_nfev=0,
               scales=scales)


def _bic(out: FitOutcome) -> float:
    n = out.n_residuals
    return n * math.log(max(2 * out.cost / n, 1e-300)) + out.n_free * math.log(n)


def _pooled(engine: Engine, windows: Sequence[Window], sims: dict[int, np.ndarray],
            scales: np.ndarray) -> float:
    idx = sorted(sims)
    return nrmse(engine, [windows[i] for i in idx], [sims[i] for i in idx], scales)


def _effect_params(engine: Engine, setup: Setup, state: State, key: str) -> dict[str, float]:
    name, loc = key.split("@", 1)
    if name == "backlash":
        return {"gap": float(state.p[engine.p_index(f"{loc}.gap")])}
    c = engine.candidates[engine.candidate_index(key)]
    out = {nm: float(state.p[engine.p_index(f"{c.key}.{nm}")]) for nm in c.param_names}
    if name in ("softening_stiffness", "hardening_stiffness"):
        out["k_after"] = out["k_ratio"] * engine.mill.element(loc).k
    return out


def discrepancy(data: Any, mill: Mill, *, rule: DecisionRule = DecisionRule(),
                n_refit: int = 3, rate_hz: float = 1000.0, window_s: float = 0.45,
                max_nfev: int = 10, progress: Callable[[str], None] | None = None
                ) -> DiscrepancyResult:
    """Find where model and data disagree, name the missing effect, add it, refit.

    Parameters
    ----------
    data : Recording or sequence of windows
        A recording as read by :func:`ident.io.read_recording` (its bites and
        releases are segmented), or windows (:class:`~.windows.Window`,
        ``ident.fit``'s ``FitWindow`` or alike, reduced torques in N*m).
    mill : Mill
        The mill file's description (what the model knows).
    rule : DecisionRule
        When a candidate is named.
    n_refit : int
        Leading candidates added to the model and refitted.
    rate_hz : float
        Windows are resampled to this rate, Hz.
    window_s : float
        Window length after each step, s.
    max_nfev : int
        Solver budget per training fit.
    progress : callable, optional
        Called with one line per stage.

    Returns
    -------
    DiscrepancyResult

    Raises
    ------
    FitError
        Fewer than two bars (cross-validation needs bars to hold out), or no window.
    RecordingError
        The recording has none of the mill's torque channels.
    """
    t_start = time.perf_counter()
    say = progress or (lambda s: None)
    if hasattr(data, "frames"):
        windows = windows_from_recording(data, mill, window_s=window_s, rate_hz=rate_hz)
    else:
        windows = as_windows(data)
    bars = sorted({w.bar for w in windows})
    if len(bars) < 2:
        raise FitError(f"the discrepancy workflow holds whole bars out, so it needs windows of "
                       f"at least two bars. Got {len(bars)} bar(s) ({len(windows)} windows).")
    groups = fold_bars(bars)
    folds = []
    for g in groups:
        train = tuple(i for i, w in enumerate(windows) if w.bar not in g)
        test = tuple(i for i, w in enumerate(windows) if w.bar in g)
        folds.append(_Fold(train=train, test=test))
    say(f"{len(windows)} windows of {len(bars)} bars; held-out bars per fold {groups}")

    n = max(w.n_samples for w in windows)
    dt = windows[0].dt
    base_engine = build_engine(mill, (), dt=dt, n_samples=n)
    scales = channel_scales(base_engine, windows)
    base_setup = Setup.baseline(base_engine)

    # ---- baseline per fold, held-out residuals ----
    sims_before: dict[int, np.ndarray] = {}
    rises_before: dict[int, float] = {}
    for k, fd in enumerate(folds):
        tw = [windows[i] for i in fd.train]
        start = State(p=base_engine.base_params(), W=initial_window_params(base_engine, tw))
        fd.base = _fit_train(base_engine, tw, base_setup, start, scales=scales,
                             max_nfev=max_nfev + 6, keep_jac=True)
        hw = [windows[i] for i in fd.test]
        ho = _heldout(base_engine, hw, base_setup, fd.base.state, scales=scales)
        fd.heldout = [ho]
        for j, i in enumerate(fd.test):
            sims_before[i] = ho.sims[j]
            rises_before[i] = float(ho.state.W[j, 3])
        say(f"fold {k}: baseline train nrmse {fd.base.nrmse:.4f}, held-out {ho.nrmse:.4f}")
    before = _pooled(base_engine, windows, sims_before, scales)
    fold_before = [fd.heldout[0].nrmse for fd in folds]
    res_before = _residual_report(mill, base_engine, windows, sims_before, scales, rises_before)
    say(f"held-out nrmse of the mill file's model: {before:.4f}")

    # ---- candidates by signature ----
    super_engine = build_engine(mill, model_candidates(mill), dt=dt, n_samples=n)
    per_fold_scores = []
    for fd in folds:
        tw = [windows[i] for i in fd.train]
        moved = _moved_outcome(fd.base, base_engine, super_engine)
        linear = score_candidates(super_engine, tw, moved, scales=scales)
        per_fold_scores.append({c.key: c for c in rescore_on_grid(
            super_engine, tw, moved, linear, scales=scales, top=n_refit + 2)})
    keys = list(dict.fromkeys(k for sc in per_fold_scores for k in sc))
    candidates = []
    for key in keys:
        got = [sc[key] for sc in per_fold_scores if key in sc]
        total = float(sum(c.score for c in got))
        frac = float(np.mean([c.fraction for c in got]))
        best = max(got, key=lambda c: c.score)
        candidates.append(CandidateScore(effect=best.effect, location=best.location,
                                         score=total, fraction=frac, start=best.start))
    candidates.sort(key=lambda c: -c.score)
    chosen = [c for c in candidates if c.score > 0][:n_refit]
    say("leading candidates: " + ", ".join(f"{c.key} ({c.score:.0f})" for c in chosen))

    # ---- refit the leading candidates ----
    refits: list[Refit] = []
    for c in chosen:
        refits.append(_refit(mill, c, folds, windows, per_fold_scores, base_engine,
                             scales=scales, before=before, fold_before=fold_before,
                             max_nfev=max_nfev, dt=dt, n=n))
        r = refits[-1]
        say(f"refit {r.key}: held-out nrmse {r.nrmse:.4f} ({100 * r.improvement:+.1f} %), "
            f"folds {', '.join(f'{100 * v:+.1f} %' for v in r.fold_improvements)}")
    refits.sort(key=lambda r: r.nrmse)

    effect, location, explained, reason = rule.decide(refits)
    named = next((r for r in refits if r.effect == effect and r.location == location), None)
    after = named.nrmse if named is not None else before
    shown = named if named is not None else (refits[0] if refits else None)
    res_after = None
    if shown is not None:
        sims_after = {i: s for i, s in shown.sims}
        res_after = _residual_report(mill, base_engine, windows, sims_after, scales, rises_before)
    say(f"answer: {effect}@{location} ({reason})" if explained else f"answer: null ({reason})")
    return DiscrepancyResult(effect=effect, location=location, explained=explained,
                             before=before, after=after, candidates=tuple(candidates),
                             refits=tuple(refits), reason=reason, residuals_before=res_before,
                             residuals_after=res_after, windows=tuple(windows), mill=mill,
                             folds=tuple(fd.test for fd in folds), rule=rule,
                             seconds=time.perf_counter() - t_start,
                             sims_before=tuple(sorted(sims_before.items())),
                             measured=base_engine.measured)


def fold_bars(bars: Sequence[int]) -> tuple[tuple[int, ...], ...]:
    """The bars each cross-validation fold holds out (every bar exactly once).

    Bars alternate between two folds, so that each fold's model learns from
    bars spread over the recording; with three bars, each is held out on its
    own instead (three folds), so that every fold still trains on two bars:
    a single bar pins down little (one bite: one roll angle at bite, one load).

    Parameters
    ----------
    bars : sequence of int
        The recording's bars, in time order (at least two).

    Returns
    -------
    tuple of tuple of int
    """
    bars = tuple(bars)
    k = 3 if len(bars) == 3 else 2
    return tuple(bars[i::k] for i in range(k))


def _moved_outcome(out: FitOutcome, src: Engine, dst: Engine) -> FitOutcome:
    return replace(out, state=out.state.moved(src, dst))


def _residual_report(mill: Mill, engine: Engine, windows: Sequence[Window],
                     sims: dict[int, np.ndarray], scales: np.ndarray,
                     rises: dict[int, float]) -> ResidualReport:
    idx = sorted(sims)
    ws = [windows[i] for i in idx]
    res = [(sims[i] - windows[i].columns(engine.measured)) / scales for i in idx]
    return analyse_residuals(mill, ws, res, engine.measured, rises=[rises[i] for i in idx])


def _best_start(engine: Engine, setup: Setup, windows: Sequence[Window], base: State,
                cand: CandidateScore, *, scales: np.ndarray, base_fit: FitOutcome,
                base_engine: Engine) -> State:
    """The lowest-cost start on the training windows among: the baseline; the signature's
    Gauss-Newton step (candidate and baseline variables together, full and half); the
    candidate's grid."""
    best_state, best_cost = base, _cost(engine, windows, setup, base, scales)
    if cand.step is not None and cand.start and base_fit.layout is not None:
        for f in (1.0, 0.5):
            moved = base_fit.layout.stepped(base_fit.state, f * cand.step)
            st = start_state(engine, moved.moved(base_engine, engine), replace(
                cand, start={k: (v if k not in _LINEAR else f * v)
                             for k, v in cand.start.items()}))
            c = _cost(engine, windows, setup, st, scales)
            if c < best_cost:
                best_state, best_cost = st, c
    for point in start_grid(engine.mill, cand, torque=peak_torque(windows)):
        st = start_state(engine, base, replace(cand, start=point))
        st = scan_frac(engine, windows, State(p=setup.apply_gates(engine, st.p), W=st.W),
                       scales=scales)
        c = _cost(engine, windows, setup, st, scales)
        if c < best_cost:
            best_state, best_cost = st, c
    return best_state


def _fresh_start(engine: Engine, setup: Setup, windows: Sequence[Window],
                 cand: CandidateScore, base: State, *, scales: np.ndarray) -> State:
    """From the mill file's gaps and the baseline's loads: the best grid point.

    Gap-like effects have narrow basins (the timing of flank impacts), so the
    grid is fine and each point gets its own gap positions (``frac``).
    """
    best, best_cost = None, math.inf
    start = State(p=engine.base_params(), W=base.W.copy())
    for point in ([dict(cand.start)] if cand.start else []) + start_grid(
            engine.mill, cand, fine=True, torque=peak_torque(windows)):
        st = start_state(engine, start, replace(cand, start=point))
        st = scan_frac(engine, windows, State(p=setup.apply_gates(engine, st.p), W=st.W),
                       scales=scales)
        c = _cost(engine, windows, setup, st, scales)
        if c < best_cost:
            best, best_cost = st, c
    return best


def _regrid(engine: Engine, setup: Setup, windows: Sequence[Window], out: FitOutcome,
            cand: CandidateScore, *, scales: np.ndarray, max_nfev: int) -> FitOutcome:
    """Look again from a fit's gaps and loads: the candidate's fine grid, refitted if better.

    The starting grids were judged with the baseline's loads (or the mill file's
    gaps); once the loads fit the candidate, a grid point that beats the fit
    itself marks a better basin (a knee with its stiffness ratio, a lag, a gap).
    """
    best_cost, best = 2.0 * out.cost, None  # _cost is the plain sum of squares
    for point in start_grid(engine.mill, cand, fine=True, torque=peak_torque(windows)):
        st = start_state(engine, out.state, replace(cand, start=point))
        c = _cost(engine, windows, setup, st, scales)
        if c < best_cost:
            best_cost, best = c, st
    if best is None:
        return out
    alt = fit(engine, windows, setup, best, max_nfev=max_nfev, scales=scales)
    return alt if alt.cost < out.cost else out


#: Effect parameters that scale the effect linearly (halved with a half step).
_LINEAR = ("force", "amplitude", "k", "c")


def _grid_refine(engine: Engine, setup: Setup, windows: Sequence[Window], start: State,
                 key: str, *, scales: np.ndarray) -> State:
    """Grid over ``amplitude`` and ``phase`` of a roll-angle effect, then a finer one.

    Each point is judged after a short fit of the loads: the bites' ramps and
    gap positions were fitted for another model, and at them the cost over the
    phase has its minima in the wrong places.  The amplitudes are shares of
    the spindle's gap (the open part cannot swing further than the gap).
    """
    ia = engine.p_index(f"{key}.amplitude")
    ip = engine.p_index(f"{key}.phase")
    gap = max(engine.mill.element(key.split("@", 1)[1]).gap, 1e-3)
    hold = Setup.baseline(engine).with_active(setup.active)
    W_start = start.W.copy()
    W_start[:, WINDOW_PARAMS.index("history")] = 1.0  # rows fitted for the baseline start at rest

    def cost_at(a: float, ph: float) -> tuple[float, np.ndarray]:
        p = hold.apply_gates(engine, start.p)
        p[ia], p[ip] = a, ph
        # each bite after a release from its simulated idle or at rest, whichever fits
        st = scan_frac(engine, windows, State(p=p, W=W_start), scales=scales)
        out = fit(engine, windows, hold, st, free_shared=False, max_nfev=4,
                  scales=scales, ftol=1e-3)
        return out.cost, out.state.W

    c0, W0 = cost_at(float(start.p[ia]), float(start.p[ip]))
    best = (c0, float(start.p[ia]), float(start.p[ip]), W0)
    for a in (0.35, 0.7):
        for ph in np.arange(8) * math.pi / 4:
            c, W = cost_at(a * gap, ph)
            if c < best[0]:
                best = (c, a * gap, ph, W)
    _, a0, p0, _ = best
    for fa, dp in ((0.75, 0.0), (1.3, 0.0), (1.0, -math.pi / 8), (1.0, math.pi / 8)):
        c, W = cost_at(min(a0 * fa, gap), p0 + dp)
        if c < best[0]:
            best = (c, min(a0 * fa, gap), p0 + dp, W)
    p = start.p.copy()
    p[ia], p[ip] = best[1], best[2]
    return State(p=p, W=best[3].copy())


def _cost(engine: Engine, windows: Sequence[Window], setup: Setup, state: State,
          scales: np.ndarray) -> float:
    p = setup.apply_gates(engine, state.p)
    tot = 0.0
    for i, w in enumerate(windows):
        r = (simulate_window(engine, w, p, state.W[i]) - w.columns(engine.measured)) / scales
        tot += float(np.sum(r ** 2))
    return tot


def _refit(mill: Mill, cand: CandidateScore, folds: list, windows: Sequence[Window],
           per_fold_scores: list, base_engine: Engine, *, scales: np.ndarray, before: float,
           fold_before: list, max_nfev: int, dt: float, n: int) -> Refit:
    key = cand.key
    if cand.effect == "backlash":
        engine = base_engine
    else:
        engine = build_engine(mill, (make_effect(cand.effect, cand.location),), dt=dt,
                              n_samples=n)
    setup = Setup.for_candidate(engine, key)
    rough = any(getattr(c, "needs_history", False) for c in engine.candidates)
    sims: dict[int, np.ndarray] = {}
    params, train, fold_nrmse, dbic = [], [], [], 0.0
    for k, fd in enumerate(folds):
        tw = [windows[i] for i in fd.train]
        sc = per_fold_scores[k].get(key)
        start_cand = sc if (sc is not None and sc.score > 0) else cand
        st = _best_start(engine, setup, tw, fd.base.state.moved(base_engine, engine),
                         start_cand, scales=scales, base_fit=fd.base, base_engine=base_engine)
        if rough:
            # a rough cost (idle rattle): search the effect's parameters on a grid first,
            # each point with its loads fitted
            st = _grid_refine(engine, setup, tw, st, key, scales=scales)
        # the loads first: the baseline's ramps and gap positions were fitted around the
        # missing effect, and from them the joint fit can stall far from the candidate's
        # optimum (a knee slides along a narrow valley of the loaded stiffness)
        out = _fit_train(engine, tw, setup, st, scales=scales, max_nfev=max_nfev)
        if rough:
            # the baseline bends its gaps around a swinging gap (a rattle it cannot make),
            # and from its gaps the effect looks worse than it is: again from the mill
            # file's gaps
            moved = fd.base.state.moved(base_engine, engine)
            fresh = _grid_refine(engine, setup, tw, State(p=engine.base_params(), W=moved.W),
                                 key, scales=scales)
            alt = _fit_train(engine, tw, setup, fresh, scales=scales, max_nfev=max_nfev)
            if alt.cost < out.cost:
                out = alt
        else:
            # the baseline may have bent its gaps and gap positions around the missing
            # effect, and the candidate then settles next to them: start afresh as the
            # baseline did, from the mill file's gaps and the best grid point
            moved = fd.base.state.moved(base_engine, engine)
            starts = [_fresh_start(engine, setup, tw, start_cand, moved, scales=scales)]
            if cand.effect == "backlash":
                # flank impacts make narrow basins in the gap size: several starts
                starts += [start_state(engine, State(p=engine.base_params(), W=moved.W),
                                       replace(start_cand, start={"gap": g}))
                           for g in (8e-4, 1.6e-3, 2.8e-3, 4.5e-3)]
            for fresh in starts:
                alt = _fit_train(engine, tw, setup, fresh, scales=scales, max_nfev=max_nfev)
                if alt.cost < out.cost:
                    out = alt
            out = _regrid(engine, setup, tw, out, start_cand, scales=scales, max_nfev=max_nfev)
        hw = [windows[i] for i in fd.test]
        ho = _heldout(engine, hw, setup, out.state, scales=scales)
        for j, i in enumerate(fd.test):
            sims[i] = ho.sims[j]
        params.append(_effect_params(engine, setup, out.state, key))
        train.append(out.nrmse)
        fold_nrmse.append(ho.nrmse)
        dbic += _bic(out) - _bic(fd.base)
    total = _pooled(engine, windows, sims, scales)
    return Refit(effect=cand.effect, location=cand.location, score=cand.score,
                 params=tuple(params), nrmse=total, improvement=1.0 - total / before,
                 fold_improvements=tuple(1.0 - a / b for a, b in zip(fold_nrmse, fold_before)),
                 train_nrmse=tuple(train), delta_bic=dbic, sims=tuple(sorted(sims.items())))
