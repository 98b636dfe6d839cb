"""Render report sections as one self-contained HTML page (inline CSS, embedded PNGs).

No script, no font, no style sheet and no image is fetched from anywhere: the
file opens the same from a mail attachment, a file share or a browser offline.
"""

from __future__ import annotations

import datetime as dt
import html
import math
from typing import Sequence

import pandas as pd

from .build import Assessment, MillSection
from .figures import STATUS_COLORS
from .trend import Crossing

__all__ = ["render"]

_CSS = """
body{font-family:-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;margin:0;
     color:#212121;background:#fafafa;line-height:1.4}
header{background:#263238;color:#fff;padding:14px 28px}
header h1{margin:0 0 4px 0;font-size:22px}
header p{margin:0;font-size:13px;color:#cfd8dc}
main{padding:8px 28px 40px 28px;max-width:1180px}
nav{font-size:13px;margin:10px 0}
nav a{margin-right:14px}
section.mill{background:#fff;border:1px solid #e0e0e0;border-radius:6px;padding:4px 20px 18px;
     margin:18px 0}
h2{font-size:20px;margin:14px 0 2px} h3{font-size:16px;margin:22px 0 6px;
     border-bottom:1px solid #eceff1;padding-bottom:3px}
p.meta{color:#546e7a;font-size:13px;margin:2px 0 10px}
.headline{font-size:15px;padding:10px 14px;border-radius:5px;margin:8px 0 4px;
     border-left:6px solid #9e9e9e;background:#f5f5f5}
table{border-collapse:collapse;font-size:13px;margin:6px 0}
th,td{border-bottom:1px solid #e0e0e0;padding:4px 9px;text-align:left;vertical-align:top}
th{background:#eceff1;font-weight:600}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.light{display:inline-block;min-width:78px;padding:2px 8px;border-radius:10px;color:#fff;
     font-weight:600;font-size:12px;text-align:center}
img{max-width:100%;height:auto;display:block;margin:6px 0}
.note{color:#546e7a;font-size:12.5px;max-width:980px}
.err{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12px;white-space:pre-wrap}
details{margin:6px 0}
"""

_FAR_DAYS = 3652.5
_ORDER = {"critical": 0, "worn": 1, "unknown": 2, "good": 3}


def _e(x: object) -> str:
    return html.escape("" if x is None else str(x))


def _date(t_ref_ns: int, days: float) -> str:
    if not math.isfinite(days):
        return "open"
    if abs(days) > _FAR_DAYS:
        return "beyond 10 years" if days > 0 else "–"
    return (dt.datetime.fromtimestamp(t_ref_ns / 1e9, dt.timezone.utc)
            + dt.timedelta(days=days)).strftime("%d %b %Y")


def _fmt(x: float, digits: int = 2) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _light(status: str) -> str:
    return (f'<span class="light" style="background:{STATUS_COLORS.get(status, "#9e9e9e")}">'
            f"{_e(status.upper())}</span>")


def _forecast(a: Assessment, c: Crossing | None, limit: float, t_ref: int) -> str:
    if math.isfinite(a.now) and a.now >= limit:
        when = c.t if c is not None and c.trend and math.isfinite(c.t) else (
            a.worn_reached if limit == a.worn else a.critical_reached)
        return f"<b>crossed</b> {_date(t_ref, when)}" if math.isfinite(when) else "<b>crossed</b>"
    if c is None:
        return "too few recordings for a trend" if a.n < 3 else "–"
    if not c.trend:
        return "not rising (no forecast)"
    if c.t > _FAR_DAYS:
        return "not within 10 years"
    return (f"<b>{_date(t_ref, c.t)}</b><br><span class='note'>95 %: "
            f"{_date(t_ref, c.t_early)} – {_date(t_ref, c.t_late)}</span>")


def _days_words(d: float | None) -> str:
    if d is None or not math.isfinite(d):
        return "no end"
    if d > _FAR_DAYS:
        return "more than 10 years"
    if d < 1.0:
        return "less than a day"
    return f"{d:.0f} day" + ("" if round(d) == 1 else "s")


def life_words(part: dict | None) -> str:
    """Remaining life of one part of the status JSON (:mod:`ident.report.status`) in plain words."""
    if not part or part.get("status") == "unknown":
        return "not known: no evidence"
    limit = part.get("next_limit")
    if part.get("critical_reached") or part.get("status") == "critical":
        since = part.get("critical_at")
        return "critical limit reached" + (f" ({since})" if since else "") + ": act now"
    days = part.get("days_left")
    if days is None:
        return f"no rising trend: no date for the {limit} limit"
    ci = part.get("days_left_ci95")
    band = ""
    if ci is not None and ci[0] is not None:
        band = f" (95 %: {_days_words(ci[0])} to {_days_words(ci[1])})"
    if days <= 0:  # the trend crossed it between the last recording and the report
        when = part.get(f"{limit}_at")
        return (f"{limit} limit probably reached since the last recording"
                + (f", on {when} by the trend" if when else "") + ": check now")
    if days > _FAR_DAYS:
        return f"more than 10 years to the {limit} limit"
    return f"about {_days_words(days)} to the {limit} limit{band}"


def _evidence(a: Assessment) -> str:
    if a.kind == "bearing":
        return f"{a.n_identified} of {a.n_recordings} diagnosed"
    txt = f"{a.n_identified} of {a.n_recordings} identified"
    if a.n_rejected:
        txt += f"<br><span class='note'>{a.n_rejected} fit(s) not identified</span>"
    if a.source == "diagnosis":
        txt += "<br><span class='note'>value from the wear diagnosis</span>"
    return txt


def _glance(s: MillSection, status: dict | None = None) -> str:
    if not s.assessments:
        return "<p class='note'>No identified gaps or clearances stored for this mill.</p>"
    parts = (status or {}).get("mills", {}).get(s.name, {})
    rows = []
    for a in sorted(s.assessments, key=lambda a: (a.kind != "element", _ORDER[a.status], a.id)):
        part = parts.get("elements" if a.kind == "element" else "bearings", {}).get(a.id)
        now = (f"{_fmt(a.now)} <span class='note'>({_fmt(a.now_lo)} – {_fmt(a.now_hi)})</span>"
               if math.isfinite(a.now_lo) else _fmt(a.now))
        trend = "–" if not math.isfinite(a.slope_per_30d) else (
            f"{a.slope_per_30d:+.3f}" + ("" if a.p_increasing < 0.05 else
                                         " <span class='note'>(not significant)</span>"))
        last = _date(s.t_ref_ns, a.t_last) if math.isfinite(a.t_last) else "–"
        rows.append(
            f"<tr><td>{_light(a.status)}</td><td><b>{_e(a.id)}</b> {_e(a.label)}<br>"
            f"<span class='note'>{_e(a.reason)}</span></td>"
            f"<td class='num'>{now} <span class='note'>{_e(a.unit)}</span></td>"
            f"<td class='num'>{_fmt(a.worn)} / {_fmt(a.critical)}</td>"
            f"<td class='num'>{trend}</td>"
            f"<td><b>{_e(life_words(part))}</b></td>"
            f"<td>{_forecast(a, a.worn_at, a.worn, s.t_ref_ns)}</td>"
            f"<td>{_forecast(a, a.critical_at, a.critical, s.t_ref_ns)}</td>"
            f"<td>{_e(a.classifier or '–')}"
            f"{' <span class=note>(uncertain)</span>' if a.classifier_uncertain else ''}"
            f"</td><td>{last}</td><td>{_evidence(a)}</td></tr>")
    return ("<table><tr><th>status</th><th>element / bearing</th><th>now (95 %)</th>"
            "<th>worn / critical limit</th><th>trend per 30 days</th><th>remaining life</th>"
            "<th>worn limit</th><th>critical limit</th><th>latest verdict</th>"
            "<th>last data</th><th>evidence</th></tr>"
            + "".join(rows) + "</table>"
            "<p class='note'>Values in mm (gaps at the element's radius where it has one, "
            "else mrad at the motor shaft; bearing clearances in mm). <i>now</i> is the "
            "trend line at the last recording with its 95 % confidence band (or the last "
            "value when fewer than three recordings). Remaining life counts from this "
            "report's date to the next limit the trend reaches, with Fieller's 95 % "
            "interval; no date when the values are not significantly rising (one-sided "
            "p ≥ 0.05). Fits that did not identify a gap are left out of the trend.</p>")


def _headline(s: MillSection) -> str:
    by = {k: [a for a in s.assessments if a.status == k] for k in _ORDER}
    if not s.assessments:
        color, text = STATUS_COLORS["unknown"], "No wear results yet."
        q = s.tables.get("quality")
        why = set(q["kind"]) & {"stage_unavailable", "no_model"} if q is not None else set()
        if why:
            text += (" The gap fit or the wear diagnosis did not run for these recordings "
                     "(see <i>Data quality</i>: " + ", ".join(sorted(why)) + ").")
    elif by["critical"]:
        color = STATUS_COLORS["critical"]
        text = "Act now: " + "; ".join(f"<b>{_e(a.id)}</b> {_e(a.label)} — {_e(a.reason)}"
                                       for a in by["critical"])
    elif by["worn"]:
        color = STATUS_COLORS["worn"]
        text = "Plan maintenance: " + "; ".join(
            f"<b>{_e(a.id)}</b> {_e(a.label)} — {_e(a.reason)}" for a in by["worn"])
    elif not by["good"]:
        color = STATUS_COLORS["unknown"]
        text = ("No element's or bearing's wear state is known: no fit identified a gap "
                "and no wear diagnosis is stored (see the trend panels and "
                "<i>Data quality</i>).")
    else:
        color = STATUS_COLORS["good"]
        text = "All elements and bearings below their worn limits, no limit expected within " \
               "the horizon."
        if by["unknown"]:
            text = (f"{len(by['good'])} of {len(s.assessments)} elements and bearings below "
                    "their worn limits, no limit expected within the horizon; the others' "
                    "state is unknown.")
    counts = ", ".join(f"{len(by[k])} {k}" for k in ("critical", "worn", "good", "unknown")
                       if by[k])
    n_rej = sum(a.n_rejected for a in s.assessments if a.kind == "element")
    n_fit = n_rej + sum(a.n_identified for a in s.assessments if a.kind == "element")
    if n_rej:
        counts += (f" · {n_rej} of {n_fit} element fits did not identify their gap "
                   "(hollow points, left out of the trends)")
    return (f'<div class="headline" style="border-left-color:{color}">{text}'
            f'<br><span class="note">{counts}</span></div>')


#: Plain words for the codes the stages store (solver statuses, finding kinds, error types).
SOLVER_WORDS = {"Solve_Succeeded": "converged",
                "Solved_To_Acceptable_Level": "converged (to the acceptable tolerance)",
                "Stationary_At_Limit": "converged (cost stationary at the iteration limit)",
                "Maximum_Iterations_Exceeded": "stopped: iteration limit",
                "Maximum_CpuTime_Exceeded": "stopped: time limit",
                "Maximum_WallTime_Exceeded": "stopped: time limit",
                "Infeasible_Problem_Detected": "failed: no feasible solution",
                "Restoration_Failed": "failed: restoration phase",
                "Error_In_Step_Computation": "failed: step computation",
                "Invalid_Number_Detected": "failed: invalid number",
                "(none)": "no solver status"}
FINDING_WORDS = {"no_model": "no trained wear model (diagnosis skipped)",
                 "stage_unavailable": "stage not installed (skipped)",
                 "no_absolute_time": "no absolute time in the file (file date used)",
                 "dropout": "telemetry dropout", "gap": "gap in the samples",
                 "clipping": "signal clipped", "flatline": "flat (stuck) signal",
                 "n_found": "transients found",
                 "refit_from_neighbour": "refitted from a neighbouring recording's gaps"}
ERROR_WORDS = {"RecordingError": "bad recording", "MillFileError": "bad mill file",
               "FitError": "the fit failed", "IdentError": "could not be processed",
               "MemoryError": "out of memory", "WorkerCrashed": "the worker process died"}


def plain(code: object, words: dict[str, str]) -> str:
    """Plain words for a stored code: the table's, else the code with its underscores as spaces."""
    if code is None or (isinstance(code, float) and math.isnan(code)):
        return ""
    c = str(code)
    if c in words:
        return words[c]
    if c.startswith("warning:"):
        return "warning (" + c.split(":", 1)[1].replace("Warning", "").strip() + ")"
    return c.replace("_", " ").lower() if c.replace("_", "").isalnum() and "_" in c else c


def _plain_quality(df: pd.DataFrame | None) -> pd.DataFrame | None:
    if df is None or df.empty:
        return df
    return df.assign(kind=[plain(k, FINDING_WORDS) for k in df["kind"]]).rename(
        columns={"kind": "finding"})


def _plain_solver(df: pd.DataFrame | None) -> pd.DataFrame | None:
    if df is None or df.empty:
        return df
    col = "solver_status"
    return df.assign(**{col: [plain(k, SOLVER_WORDS) for k in df[col]]}).rename(
        columns={col: "solver"})


def _plain_failed(df: pd.DataFrame | None) -> pd.DataFrame | None:
    if df is None or df.empty:
        return df
    return pd.DataFrame({"file": df["file_name"], "stage": df["stage"],
                         "what": [plain(k, ERROR_WORDS) for k in df["error_kind"]],
                         "why": df["error"], "processed": df["processed"]})


def _table(df: pd.DataFrame, *, num: Sequence[str] = (), err: Sequence[str] = (),
           limit: int = 300) -> str:
    if df is None or df.empty:
        return "<p class='note'>None.</p>"
    head = "".join(f"<th>{_e(c)}</th>" for c in df.columns)
    body = []
    for _, row in df.head(limit).iterrows():
        cells = []
        for c in df.columns:
            v = row[c]
            if c in num:
                cells.append(f"<td class='num'>{_fmt(float(v), 3) if pd.notna(v) else '–'}</td>")
            elif c in err:
                cells.append(f"<td class='err'>{_e(v)}</td>")
            else:
                cells.append(f"<td>{_e('' if pd.isna(v) else v)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    more = (f"<p class='note'>… and {len(df) - limit} more (see the store).</p>"
            if len(df) > limit else "")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>{more}"


def _img(uri: str | None, alt: str) -> str:
    return f'<img src="{uri}" alt="{_e(alt)}">' if uri else \
        f"<p class='note'>No data for {_e(alt)}.</p>"


def _age(s: MillSection, status: dict | None) -> str:
    """Last recording's date, the data's age at the report's date and a stale warning."""
    m = (status or {}).get("mills", {}).get(s.name)
    if not m or m.get("data_age_days") is None:
        return ""
    age = m["data_age_days"]
    last = _date(s.t_ref_ns, (s.t_last_ns - s.t_ref_ns) / 864e11)
    txt = f"Last recording {last}, {_days_words(max(age, 0.0))} before this report."
    if m.get("stale"):
        return (f"<p class='headline' style='border-left-color:{STATUS_COLORS['worn']}'>"
                f"<b>Stale data:</b> {_e(txt)} The states below describe the mill as it was "
                f"then; more than {status.get('stale_days', 14):g} days without a new "
                "recording.</p>")
    return f"<p class='meta'>{_e(txt)}</p>"


def _section(s: MillSection, status: dict | None = None) -> str:
    sid = "mill-" + "".join(ch if ch.isalnum() else "-" for ch in s.name)
    period = (f"{_date(s.t_ref_ns, 0)} – {_date(s.t_ref_ns, (s.t_last_ns - s.t_ref_ns) / 864e11)}"
              if s.t_ref_ns else "no dated recordings")
    desc = f" — {_e(s.mill.description)}" if s.mill is not None and s.mill.description else ""
    parts = [f'<section class="mill" id="{sid}"><h2>Mill {_e(s.name)}{desc}</h2>',
             f"<p class='meta'>Recordings {period} · {s.n_done} processed · "
             f"{s.n_failed} failed · {s.n_transients} transients ({s.n_bites} bites)</p>",
             _headline(s), _age(s, status)]
    if "mill" in s.notes:
        parts.append(f"<p class='note'>{_e(s.notes['mill'])}</p>")
    parts.append(f"<h3>At a glance</h3>{_glance(s, status)}")
    parts.append("<h3>Gap trend per element</h3>" + _img(s.figures.get("gaps"), "gap trends") +
                 "<p class='note'>Each point is one recording's identified gap with its 95 % "
                 "interval; hollow points are fits that did not identify the gap (left out "
                 "of the trend); the line and shaded band are the weighted linear trend and its "
                 "95 % confidence band; dashed lines are the worn (amber) and critical (red) "
                 "limits of the mill file; a vertical line and shading mark when the trend "
                 "reaches a limit and its 95 % interval. The frame colour is the status.</p>")
    taf_el = s.notes.get("taf_element", "")
    parts.append(f"<h3>TAF against static torque (seed Fig. 4), {_e(taf_el)}</h3>" +
                 _img(s.figures.get("taf"), "TAF against static torque") +
                 "<p class='note'>Measured at every bite: peak torque within 1 s after the "
                 "bite and the bar's static rolling torque, both reduced to the motor shaft; "
                 "colour is the recording date. With wear in the gaps the TAF grows, most at "
                 "low static torque (seed section 1.1).</p>" +
                 _table(s.tables.get("taf"), num=("median", "p95", "max")))
    parts.append("<h3>Natural-frequency amplitude and phase</h3>" +
                 _img(s.figures.get("modes"), "amplitude and phase trends") +
                 "<p class='note'>Spectral amplitude of the measured torque at each natural "
                 "frequency relative to the linear baseline, and the phase shift (seed "
                 "section 2.1: the 20 Hz amplitude and phase are the most wear-sensitive; "
                 "after about 2.5 mm of spindle wear A45 falls below A20).</p>")
    parts.append("<h3>Bearing clearance trend</h3>" +
                 _img(s.figures.get("bearings"), "bearing clearance trends"))
    parts.append("<h3>Data quality</h3>" +
                 "<p class='note'>Findings of the readers and warnings of the stages, by kind "
                 "(recordings affected and channels named).</p>" +
                 _table(_plain_quality(s.tables.get("quality"))) +
                 "<p class='note'>Solver status of the gap fits (normalized RMS error of the "
                 "fitted model):</p>" +
                 _table(_plain_solver(s.tables.get("solver")),
                        num=("median nrmse", "worst nrmse")) +
                 (f"<p class='note'>Fits worse than the linear baseline: "
                  f"{_e(s.notes['worse_than_linear'])}.</p>"
                  if "worse_than_linear" in s.notes else ""))
    failed = s.tables.get("failed")
    parts.append(f"<h3>Failed recordings ({0 if failed is None else len(failed)})</h3>" +
                 _table(_plain_failed(failed), err=("why",)))
    parts.append("</section>")
    return "".join(parts)


def render(sections: Sequence[MillSection], *, runs: pd.DataFrame, title: str, store: str,
           now: dt.datetime, status: dict | None = None) -> str:
    """The report page for ``sections`` (see :func:`ident.report.build_report`)."""
    nav = ""
    if len(sections) > 1:
        nav = "<nav>Mills: " + "".join(
            f'<a href="#mill-{"".join(c if c.isalnum() else "-" for c in s.name)}">'
            f"{_e(s.name)}</a>" for s in sections) + "</nav>"
    body = "".join(_section(s, status) for s in sections) or \
        "<p>The store holds no recordings yet. Run <code>ident campaign</code> first.</p>"
    run_tab = ""
    if runs is not None and len(runs):
        r = runs.tail(10)[["id", "started_at", "finished_at", "status", "mill_name", "executor",
                           "n_found", "n_skipped", "n_done", "n_failed"]].copy()
        for c in ("started_at", "finished_at"):
            r[c] = pd.to_datetime(r[c]).dt.strftime("%Y-%m-%d %H:%M:%S")
        r = r.rename(columns={"id": "run", "started_at": "started (UTC)",
                              "finished_at": "finished (UTC)", "mill_name": "mill",
                              "executor": "ran on", "n_found": "found", "n_skipped":
                              "already stored", "n_done": "stored", "n_failed": "failed"})
        run_tab = ("<h3>Last campaign runs</h3>" + _table(r.iloc[::-1]))
    return (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>"
        f"<header><h1>{_e(title)}</h1><p>Generated {now:%d %b %Y %H:%M} UTC from "
        f"{_e(store)} · {len(sections)} mill(s)</p></header><main>{nav}{body}"
        f"{run_tab}</main></body></html>\n")
