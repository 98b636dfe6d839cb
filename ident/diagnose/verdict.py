"""One wear verdict per element and bearing of a recording, and the ``diagnose`` JSON.

    fit JSON (cli.md ``fit``) ─────┐
                                   ├──► verdicts(mill, diagnosis, fit=...) ──► diagnosis_json
    Diagnosis (trained model) ─────┘

The one place that decides an element's or bearing's state from a recording's
evidence; ``ident diagnose`` and the campaign (:mod:`ident.store.process`) both
call :func:`diagnosis_json`.

* An element whose gap the fit identified (``identified: true`` in the fit
  JSON), or whose interval it trusts though it is wider than an identified
  gap's (``bounded: true``, :mod:`ident.fit.verdict`), takes its state from that
  gap against the element's ``gap_worn`` and ``gap_critical``
  (:func:`~ident.diagnose.states.element_state`), and the state's probability
  from the gap's 95 % interval against those limits: the interval is read as a
  split normal around the estimate (each side's standard deviation its
  half-width / 1.96) and the probability of a state is that distribution's mass
  between the state's limits.  ``source: "fit"``; ``identified`` says which of
  the two, and a bounded gap carries the fit's ``reason``.  A state needs less
  than a gap's value: 9.1 mrad with +-20 % is critical or at least worn.
* Any other element takes the trained diagnosis' state and probability (the
  regressor's interval blended with the classifier, :mod:`ident.diagnose.model`),
  ``source: "diagnosis"``, with the fit's ``reason`` when a fit did not
  identify it.
* A bearing always takes the diagnosis' state (from its accelerometers),
  ``source: "diagnosis"``.

An element or bearing with neither evidence has no verdict (it is left out).
Values are SI: gaps in rad reduced to the motor shaft, clearances in m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Mapping

from ..description import Element, Mill
from .model import UNCERTAIN_PROBABILITY, Diagnosis, TargetDiagnosis
from .states import element_state

__all__ = ["Verdict", "state_probabilities", "fit_verdicts", "verdicts", "diagnosis_json",
           "SOURCES"]

_Z95 = 1.959963984540054
#: where a verdict comes from
SOURCES: tuple[str, ...] = ("fit", "diagnosis")


@dataclass(frozen=True)
class Verdict:
    """The wear state of one element or bearing in one recording.

    Attributes
    ----------
    kind : {'element', 'bearing'}
    target : str
        Element or bearing id.
    state : {'good', 'worn', 'critical'}
    probability : float
        Probability of ``state``.
    probabilities : dict
        Every state's probability.
    value : float
        Gap (rad, reduced) or clearance (m) the state rests on.
    ci95 : (float, float)
        Its 95 % interval (NaN when not known).
    source : {'fit', 'diagnosis'}
    reason : str
        Why an element's verdict is not the fit's, or why the fit's gap is only
        bounded (the fit's own reason), else "".
    diagnosis : TargetDiagnosis or None
        The trained diagnosis of the same target, also where the fit decided.
    identified : bool
        ``source`` is the fit and it identified the gap (False for a gap the
        fit only bounded, and for the diagnosis).
    """

    kind: Literal["element", "bearing"]
    target: str
    state: str
    probability: float
    probabilities: dict[str, float]
    value: float
    ci95: tuple[float, float]
    source: Literal["fit", "diagnosis"]
    reason: str = ""
    diagnosis: TargetDiagnosis | None = field(default=None, compare=False)
    identified: bool = False

    @property
    def uncertain(self) -> bool:
        """The state's probability is below :data:`~ident.diagnose.model.UNCERTAIN_PROBABILITY`
        (or the diagnosis flagged the recording as out of its library's range)."""
        if self.source == "diagnosis" and self.diagnosis is not None:
            return bool(self.diagnosis.uncertain)
        return bool(self.probability < UNCERTAIN_PROBABILITY)


def _split_normal_cdf(x: float, mu: float, s_lo: float, s_hi: float) -> float:
    """CDF at ``x`` of the split normal with mode ``mu`` and side deviations ``s_lo, s_hi``."""
    if s_lo <= 0 and s_hi <= 0:
        return 1.0 if x >= mu else 0.0
    tot = s_lo + s_hi
    if x <= mu:
        if s_lo <= 0:
            return 0.0
        return 2.0 * s_lo / tot * 0.5 * math.erfc(-(x - mu) / (s_lo * math.sqrt(2.0)))
    if s_hi <= 0:
        return 1.0
    return 1.0 - 2.0 * s_hi / tot * 0.5 * math.erfc((x - mu) / (s_hi * math.sqrt(2.0)))


def state_probabilities(value: float, ci95: tuple[float, float],
                        limits: tuple[float, float]) -> dict[str, float]:
    """Probability of each state from an estimate and its 95 % interval.

    Parameters
    ----------
    value : float
        Estimate (rad or m).
    ci95 : (float, float)
        Its 95 % interval, same unit; a missing or inverted side counts as zero width.
    limits : (float, float)
        Worn and critical limits, same unit.

    Returns
    -------
    dict
        ``{"good": p, "worn": p, "critical": p}``, summing to 1: the mass of the
        split normal (side deviations = half-widths / 1.96) below the worn limit,
        between the limits and above the critical one.
    """
    lo, hi = ci95
    s_lo = max(value - lo, 0.0) / _Z95 if math.isfinite(lo) else 0.0
    s_hi = max(hi - value, 0.0) / _Z95 if math.isfinite(hi) else 0.0
    worn, crit = limits
    f_w = _split_normal_cdf(worn, value, s_lo, s_hi)
    f_c = _split_normal_cdf(crit, value, s_lo, s_hi)
    p = {"good": f_w, "worn": max(f_c - f_w, 0.0), "critical": max(1.0 - f_c, 0.0)}
    tot = sum(p.values())
    return {k: v / tot for k, v in p.items()}


def _num(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def _fit_verdict(e: Element, el: Mapping[str, Any]) -> Verdict | None:
    gap = _num(el.get("gap"))
    identified = bool(el.get("identified"))
    if not (identified or el.get("bounded")) or not math.isfinite(gap):
        return None
    ci = el.get("gap_ci95") or [math.nan, math.nan]
    ci95 = (_num(ci[0]), _num(ci[1]))
    probs = state_probabilities(gap, ci95, (e.gap_worn, e.gap_critical))
    state = element_state(e, gap).value
    return Verdict(kind="element", target=e.id, state=state, probability=probs[state],
                   probabilities=probs, value=gap, ci95=ci95, source="fit",
                   reason="" if identified else str(el.get("reason") or ""),
                   identified=identified)


def fit_verdicts(mill: Mill, fit: Mapping[str, Any] | None) -> dict[str, Verdict]:
    """Verdicts of the elements the fit identified or bounded (cli.md ``fit`` JSON), by
    element id."""
    els = (fit or {}).get("elements") or {}
    out = {}
    for e in mill.elements:
        v = _fit_verdict(e, els.get(e.id) or {})
        if v is not None:
            out[e.id] = v
    return out


def _from_diagnosis(kind: str, target: str, d: TargetDiagnosis, reason: str = "") -> Verdict:
    return Verdict(kind=kind, target=target, state=d.state, probability=float(d.probability),
                   probabilities=dict(d.probabilities), value=float(d.size),
                   ci95=(float(d.interval[0]), float(d.interval[1])), source="diagnosis",
                   reason=reason, diagnosis=d)


def verdicts(mill: Mill, diagnosis: Diagnosis | None, *, fit: Mapping[str, Any] | None = None,
             ) -> tuple[dict[str, Verdict], dict[str, Verdict]]:
    """Each element's and bearing's verdict from a recording's fit and diagnosis.

    Parameters
    ----------
    mill : Mill
    diagnosis : Diagnosis or None
        :func:`~ident.diagnose.diagnose_features` of the recording (None: no model).
    fit : mapping, optional
        cli.md ``fit`` JSON of the same recording.

    Returns
    -------
    elements, bearings : dict of str to Verdict
        In the mill file's order; a target without evidence is left out.
    """
    by_fit = fit_verdicts(mill, fit)
    fit_els = (fit or {}).get("elements") or {}
    elements: dict[str, Verdict] = {}
    for e in mill.elements:
        d = diagnosis.elements.get(e.id) if diagnosis is not None else None
        if e.id in by_fit:
            elements[e.id] = replace(by_fit[e.id], diagnosis=d)
        elif d is not None:
            el = fit_els.get(e.id)
            reason = ""
            if el is not None:
                reason = str(el.get("reason") or "the fit did not identify its gap")
            elements[e.id] = _from_diagnosis("element", e.id, d, reason)
    bearings = {b.id: _from_diagnosis("bearing", b.id, diagnosis.bearings[b.id])
                for b in mill.bearings if diagnosis is not None and b.id in diagnosis.bearings}
    return elements, bearings


def _diag_block(d: TargetDiagnosis, size_key: str) -> dict[str, Any]:
    return {"state": d.state, "probability": d.probability, size_key: d.size,
            f"{size_key}_ci95": list(d.interval), "probabilities": d.probabilities,
            "uncertain": d.uncertain, "novelty": d.novelty,
            "explanations": list(d.explanation)}


def _element_block(e: Element, v: Verdict) -> dict[str, Any]:
    out: dict[str, Any] = {"state": v.state, "probability": v.probability, "gap": v.value,
                           "source": v.source, "gap_ci95": list(v.ci95),
                           "probabilities": v.probabilities, "uncertain": v.uncertain}
    mm = e.gap_mm(v.value)
    if mm is not None:
        out["gap_mm"] = mm
    d = v.diagnosis
    if v.source == "fit":
        out["identified"] = v.identified
        if v.reason:
            out["reason"] = v.reason
        if d is not None:  # what the trained model said, for comparison
            out["diagnosis"] = {"state": d.state, "probability": d.probability, "gap": d.size,
                                "gap_ci95": list(d.interval)}
    else:
        out.update({k: x for k, x in _diag_block(d, "gap").items() if k not in out})
        out["observable"] = d.observable
        if v.reason:
            out["reason"] = v.reason
    if d is not None:
        out.setdefault("observable", d.observable)
    return out


def diagnosis_json(mill: Mill, diagnosis: Diagnosis | None, *,
                   fit: Mapping[str, Any] | None = None,
                   features: Mapping[str, Any] | None = None,
                   warnings: tuple[str, ...] | list[str] = ()) -> dict[str, Any]:
    """cli.md ``diagnose`` JSON of one recording (``elements``, ``bearings``, ``features``).

    Every element and bearing with a verdict (:func:`verdicts`) appears with ``state``,
    ``probability``, its value (``gap`` in rad or ``clearance`` in m) and ``source``
    (``fit`` or ``diagnosis``), plus its interval, every state's probability and,
    from the diagnosis, ``uncertain``, ``novelty`` and the features that drove it.

    Parameters
    ----------
    mill : Mill
    diagnosis : Diagnosis or None
    fit : mapping, optional
        cli.md ``fit`` JSON of the same recording.
    features : mapping, optional
        :func:`ident.features.feature_summary` of the recording.
    warnings : sequence of str
        Added to the diagnosis' own warnings.
    """
    els, brs = verdicts(mill, diagnosis, fit=fit)
    elements = {eid: _element_block(mill.element(eid), v) for eid, v in els.items()}
    bearings = {}
    for bid, v in brs.items():
        d = v.diagnosis
        bearings[bid] = {"state": v.state, "probability": v.probability, "clearance": v.value,
                         "source": v.source, "clearance_mm": v.value * 1e3,
                         **{k: x for k, x in _diag_block(d, "clearance").items()
                            if k not in ("state", "probability", "clearance")}}
    out: dict[str, Any] = {"elements": elements, "bearings": bearings}
    out["features"] = dict(features) if features is not None else {}
    out["warnings"] = list(diagnosis.warnings if diagnosis is not None else ()) + list(warnings)
    return out

