"""Which features drove a decision, and what they mean.

For one recording and one element (or bearing), each of the target's most
important features (permutation importance of its regressor over the
library, then the features it ranks best) is set in turn to its median over
the library's ``good`` samples, and the drop of the decided state's
probability is that feature's *effect*: the features whose typical healthy
value would most have changed the decision drove it.  For a ``good``
decision the reference is the ``critical`` median instead.  One batch of
probability calls per decision.

:func:`describe_feature` turns a feature name into words, e.g.
``bite.C46.A20.phase`` -> "phase shift at 20 Hz against the linear baseline
(deg) in C46's torque, at bites" -- the seed's A20 and its phase (section 2.1).
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from ..features.rattle import RATTLE_BANDS_HZ, RATTLE_FEATURES
from ..features.sweep import SWEEP_FEATURES

__all__ = ["explain_decision", "describe_feature"]

_TORQUE = {
    "ratio": "amplitude at {f} Hz over the linear baseline's (log10)",
    "phase": "phase shift at {f} Hz against the linear baseline (deg)",
    "": "amplitude at {f} Hz per N*m of load step",
}
_SWEEP = {
    "peak": "peak torque over the step (TAF in units of the step)",
    "peak_ms": "time of the peak torque after the step (ms)",
    "onset_rate": "steepest rise as the flanks meet (1/s)",
    "impact": "impact at the flanks' contact (steepest rise squared x static torque)",
    "rebound": "rebound beyond the new level (fraction of the step)",
    "rebound_ms": "time of the rebound after the step (ms)",
    "brake": "speed-loop braking excursion beyond the new level (fraction of the step)",
    "brake_ms": "time of the braking excursion (ms)",
    "back_rate": "closing speed at the back-flank contact (1/s)",
    "sweep": "back-flank contact time x closing speed (gap swept)",
    "settled": "time at the new level after the step (zero torque inside a gap)",
}
_OTHER = {
    "residual": "RMS difference from the linear baseline's response",
    "taf": "torque amplification factor (TAF)",
    "taf.excess": "TAF above the linear baseline's",
    "taf_slope": "change of TAF with static torque over the bars (seed 1.1)",
    "lag_ms": "delay of the torque rise behind the baseline's (ms)",
    "dwell": "time spent with the torque near its new level (inside a gap)",
    "H2": "2nd harmonic of the dominant mode",
    "H3": "3rd harmonic of the dominant mode",
    "rms": "housing vibration RMS", "peak": "housing vibration peak",
    "rms_late": "housing vibration RMS after the impact",
    "crest": "crest factor of the housing vibration",
    "kurtosis": "kurtosis of the housing vibration",
    "f_peak": "dominant housing frequency (Hz)",
    "centroid_hz": "spectral centroid of the housing vibration (Hz)",
    "phase": "phase of the dominant housing frequency (deg)",
    "impact_ms": "time of the first housing impact after the step (ms)",
}
_RATTLE = {
    "lrms": "housing vibration RMS (log10, per the mesh-force step's)",
    "lpeak": "housing vibration peak (log10, per the mesh-force step's)",
    "kurt": "kurtosis of the housing vibration",
    "rate": "shaft impacts per second",
    "ival_ms": "interval between shaft impacts (ms)",
    "cent_hz": "spectral centroid of the housing vibration (Hz)",
    "cent_low_hz": "spectral centroid of the housing vibration below 700 Hz (Hz)",
    "lpeak_med": "median shaft impact (log10, per the mesh-force step's)",
    "lswing": "impact height x interval between impacts (log10; ~ clearance flown)",
}
_WINDOW = {"hit": "around the step", "after": "after the step (the rattle in the pause, or "
                                              "rolling)"}
_CONTEXT = {"static": "static torque over nominal", "rise_ms": "rise time of the load step (ms)",
            "idle_level": "load between bars over nominal"}
_AGG = {"max": "largest", "min": "smallest"}


def _sweep_words(name: str) -> str:
    m = re.fullmatch(r"rise(\d\d)_ms", name)
    if m:
        return f"time the torque reaches {int(m.group(1))} % of its step (ms)"
    m = re.fullmatch(r"back(\d\d)_(ms|sq|st)", name)
    if m:
        pct = int(m.group(1))
        return {"ms": f"time to the back-flank contact ({pct} % beyond the new level, ms)",
                "sq": f"back-flank contact time ({pct} %) squared x static torque (gap swept "
                      f"under braking)",
                "st": f"back-flank contact time ({pct} %) x static torque (gap swept by the "
                      f"rebound)"}[m.group(2)]
    return _SWEEP.get(name, name)


def describe_feature(name: str) -> str:
    """Plain-words description of a feature name."""
    parts = name.split(".")
    if len(parts) < 3:
        if len(parts) == 2 and parts[1] in _CONTEXT:
            at = {"bite": "at bites", "release": "at releases"}.get(parts[0], parts[0])
            return f"{_CONTEXT[parts[1]]}, {at}"
        return {"bite.static": "static torque over nominal", "n_bites": "number of bites",
                "n_releases": "number of releases"}.get(name, name)
    kind, where = parts[0], parts[1]
    rest = parts[2:]
    agg = ""
    if rest[-1] in _AGG and len(rest) > 1:
        agg = _AGG[rest[-1]]
        rest = rest[:-1]
    tail = ".".join(rest)
    at = {"bite": "bites", "release": "releases"}.get(kind, kind)
    at = f"{agg} over the {at}" if agg else f"at {at}"
    m = re.fullmatch(r"A(\d+)b*(?:\.(ratio|phase))?", tail)
    if m:
        what = _TORQUE[m.group(2) or ""].format(f=m.group(1))
        return f"{what} in {where}'s torque, {at}"
    if ":" in where:
        src = f"accelerometer {where}"
        if rest[0] in _WINDOW and len(rest) == 2 and rest[1] in RATTLE_FEATURES:
            m = re.fullmatch(r"b(\d+)", rest[1])
            if m:
                i = int(m.group(1))
                what = (f"housing vibration energy fraction in {RATTLE_BANDS_HZ[i]:.0f}-"
                        f"{RATTLE_BANDS_HZ[i + 1]:.0f} Hz")
            else:
                what = _RATTLE.get(rest[1], rest[1])
            return f"{what} {_WINDOW[rest[0]]} at {src}, {at}"
        if tail.startswith("band"):
            return f"housing vibration energy fraction in band {tail[4:]} at {src}, {at}"
        return f"{_OTHER.get(tail, tail)} in {src}, {at}"
    if tail in SWEEP_FEATURES:
        what = _sweep_words(tail)
        if "-" in where:
            a, b = where.split("-", 1)
            return f"{what}: {a}'s minus {b}'s torque, {at}"
        src = "the summed torque nearest the rolls" if where == "near" else f"{where}'s torque"
        return f"{what} in {src}, {at}"
    return f"{_OTHER.get(tail, tail)} in {where}'s torque, {at}"


def explain_decision(target: Any, x: np.ndarray, state: str, *, n: int = 3,
                     candidates: int = 15,
                     min_effect: float = 1e-3) -> tuple[dict[str, Any], ...]:
    """Features that drove the decision ``state`` for one feature vector.

    Parameters
    ----------
    target : TargetModel
        The element's or bearing's models (``ident.diagnose.model``).
    x : ndarray, shape (n_features,)
        The recording's features in ``target.features`` order.
    state : str
        The decided state.
    n : int
        Features to return.
    candidates : int
        Most important features tried.
    min_effect : float
        Smaller drops of the probability are not reported.

    Returns
    -------
    tuple of dict
        ``feature``, ``description``, ``value``, ``reference`` (the median the
        feature was set to), ``reference_state`` and ``effect`` (drop of the
        state's probability), largest effect first; only effects above
        ``min_effect``.
    """
    from .states import STATES

    names = list(target.features)
    ref_state = "critical" if state == "good" else "good"
    ref = target.class_medians.get(ref_state, {})
    cand = [nm for nm, _ in target.importances if nm in names][:candidates]
    for nm in names:  # too few important ones (a small library): the others in turn
        if len(cand) >= candidates:
            break
        if nm not in cand:
            cand.append(nm)
    cand = [nm for nm in cand if np.isfinite(ref.get(nm, np.nan))]
    if not cand or state not in STATES:
        return ()
    k = STATES.index(state)
    X = np.repeat(np.asarray(x, dtype=float)[None, :], len(cand) + 1, axis=0)
    for i, nm in enumerate(cand):
        X[i + 1, names.index(nm)] = ref[nm]
    p = target.state_proba(X)[0][:, k]
    effects = p[0] - p[1:]
    order = np.argsort(-effects, kind="stable")
    out = []
    for i in order[:n]:
        if effects[i] <= min_effect:
            break
        nm = cand[i]
        v = float(x[names.index(nm)])
        out.append({"feature": nm, "description": describe_feature(nm),
                    "value": v if np.isfinite(v) else None,
                    "reference": float(ref[nm]), "reference_state": ref_state,
                    "effect": float(effects[i])})
    return tuple(out)
