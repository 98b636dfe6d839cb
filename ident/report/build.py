"""Assemble the wear trend report of a results store, one section per mill.

:func:`analyse_mill` turns a mill's stored results (DataFrames of
:func:`ident.store.load_results`) into plain values: per element and bearing a
trend, its forecasts and a traffic-light status; :func:`build_report` renders
those into one self-contained HTML file (:mod:`ident.report.html`).

Status of an element or bearing (the traffic light)
---------------------------------------------------
The evidence is, per recording, the gap the fit *identified* (its verdict
``identified``), else the wear verdict stored in ``diagnoses`` (the trained
model's regressed gap or clearance, :mod:`ident.diagnose.verdict`).  Fits the
fit itself rejected (not identified) are drawn hollow and left out of the trend;
the headline counts them.

The *current value* is the trend line at the last recording when three or more
recordings give a trend, otherwise the last value.

* ``critical`` (red): the current value is at or above the critical limit, or the
  latest verdict says ``critical``.
* ``worn`` (amber): the current value is at or above the worn limit, the latest
  verdict says ``worn``, or the 95 % interval of the time the trend reaches a
  limit begins within ``horizon_days`` of the last recording.

Where fits identified an element's gap, the values are those gaps and the
verdicts of the trained model do not change its status (they are shown).
Where the values are the trained model's own (a bearing, or an element no fit
identified) and they give a trend, the latest verdict counts only when it is
confident (not ``uncertain``): an uncertain verdict is one noisy recording of the
trend the status already reads (campaign study: a bearing at 1.26 mm by its
trend, worn limit 1.0 and critical 1.8, was called critical from its last
recording alone, regressed at 2.1 mm with probability 0.57).
* ``good`` (green): none of these.  ``unknown`` (grey): no evidence at all (no
  identified fit and no verdict).

Limits are the mill file's ``gap_worn``/``gap_critical`` (elements, rad reduced,
shown in mm where the element has a ``radius``, else mrad) and
``clearance_worn``/``clearance_critical`` (bearings, m, shown in mm).
"""

from __future__ import annotations

import datetime as dt
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
import numpy as np
import pandas as pd

from ..description import Mill
from ..io.millfile import load_mill, parse_mill
from ..store import Store, load_results
from . import figures as F
from .trend import Crossing, crossing, fit_trend

__all__ = ["Assessment", "Evidence", "MillSection", "ReportSummary", "analyse_mill", "build_report"]

DAY_NS = 86_400 * 10**9
_Z95 = 1.959963984540054


@dataclass(frozen=True)
class Assessment:
    """Trend, forecast and status of one element's gap or one bearing's clearance.

    Attributes
    ----------
    kind : {'element', 'bearing'}
    id, label : str
    unit : str
        Display unit of the values below (``mm`` or ``mrad``).
    status : str
        ``good``, ``worn``, ``critical`` or ``unknown``.
    reason : str
        Why, in a few words.
    now, now_lo, now_hi : float
        Current value and its 95 % interval (NaN when unknown).
    worn, critical : float
        Limits.
    slope_per_30d : float
        Trend slope per 30 days (NaN without a trend).
    p_increasing : float
        One-sided p-value of the trend rising.
    worn_at, critical_at : Crossing or None
        When the trend reaches each limit, in days since :attr:`MillSection.t_ref_ns`.
    classifier : str or None
        Latest state from the wear diagnosis.
    classifier_uncertain : bool
        That latest state was ``uncertain`` (then it does not override a trend).
    n : int
        Recordings behind the trend (identified fits, or verdicts without them).
    identifiable : bool
        False when no fit identified the element's gap.
    scale : float
        Display unit per SI unit (``now * / scale`` is rad or m).
    source : str
        ``fit`` (identified gaps), ``diagnosis`` (the trained model's verdicts) or
        ``""`` (no evidence).
    n_identified, n_rejected, n_recordings : int
        Fits that identified the gap, fits that did not, and the mill's processed
        recordings.
    t_last : float
        Days since :attr:`MillSection.t_ref_ns` of the last evidence (NaN without).
    worn_reached, critical_reached : float
        Day of the first evidence at or above each limit (NaN when none is).
    """

    kind: str
    id: str
    label: str
    unit: str
    status: str
    reason: str
    now: float
    now_lo: float
    now_hi: float
    worn: float
    critical: float
    slope_per_30d: float
    p_increasing: float
    worn_at: Crossing | None
    critical_at: Crossing | None
    classifier: str | None
    n: int
    identifiable: bool = True
    scale: float = 1.0
    source: str = ""
    classifier_uncertain: bool = False
    n_identified: int = 0
    n_rejected: int = 0
    n_recordings: int = 0
    t_last: float = math.nan
    worn_reached: float = math.nan
    critical_reached: float = math.nan


@dataclass(frozen=True)
class MillSection:
    """Everything the report shows about one mill."""

    name: str
    mill: Mill | None
    t_ref_ns: int
    t_last_ns: int
    n_done: int
    n_failed: int
    n_transients: int
    n_bites: int
    assessments: tuple[Assessment, ...]
    figures: dict[str, str] = field(default_factory=dict)
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class ReportSummary:
    """What :func:`build_report` wrote.

    Attributes
    ----------
    path : Path
    mills : tuple of str
    n_recordings, n_failed : int
    assessments : tuple of (str, Assessment)
        ``(mill name, assessment)`` for every element and bearing.
    elapsed_s : float
    status : dict
        The ``report --json`` document (:func:`ident.report.status.status_json`).
    json_path : Path or None
        Where it was written.
    """

    path: Path
    mills: tuple[str, ...]
    n_recordings: int
    n_failed: int
    assessments: tuple[tuple[str, Assessment], ...]
    elapsed_s: float
    status: dict = field(default_factory=dict)
    json_path: Path | None = None


# ---- analysis -----------------------------------------------------------------------
def _days(t0_ns: pd.Series, t_ref_ns: int) -> np.ndarray:
    return (t0_ns.astype("float64").to_numpy() - t_ref_ns) / DAY_NS


def _status(now: float, worn: float, critical: float, classifier: str | None,
            worn_at: Crossing | None, crit_at: Crossing | None, t_last: float,
            horizon: float) -> tuple[str, str]:
    if not math.isfinite(now) and classifier is None:
        return "unknown", "no evidence: no identified fit and no diagnosis"
    if math.isfinite(now) and now >= critical:
        return "critical", "above the critical limit"
    if classifier == "critical":
        return "critical", "diagnosed critical"
    if math.isfinite(now) and now >= worn:
        return "worn", "above the worn limit"
    if classifier == "worn":
        return "worn", "diagnosed worn"
    for c, name in ((crit_at, "critical"), (worn_at, "worn")):
        if c is not None and c.trend and math.isfinite(c.t_early) and \
                c.t_early <= t_last + horizon:
            return "worn", f"may reach the {name} limit within {horizon:.0f} days"
    return "good", "below the limits"


@dataclass(frozen=True)
class Evidence:
    """One element's or bearing's values over a mill's recordings, in display units.

    ``t`` days since the report's reference time, ``y`` the value and ``lo, hi``
    its 95 % interval (NaN where unknown); ``rejected_*`` the fits that did not
    identify the gap (drawn, never trended); ``n_bounded`` of the verdicts, those
    whose gap and interval came from a fit that bounded the gap (the fit's
    interval wider than an identified gap's, :mod:`ident.fit.verdict`).
    """

    t: np.ndarray
    y: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    source: str
    n_identified: int = 0
    n_bounded: int = 0
    rejected_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rejected_y: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _first_at_or_above(t: np.ndarray, y: np.ndarray, limit: float,
                       lo: np.ndarray | None = None) -> float:
    """Day of the first value at or above ``limit``; with ``lo``, of the first whose 95 %
    interval is (the first value at or above it when none is)."""
    if lo is not None:
        sure = _first_at_or_above(t, lo, limit)
        if math.isfinite(sure):
            return sure
    hit = np.isfinite(t) & np.isfinite(y) & (y >= limit)
    return float(np.min(t[hit])) if hit.any() else math.nan


def _assess(kind: str, id_: str, label: str, unit: str, ev: Evidence, worn: float,
            critical: float, classifier: str | None, horizon: float, *, scale: float = 1.0,
            n_recordings: int = 0, quantity: str = "", classifier_uncertain: bool = False,
            ) -> tuple[Assessment, F.GapPanel]:
    days, y, lo, hi = ev.t, ev.y, ev.lo, ev.hi
    sigma = (hi - lo) / (2 * _Z95)
    ok = np.isfinite(days) & np.isfinite(y)
    tr = fit_trend(days[ok], y[ok], sigma=sigma[ok]) if ok.sum() >= 2 else None
    trend = tr if tr is not None and tr.n >= 3 else None
    w_at = crossing(trend, worn) if trend is not None else None
    c_at = crossing(trend, critical) if trend is not None else None
    if trend is not None:
        t_last = trend.t_last
        now = float(trend.predict(t_last))
        blo, bhi = trend.band(t_last)
        now_lo, now_hi = float(blo), float(bhi)
    elif ok.any():
        i = int(np.argmax(np.where(ok, days, -np.inf)))
        t_last, now, now_lo, now_hi = float(days[i]), float(y[i]), float(lo[i]), float(hi[i])
    else:
        t_last, now, now_lo, now_hi = math.nan, math.nan, math.nan, math.nan
    # identified gaps are the most accurate evidence: where fits identified the gap,
    # the trained model's verdicts are shown but do not decide the status
    fitted = ev.source == "fit"
    decisive = None if (fitted and ok.any()) or (trend is not None and classifier_uncertain) \
        else classifier
    status, reason = _status(now, worn, critical, decisive, w_at, c_at,
                             t_last if math.isfinite(t_last) else 0.0, horizon)
    if status == "unknown" and ev.rejected_t.size:
        reason = f"no evidence: the {ev.rejected_t.size} fit(s) did not identify the gap"
    n_rej = int(ev.rejected_t.size)
    # the trained model's values scatter (plant bearings: about 0.4 mm per recording), and
    # one of them above a limit is no crossing: the first whose interval is above it is
    noisy_lo = None if fitted else lo
    a = Assessment(kind=kind, id=id_, label=label, unit=unit, status=status, reason=reason,
                   now=now, now_lo=now_lo, now_hi=now_hi, worn=worn, critical=critical,
                   slope_per_30d=30.0 * trend.slope if trend is not None else math.nan,
                   p_increasing=trend.p_increasing if trend is not None else math.nan,
                   worn_at=w_at, critical_at=c_at, classifier=classifier,
                   classifier_uncertain=classifier_uncertain, n=int(ok.sum()),
                   identifiable=ev.n_identified > 0 or kind == "bearing", scale=scale,
                   source=ev.source if ok.any() or classifier is not None else "",
                   n_identified=ev.n_identified, n_rejected=n_rej, n_recordings=n_recordings,
                   t_last=t_last, worn_reached=_first_at_or_above(days, y, worn, noisy_lo),
                   critical_reached=_first_at_or_above(days, y, critical, noisy_lo))
    title = f"{id_}" + (f" — {label}" if label else "") + f"  [{status.upper()}]"
    note = ""
    if kind == "element" and ev.source == "diagnosis" and ok.any() and ev.n_bounded:
        note = (f"no fit identified the gap; {ev.n_bounded} fit(s) bounded it (95 % interval "
                "wider than an identified gap's), the wear diagnosis gives the rest")
    elif kind == "element" and ev.source == "diagnosis" and ok.any():
        note = "gap regressed by the wear diagnosis (no fit identified it)"
    elif not ok.any() and n_rej:
        note = "no fit identified the gap: hollow points for reference only"
    panel = F.GapPanel(title=title, unit=unit, t=days[ok], y=y[ok], lo=lo[ok], hi=hi[ok],
                       worn=worn, critical=critical, trend=trend, worn_at=w_at,
                       critical_at=c_at, status=status, horizon=horizon, note=note,
                       rejected_t=ev.rejected_t, rejected_y=ev.rejected_y, quantity=quantity,
                       evidence=("identified (95 % CI)" if fitted else
                                 "diagnosed (95 % interval)"))
    return a, panel


def _latest_state(diag: pd.DataFrame, kind: str, target: str) -> tuple[str | None, bool]:
    """The latest stored verdict's state of a target and whether it was ``uncertain``."""
    d = diag[(diag["kind"] == kind) & (diag["target"] == target) & diag["state"].notna()]
    if d.empty:
        return None, False
    last = d.sort_values(["t0_ns", "recording_pk"]).iloc[-1]
    unc = last.get("uncertain")
    return str(last["state"]), bool(pd.notna(unc) and unc)


def _col(d: pd.DataFrame, name: str) -> np.ndarray:
    return d[name].to_numpy(float) if name in d else np.full(len(d), np.nan)


def _element_evidence(er: pd.DataFrame, diag: pd.DataFrame, eid: str, t_ref: int,
                      f: float) -> Evidence:
    """Identified fits of one element, else its verdicts' gaps; rejected fits apart."""
    d = er[er["element"] == eid].sort_values("t0_ns")
    verdict = d["identifiable"]
    # rows of an older store carry no verdict (NULL): they count as identified
    rejected = d[verdict.notna() & (verdict == False)]  # noqa: E712 - a nullable column
    good = d[~d.index.isin(rejected.index)]
    rej_t, rej_y = _days(rejected["t0_ns"], t_ref), rejected["gap"].to_numpy(float) * f
    if not good.empty:
        return Evidence(t=_days(good["t0_ns"], t_ref), y=good["gap"].to_numpy(float) * f,
                        lo=good["gap_ci_lo"].to_numpy(float) * f,
                        hi=good["gap_ci_hi"].to_numpy(float) * f, source="fit",
                        n_identified=len(good), rejected_t=rej_t, rejected_y=rej_y)
    v = diag[(diag["kind"] == "element") & (diag["target"] == eid)
             & diag["gap"].notna()].sort_values("t0_ns")
    # a verdict from a fit that bounded the gap carries that fit's gap: it is in the
    # trend, not also a hollow point
    bounded = v["source"].eq("fit") if "source" in v else pd.Series(False, index=v.index)
    keep = ~rejected["recording_pk"].isin(v.loc[bounded, "recording_pk"])
    return Evidence(t=_days(v["t0_ns"], t_ref), y=v["gap"].to_numpy(float) * f,
                    lo=_col(v, "value_ci_lo") * f, hi=_col(v, "value_ci_hi") * f,
                    source="diagnosis", n_bounded=int(bounded.sum()),
                    rejected_t=rej_t[keep.to_numpy()], rejected_y=rej_y[keep.to_numpy()])


def _bearing_evidence(diag: pd.DataFrame, bid: str, t_ref: int) -> Evidence:
    v = diag[(diag["kind"] == "bearing") & (diag["target"] == bid)
             & diag["clearance"].notna()].sort_values("t0_ns")
    return Evidence(t=_days(v["t0_ns"], t_ref), y=v["clearance"].to_numpy(float) * 1e3,
                    lo=_col(v, "value_ci_lo") * 1e3, hi=_col(v, "value_ci_hi") * 1e3,
                    source="diagnosis", n_identified=len(v))


def _mill_of(name: str, recs: pd.DataFrame, mills: pd.DataFrame,
             given: Mill | None) -> Mill | None:
    if given is not None and given.name == name:
        return given
    shas = recs["mill_sha256"].tolist()
    texts = dict(zip(mills["sha256"], mills["text"]))
    for sha in reversed(shas):
        if sha in texts:
            return parse_mill(texts[sha], path=f"<store: mill file {sha[:12]}>")
    return None


def analyse_mill(name: str, res: dict[str, pd.DataFrame], *, mill: Mill | None = None,
                 horizon_days: float = 30.0, figures: bool = True) -> MillSection:
    """Trends, forecasts, statuses, tables and figures of one mill's results.

    Parameters
    ----------
    name : str
        Mill name as stored.
    res : dict of DataFrame
        :func:`ident.store.load_results` output.
    mill : Mill, optional
        The description for the limits; default the mill file stored with the
        latest recording.
    horizon_days : float
        Look-ahead of the amber status and of the plotted trend, days.
    figures : bool
        Render the plots (False for tests of the numbers only).
    """
    def of(df: pd.DataFrame) -> pd.DataFrame:
        return df[df["mill_name"] == name]

    recs = of(res["recordings"]).copy()
    done = recs[recs["status"] == "done"]
    failed = recs[recs["status"] == "failed"]
    mill = _mill_of(name, recs, res["mills"], mill)
    t0s = recs["t0_ns"].dropna()
    t_ref = int(t0s.min()) if len(t0s) else 0
    t_last = int(t0s.max()) if len(t0s) else 0
    done_pk = set(done["id"])
    er = of(res["element_results"])
    er = er[er["transient_idx"].isna() & er["recording_pk"].isin(done_pk)]
    er = er.merge(recs[["id", "t0_ns"]].rename(columns={"id": "recording_pk"}), on="recording_pk")
    diag = of(res["diagnoses"]).merge(recs[["id", "t0_ns"]].rename(columns={"id": "recording_pk"}),
                                      on="recording_pk")
    tr = of(res["transients"])
    assessments: list[Assessment] = []
    panels: list[F.GapPanel] = []
    bpanels: list[F.GapPanel] = []
    figs: dict[str, str] = {}
    notes: dict[str, str] = {}
    tables: dict[str, pd.DataFrame] = {}

    if mill is not None:
        for e in mill.elements:
            f, unit = (e.gap_mm(1.0), "mm") if e.radius else (1e3, "mrad")
            ev = _element_evidence(er, diag, e.id, t_ref, f)
            cls, unc = _latest_state(diag, "element", e.id)
            if not ev.t.size and not ev.rejected_t.size and cls is None:
                continue
            quantity = (f"gap at r = {e.radius:g} m" if e.radius else
                        "gap (motor shaft)")
            a, p = _assess("element", e.id, e.label, unit, ev, e.gap_worn * f,
                           e.gap_critical * f, cls, horizon_days, scale=f,
                           n_recordings=len(done), quantity=quantity,
                           classifier_uncertain=unc)
            assessments.append(a)
            panels.append(p)
        for b in mill.bearings:
            ev = _bearing_evidence(diag, b.id, t_ref)
            cls, unc = _latest_state(diag, "bearing", b.id)
            if not ev.t.size and cls is None:
                continue
            a, p = _assess("bearing", b.id, f"bearing of {b.mesh}", "mm", ev,
                           b.clearance_worn * 1e3, b.clearance_critical * 1e3, cls,
                           horizon_days, scale=1e3, n_recordings=len(done),
                           quantity="radial clearance", classifier_uncertain=unc)
            assessments.append(a)
            bpanels.append(p)
    else:
        notes["mill"] = ("the mill file of these results is not in the store: limits and "
                         "trends are left out")
    rank = {"critical": 0, "worn": 1, "unknown": 3, "good": 2}
    panels.sort(key=lambda p: rank.get(p.status, 3))
    if figures and panels:
        figs["gaps"] = F.gap_trends(panels, t0_ns=t_ref)
    if figures and bpanels:
        figs["bearings"] = F.gap_trends(bpanels, t0_ns=t_ref)

    # TAF against static torque (seed Fig. 4), motor shaft first
    taf = of(res["taf"])
    taf = taf[taf["recording_pk"].isin(done_pk) & taf["taf"].notna()]
    if not taf.empty:
        taf = taf.merge(recs[["id", "t0_ns"]].rename(columns={"id": "recording_pk"}),
                        on="recording_pk")
        motor_side = [e.id for e in mill.elements if e.from_ == mill.motor.mass] if mill else []
        present = list(taf["element"].value_counts().index)
        el = next((e for e in motor_side if e in present), present[0])
        d = taf[taf["element"] == el]
        if figures:
            figs["taf"] = F.taf_vs_static(d["static_torque"].to_numpy(float) / 1e3,
                                          d["peak_torque"].to_numpy(float) / 1e3,
                                          d["taf"].to_numpy(float), _days(d["t0_ns"], t_ref),
                                          t0_ns=t_ref, element=el)
        notes["taf_element"] = el
        g = taf.groupby("element")["taf"]
        tables["taf"] = pd.DataFrame({"bites": g.size(), "median": g.median(),
                                      "p95": g.quantile(0.95), "max": g.max()}).reset_index()

    # natural-frequency amplitude and phase trends
    ft = of(res["features"])
    ft = ft[ft["recording_pk"].isin(done_pk) & ft["transient_idx"].isna()]
    if not ft.empty and {"amplitude_ratio", "phase_shift_deg"} & set(ft["name"]):
        ft = ft.merge(recs[["id", "t0_ns"]].rename(columns={"id": "recording_pk"}),
                      on="recording_pk")
        wide = ft.pivot_table(index=["recording_pk", "t0_ns", "idx"], columns="name",
                              values="value", aggfunc="first").reset_index()
        series = []
        for idx, d in wide.groupby("idx"):
            fr = d["frequencies_hz"].median() if "frequencies_hz" in d else math.nan
            lab = f"{fr:.0f} Hz" if math.isfinite(fr) else f"mode {int(idx) + 1}"
            amp = d["amplitude_ratio"].to_numpy(float) if "amplitude_ratio" in d else \
                np.full(len(d), np.nan)
            ph = d["phase_shift_deg"].to_numpy(float) if "phase_shift_deg" in d else \
                np.full(len(d), np.nan)
            series.append((lab, _days(d["t0_ns"], t_ref), amp, ph))
        if figures:
            figs["modes"] = F.mode_trends(series, t0_ns=t_ref)

    # data quality, solver status, failures
    q = of(res["quality_issues"])
    if not q.empty:
        g = q.groupby("kind")
        tables["quality"] = pd.DataFrame({
            "findings": g.size(), "recordings": g["recording_pk"].nunique(),
            "channels": g["channel"].agg(lambda s: ", ".join(sorted(set(s.dropna())))[:120]),
        }).reset_index().sort_values("findings", ascending=False)
    fits = of(res["fits"])
    fits = fits[fits["transient_idx"].isna()]
    if not fits.empty:
        g = fits.groupby(fits["solver_status"].fillna("(none)"))
        tables["solver"] = pd.DataFrame({"fits": g.size(), "median nrmse": g["nrmse"].median(),
                                         "worst nrmse": g["nrmse"].max()}).reset_index()
        worse = fits[fits["nrmse"] > fits["nrmse_linear"]]
        notes["worse_than_linear"] = str(len(worse))
    tables["failed"] = failed.assign(
        processed=pd.to_datetime(failed["finished_at"]).dt.strftime("%Y-%m-%d %H:%M"))[
        ["file_name", "stage", "error_kind", "error", "processed"]].sort_values("file_name")
    return MillSection(name=name, mill=mill, t_ref_ns=t_ref, t_last_ns=t_last,
                       n_done=len(done), n_failed=len(failed), n_transients=len(tr),
                       n_bites=int((tr["kind"] == "bite").sum()) if len(tr) else 0,
                       assessments=tuple(assessments), figures=figs, tables=tables, notes=notes)


def _safe_url(store: str | Store) -> str:
    if isinstance(store, Store):
        return store.url
    import sqlalchemy as sa

    from ..store.store import normalize_url

    return sa.engine.make_url(normalize_url(store)).render_as_string(hide_password=True)


def build_report(store: str | Store, out: str | Path, *, mill: Mill | str | Path | None = None,
                 horizon_days: float = 30.0, title: str = "Driveline wear trend report",
                 now: dt.datetime | None = None, json_out: str | Path | None = None,
                 stale_days: float = 14.0) -> ReportSummary:
    """Write the wear trend report of a results store as one self-contained HTML file.

    Parameters
    ----------
    store : str or Store
        SQLAlchemy URL of an existing store, or an open store.
    out : path
        The HTML file to write (folders are created; written atomically).
    mill : Mill or path, optional
        Report only this mill, with the limits of this description.
    horizon_days : float
        Look-ahead of the amber status, days.
    title : str
    now : datetime, optional
        "Generated at" time, the date days left are counted from (default: now, UTC).
    json_out : path, optional
        Also write each part's status here (cli.md ``report --json``).
    stale_days : float
        Data older than this many days at ``now`` is flagged stale.

    Returns
    -------
    ReportSummary

    Raises
    ------
    StoreError
        The store does not exist or cannot be read.
    MillFileError
        ``mill`` is a path to a bad mill file.
    """
    import json

    from .html import render
    from .status import status_json

    t_start = time.perf_counter()
    if mill is not None and not isinstance(mill, Mill):
        mill = load_mill(mill)
    res = load_results(store, mill=mill.name if mill is not None else None)
    names = sorted(res["recordings"]["mill_name"].unique()) if len(res["recordings"]) else []
    sections = [analyse_mill(n, res, mill=mill, horizon_days=horizon_days) for n in names]
    now = now or dt.datetime.now(dt.timezone.utc)
    status = status_json(sections, now=now, stale_days=stale_days)
    html = render(sections, runs=res["runs"], title=title, store=_safe_url(store), now=now,
                  status=status)
    out = Path(out)
    _write_atomic(out, html)
    json_path = None
    if json_out is not None:
        json_path = Path(json_out)
        _write_atomic(json_path, json.dumps(status, indent=2) + "\n")
    recs = res["recordings"]
    return ReportSummary(path=out, mills=tuple(names), n_recordings=len(recs),
                         n_failed=int((recs["status"] == "failed").sum()) if len(recs) else 0,
                         assessments=tuple((s.name, a) for s in sections for a in s.assessments),
                         elapsed_s=time.perf_counter() - t_start, status=status,
                         json_path=json_path)


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
