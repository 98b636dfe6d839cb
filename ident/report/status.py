"""Each part's wear status for plant systems: the ``report --json`` document (cli.md).

    MillSection.assessments ──► part_status (SI values, ISO dates, days left) ──► status_json

Values leave in SI (gaps in rad reduced to the motor shaft, clearances in m),
dates as ISO 8601 (UTC), ``days_left`` counted from the report's date.  The
"next limit" of a part is the worn limit while its value is below it, the
critical limit after; ``days_left`` is 0 once the critical limit is reached and
null when there is no significantly rising trend to extrapolate.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass
from typing import Any, Sequence

from .build import DAY_NS, Assessment, MillSection
from .trend import Crossing

__all__ = ["status_json", "part_status", "remaining_life", "iso_date", "RemainingLife"]

#: Dates further than this from the reference (days) are not dates a plant can use.
_FAR_DAYS = 36_500.0


def iso_date(t_ref_ns: int, days: float) -> str | None:
    """``t_ref + days`` as an ISO date (``YYYY-MM-DD``, UTC), or None when not finite/far."""
    if days is None or not math.isfinite(days) or abs(days) > _FAR_DAYS:
        return None
    return (dt.datetime.fromtimestamp(t_ref_ns / 1e9, dt.timezone.utc)
            + dt.timedelta(days=float(days))).date().isoformat()


def _iso_time(t_ns: int) -> str | None:
    if not t_ns:
        return None
    return dt.datetime.fromtimestamp(t_ns / 1e9, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _num(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _crossed(a: Assessment, c: Crossing | None, limit: float, reached: float) -> float:
    """Day the part reached ``limit``: the trend's crossing, else the first value at or above it."""
    if c is not None and c.trend and math.isfinite(c.t):
        return c.t
    if math.isfinite(a.now) and a.now >= limit:
        return reached
    return math.nan


@dataclass(frozen=True)
class RemainingLife:
    """Days from the report's date to a part's next limit, with a 95 % interval.

    Attributes
    ----------
    limit : {'worn', 'critical'} or None
        The next limit (None: the state is unknown).
    days, days_lo, days_hi : float
        Days left (0 once the critical limit is reached) and its interval; NaN
        without a significantly rising trend, ``days_hi`` inf when the trend's
        lower band never reaches the limit.
    """

    limit: str | None
    days: float
    days_lo: float
    days_hi: float


def remaining_life(a: Assessment, t_report: float) -> RemainingLife:
    """Days left to ``a``'s next limit from ``t_report`` (days since the section's reference).

    The next limit is the worn one while the current value is below it (or, with no
    value, while the status is good), the critical one after.
    """
    nan = math.nan
    if a.status == "unknown":
        return RemainingLife(None, nan, nan, nan)
    if a.status == "critical" or (math.isfinite(a.now) and a.now >= a.critical):
        return RemainingLife("critical", 0.0, 0.0, 0.0)
    past_worn = a.now >= a.worn if math.isfinite(a.now) else a.status != "good"
    limit, c = ("critical", a.critical_at) if past_worn else ("worn", a.worn_at)
    if c is None or not c.trend or not math.isfinite(c.t):
        return RemainingLife(limit, nan, nan, nan)

    def left(t: float) -> float:
        return max(t - t_report, 0.0) if math.isfinite(t) else t

    return RemainingLife(limit, left(c.t), left(c.t_early), left(c.t_late))


def part_status(a: Assessment, section: MillSection, now_ns: int) -> dict[str, Any]:
    """One element's or bearing's entry of the ``report --json`` document.

    Parameters
    ----------
    a : Assessment
    section : MillSection
        Its mill (the reference time of ``a``'s days).
    now_ns : int
        The report's date, ns since the epoch (UTC).
    """
    t_ref = section.t_ref_ns
    t_report = (now_ns - t_ref) / DAY_NS
    si = 1.0 / a.scale if a.scale else 1.0

    def v(x: float) -> float | None:
        return _num(x * si)

    out: dict[str, Any] = {"status": a.status, "reason": a.reason,
                           "now": v(a.now),
                           "now_ci95": [v(a.now_lo), v(a.now_hi)] if math.isfinite(a.now_lo)
                           else None,
                           "worn_limit": v(a.worn), "critical_limit": v(a.critical)}
    for name, c, limit, reached in (("worn", a.worn_at, a.worn, a.worn_reached),
                                    ("critical", a.critical_at, a.critical,
                                     a.critical_reached)):
        out[f"{name}_at"] = iso_date(t_ref, _crossed(a, c, limit, reached))
        ci = None
        if c is not None and c.trend and math.isfinite(c.t_early):
            ci = [iso_date(t_ref, c.t_early), iso_date(t_ref, c.t_late)]
        out[f"{name}_at_ci95"] = ci
        out[f"{name}_reached"] = bool(math.isfinite(a.now) and a.now >= limit)
    life = remaining_life(a, t_report)
    out["next_limit"] = life.limit
    out["days_left"] = _num(round(life.days, 1)) if math.isfinite(life.days) else None
    out["days_left_ci95"] = ([_num(round(life.days_lo, 1)),
                              _num(round(life.days_hi, 1)) if math.isfinite(life.days_hi)
                              else None] if math.isfinite(life.days_lo) else None)
    out["slope_per_day"] = v(a.slope_per_30d / 30.0)
    out["last_recording"] = iso_date(t_ref, a.t_last)
    out["n_identified"] = int(a.n_identified)
    out["n_rejected"] = int(a.n_rejected)
    out["n_recordings"] = int(a.n_recordings)
    out["source"] = a.source or None
    out["diagnosis"] = a.classifier
    return out


def status_json(sections: Sequence[MillSection], *, now: dt.datetime,
                stale_days: float = 14.0) -> dict[str, Any]:
    """The ``report --json`` document: per mill, each element's and bearing's status.

    Parameters
    ----------
    sections : sequence of MillSection
    now : datetime
        The report's date (aware, UTC).
    stale_days : float
        A mill whose last recording is older than this is flagged ``stale``.

    Returns
    -------
    dict
        ``{"generated": ISO time, "mills": {name: {"last_recording", "data_age_days",
        "stale", "n_recordings", "n_failed", "elements": {...}, "bearings": {...}}}}``
        (cli.md ``report --json``).
    """
    now_ns = int(now.timestamp() * 1e9)
    mills: dict[str, Any] = {}
    for s in sections:
        age = (now_ns - s.t_last_ns) / DAY_NS if s.t_last_ns else math.nan
        m: dict[str, Any] = {"last_recording": _iso_time(s.t_last_ns),
                             "data_age_days": _num(round(age, 2)) if math.isfinite(age) else None,
                             "stale": bool(math.isfinite(age) and age > stale_days),
                             "n_recordings": s.n_done, "n_failed": s.n_failed,
                             "elements": {}, "bearings": {}}
        for a in s.assessments:
            m["elements" if a.kind == "element" else "bearings"][a.id] = part_status(a, s, now_ns)
        if s.mill is not None:  # every part of the mill file appears, unknown without evidence
            for kind, parts in (("elements", s.mill.elements), ("bearings", s.mill.bearings)):
                for p in parts:
                    m[kind].setdefault(p.id, {"status": "unknown",
                                              "reason": "no evidence: nothing stored for it",
                                              "now": None, "n_identified": 0,
                                              "n_recordings": s.n_done, "source": None})
        mills[s.name] = m
    return {"generated": now.astimezone(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "stale_days": stale_days, "mills": mills}
