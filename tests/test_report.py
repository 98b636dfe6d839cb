"""The wear trend report: forecast math on known trends, statuses, the HTML file, the CLIs.

Stores are filled through the campaign runner with the TEST DOUBLE pipeline of
``test_campaign_doubles`` (cli.md-shaped dicts from a known truth).
"""

from __future__ import annotations

import base64
import functools
import math
import re

import numpy as np
import pytest

from ident.cli import main
from ident.report import analyse_mill, build_report, crossing, fit_trend
from ident.store import load_results, run_campaign

from test_campaign_doubles import double_process, make_double_campaign, write_double_recording


# ---- forecast math against known truth ----------------------------------------------
def test_noise_free_line_is_exact():
    t = np.array([0.0, 5.0, 10.0, 20.0])
    tr = fit_trend(t, 1.0 + 0.05 * t + np.array([1e-9, -1e-9, 1e-9, -1e-9]))
    assert tr.slope == pytest.approx(0.05, rel=1e-6)
    c = crossing(tr, 3.0)
    assert c.trend and c.t == pytest.approx(40.0, rel=1e-6)
    assert c.t_early == pytest.approx(40.0, rel=1e-4) and c.t_late == pytest.approx(40.0, rel=1e-4)


def test_slope_and_crossing_coverage_over_seeds():
    """Truth a=1 mm, b=0.02 mm/day, sigma=0.05 mm: the 95 % intervals cover ~95 % of seeds."""
    a, b, sd, limit = 1.0, 0.02, 0.05, 2.0
    t_true = (limit - a) / b  # 50 days
    t = np.linspace(0, 30, 12)
    cover_slope = cover_cross = 0
    n_seeds = 400
    for seed in range(n_seeds):
        rng = np.random.default_rng(seed)
        tr = fit_trend(t, a + b * t + rng.normal(0, sd, t.size), sigma=np.full(t.size, sd))
        se = math.sqrt(tr.cov[1, 1])
        from scipy import stats
        q = stats.t.ppf(0.975, tr.dof)
        cover_slope += abs(tr.slope - b) <= q * se
        c = crossing(tr, limit)
        assert c.trend
        cover_cross += c.t_early <= t_true <= c.t_late
    assert 0.92 <= cover_slope / n_seeds <= 0.98
    assert 0.92 <= cover_cross / n_seeds <= 0.98


def test_fieller_ends_are_where_the_band_meets_the_limit():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 20, 8)
    tr = fit_trend(t, 0.5 + 0.03 * t + rng.normal(0, 0.04, t.size))
    c = crossing(tr, 1.5)
    assert tr.band(c.t_early)[1] == pytest.approx(1.5, abs=1e-9)
    assert tr.band(c.t_late)[0] == pytest.approx(1.5, abs=1e-9)
    assert c.t_early < c.t < c.t_late


def test_no_trend_and_reached():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 30, 10)
    flat = fit_trend(t, 1.0 + rng.normal(0, 0.05, t.size))
    c = crossing(flat, 2.0)
    assert not c.trend and math.isnan(c.t) and not c.reached
    up = fit_trend(t, 1.0 + 0.1 * t)
    assert crossing(up, 2.0).reached
    assert fit_trend(np.array([1.0, 1.0]), np.array([1.0, 2.0])) is None


def test_weights_follow_the_intervals():
    t = np.array([0.0, 10.0, 20.0, 30.0])
    y = np.array([1.0, 1.2, 1.4, 5.0])  # last point an outlier with a huge interval
    tr = fit_trend(t, y, sigma=np.array([0.01, 0.01, 0.01, 100.0]))
    assert tr.slope == pytest.approx(0.02, rel=1e-3)


# ---- statuses on a store ------------------------------------------------------------
@pytest.fixture(scope="module")
def store(tmp_path_factory, mill):
    d = tmp_path_factory.mktemp("report")
    make_double_campaign(d / "c", n=10, bad=2, days=40, growth_per_day=6e-5)
    url = f"sqlite:///{d}/r.db"
    run_campaign(d / "c", mill, url, workers=0, process=double_process, progress=False)
    return url


def test_statuses_and_forecasts(store, mill):
    sec = analyse_mill("hsm-f1", load_results(store), figures=False)
    a = {x.id: x for x in sec.assessments}
    # C46 grows 0.002 -> 0.0044 rad: above the 0.004 rad worn limit at the end, rising
    c46 = a["C46"]
    assert c46.status == "worn" and c46.unit == "mm"
    f = mill.element("C46").gap_mm(1.0)
    assert c46.worn == pytest.approx(0.004 * f) and c46.critical == pytest.approx(0.008 * f)
    assert c46.slope_per_30d == pytest.approx(30 * 6e-5 * f, rel=0.25)
    true_crit_day = (0.008 - 0.002) / 6e-5  # 100 days
    assert c46.critical_at.t_early <= true_crit_day <= c46.critical_at.t_late
    assert a["C12"].status == "good"
    assert {x.kind for x in sec.assessments} == {"element", "bearing"}
    assert sec.n_failed == 2 and len(sec.tables["failed"]) == 2
    assert sec.notes["taf_element"] == "C12"  # the motor shaft, as in seed Fig. 4


def test_critical_status(tmp_path, mill):
    for i in range(4):
        write_double_recording(tmp_path / "c" / f"r{i}.mcap", day=i, seed=i,
                               gaps={"C57": 0.0085})
    url = f"sqlite:///{tmp_path}/r.db"
    run_campaign(tmp_path / "c", mill, url, workers=0, process=double_process, progress=False)
    sec = analyse_mill("hsm-f1", load_results(url), figures=False)
    c57 = next(x for x in sec.assessments if x.id == "C57")
    assert c57.status == "critical" and "critical" in c57.reason


def test_gap_trend_from_the_diagnosis_without_fits(tmp_path, mill):
    for i in range(4):
        write_double_recording(tmp_path / "c" / f"r{i}.mcap", day=7 * i, seed=i, no_fit=True,
                               gaps={"C46": 0.002 + 0.0005 * i})
    url = f"sqlite:///{tmp_path}/r.db"
    run_campaign(tmp_path / "c", mill, url, workers=0, process=double_process, progress=False)
    assert load_results(url)["element_results"].empty
    sec = analyse_mill("hsm-f1", load_results(url), figures=False)
    c46 = next(x for x in sec.assessments if x.id == "C46")
    assert c46.n == 4 and c46.slope_per_30d == pytest.approx(
        30 * 0.0005 / 7 * mill.element("C46").gap_mm(1.0), rel=0.3)


# ---- the HTML file ------------------------------------------------------------------
def test_report_is_one_self_contained_file(store, tmp_path):
    r = build_report(store, tmp_path / "out" / "report.html")
    text = r.path.read_text()
    for heading in ("At a glance", "Gap trend per element", "TAF against static torque",
                    "Natural-frequency amplitude and phase", "Bearing clearance trend",
                    "Data quality", "Failed recordings (2)"):
        assert heading in text
    imgs = re.findall(r'<img src="([^"]+)"', text)
    assert len(imgs) == 4 and all(s.startswith("data:image/png;base64,") for s in imgs)
    for s in imgs:
        assert base64.b64decode(s.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    # nothing fetched from anywhere: no external URL, script, link or import
    refs = re.findall(r'(?:src|href)\s*=\s*["\']([^"\']*)', text, re.I)
    assert refs and all(v.startswith(("data:", "#")) for v in refs)
    assert not re.search(r"(https?://|<script|<link|<iframe|@import|url\()", text, re.I)
    assert "truncated or corrupt MCAP" in text and "broken1.mcap" in text
    assert "Plan maintenance" in text and "C46" in text
    assert r.n_recordings == 12 and r.n_failed == 2


def test_empty_store_and_cli(tmp_path, store):
    from ident.store import open_store
    url = f"sqlite:///{tmp_path}/empty.db"
    open_store(url).close()
    assert main(["report", "--store", url, "--out", str(tmp_path / "e.html"), "--quiet"]) == 0
    assert "no recordings yet" in (tmp_path / "e.html").read_text()
    assert main(["report", "--store", f"sqlite:///{tmp_path}/missing.db",
                 "--out", str(tmp_path / "m.html")]) == 2


def test_campaign_cli_exit_codes(tmp_path, mill_path, monkeypatch, capsys):
    import ident.store

    monkeypatch.setattr(ident.store, "run_campaign",
                        functools.partial(run_campaign, process=double_process))
    good, bad = tmp_path / "good", tmp_path / "bad"
    make_double_campaign(good, n=2, bad=0)
    make_double_campaign(bad, n=2, bad=1)
    base = ["--mill", str(mill_path), "--workers", "0", "--quiet"]
    url = f"sqlite:///{tmp_path}/r.db"
    assert main(["campaign", str(good), "--store", url, *base]) == 0
    assert main(["campaign", str(bad), "--store", url, *base]) == 3
    out = capsys.readouterr().out
    assert '"failed": 1' in out and "broken0.mcap" in out
    assert main(["campaign", str(bad), "--store", url, *base]) == 3  # rerun: still failed
    assert main(["campaign", str(tmp_path / "nope"), "--store", url, *base]) == 2
    assert main(["campaign", str(good), "--store", "nonsense", *base]) == 2
    assert main(["campaign", str(good), "--store", url, "--mill", str(tmp_path / "x.toml"),
                 "--workers", "0", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "campaign folder not found" in err and "Got 'nonsense'" in err
    assert "mill file not found" in err


def test_gap_panel_with_an_estimate_a_rounding_error_outside_its_interval():
    """A gap on its upper bound 1e-12 above the interval's end must not break the report."""
    from ident.report import figures as F

    t = np.array([0.0, 5.0, 10.0])
    y = np.array([4.0, 5.0, 30.0 + 1e-12])
    panel = F.GapPanel(title="C57", unit="mrad", t=t, y=y, lo=y - 0.5,
                       hi=np.array([4.5, 5.5, 30.0]), worn=4.0, critical=8.0, trend=None,
                       worn_at=None, critical_at=None, status="unknown", horizon=7.0, note="")
    html = F.gap_trends([panel], t0_ns=0)
    assert "<svg" in html or "data:image" in html


@pytest.mark.parametrize("statuses, says", [
    (["unknown"] * 6, "No element's or bearing's wear state is known"),
    (["good", "good", "unknown"], "2 of 3 elements and bearings below their worn limits"),
    (["good", "good"], "All elements and bearings below their worn limits"),
    (["good", "worn", "unknown"], "Plan maintenance"),
])
def test_headline_never_calls_unknown_states_good(statuses, says):
    from types import SimpleNamespace

    from ident.report.html import _headline

    sec = SimpleNamespace(assessments=[SimpleNamespace(status=st, id=f"E{i}", label="x",
                                                       reason="r", kind="element",
                                                       n_rejected=0, n_identified=1)
                                       for i, st in enumerate(statuses)], tables={})
    assert says in _headline(sec)


# ---- the status JSON (report --json) --------------------------------------------------
_NOW = __import__("datetime").datetime(2026, 2, 20, 6, 0, tzinfo=__import__("datetime").timezone.utc)


def test_status_json_per_part(store, mill, tmp_path):
    """The double store: C46 from 2 to 4.4 mrad over 40 days (6e-5 rad/day) from 1 Jan 2026."""
    import datetime as dt
    import json

    r = build_report(store, tmp_path / "r.html", json_out=tmp_path / "s.json", now=_NOW)
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc == json.loads(json.dumps(r.status)) and doc["generated"] == "2026-02-20T06:00:00Z"
    m = doc["mills"]["hsm-f1"]
    assert m["last_recording"].startswith("2026-02-10") and m["n_recordings"] == 10
    assert m["n_failed"] == 2 and m["data_age_days"] == pytest.approx(10.25, abs=0.01)
    assert m["stale"] is False
    assert set(m["elements"]) == {e.id for e in mill.elements}
    assert set(m["bearings"]) == {b.id for b in mill.bearings}
    c46 = m["elements"]["C46"]
    assert c46["status"] == "worn" and c46["source"] == "fit"
    # SI: rad, the truth at the last recording inside the 95 % band
    lo, hi = c46["now_ci95"]
    assert lo <= 0.002 + 6e-5 * 40 <= hi and lo < c46["now"] < hi
    assert c46["worn_limit"] == 0.004 and c46["critical_limit"] == 0.008
    assert c46["worn_reached"] and not c46["critical_reached"]
    # the worn limit was crossed around day 33 (3 Feb); the critical one is due at day 100
    worn_at = dt.date.fromisoformat(c46["worn_at"])
    assert abs((worn_at - dt.date(2026, 2, 3)).days) <= 4
    lo, hi = (dt.date.fromisoformat(x) for x in c46["critical_at_ci95"])
    assert lo <= dt.date(2026, 4, 11) <= hi
    assert c46["next_limit"] == "critical"
    true_left = (dt.date(2026, 4, 11) - _NOW.date()).days - 0.25  # 49.75 days
    d_lo, d_hi = c46["days_left_ci95"]
    assert d_lo <= true_left <= (d_hi if d_hi is not None else math.inf)
    assert c46["days_left"] == pytest.approx(true_left, rel=0.35)
    assert c46["n_identified"] == 10 and c46["n_rejected"] == 0 and c46["n_recordings"] == 10
    assert c46["last_recording"] == "2026-02-10"
    # C23: every fit rejected, the verdicts (the double's diagnosis) decide
    c23 = m["elements"]["C23"]
    assert c23["status"] == "good" and c23["source"] == "diagnosis"
    assert c23["n_identified"] == 0 and c23["n_rejected"] == 10
    assert m["bearings"]["B23"]["status"] == "good"
    assert m["bearings"]["B23"]["source"] == "diagnosis"


def test_stale_data_is_flagged(store, tmp_path):
    import datetime as dt

    r = build_report(store, tmp_path / "r.html", now=_NOW + dt.timedelta(days=30))
    assert r.status["mills"]["hsm-f1"]["stale"] is True
    assert "Stale data" in r.path.read_text()


def test_rejected_fits_are_left_out_of_the_trend(tmp_path, mill):
    """Every third fit of C46 is not identified and far off: the trend must not see it."""
    for i in range(9):
        rejected = i % 3 == 1  # the last recording (i = 8) is identified
        write_double_recording(tmp_path / "c" / f"r{i}.mcap", day=5 * i, seed=i,
                               gaps={"C46": 0.012 if rejected else 0.002 + 5e-5 * 5 * i},
                               identified=["C12", "C57"] if rejected else ["C12", "C46", "C57"])
    url = f"sqlite:///{tmp_path}/r.db"
    run_campaign(tmp_path / "c", mill, url, workers=0, process=double_process, progress=False)
    sec = analyse_mill("hsm-f1", load_results(url), figures=False)
    c46 = next(x for x in sec.assessments if x.id == "C46")
    f = mill.element("C46").gap_mm(1.0)
    assert c46.n_identified == 6 and c46.n_rejected == 3 and c46.n == 6
    assert c46.slope_per_30d == pytest.approx(30 * 5e-5 * f, rel=0.2)
    assert c46.now / f == pytest.approx(0.002 + 5e-5 * 40, abs=3e-4)
    assert c46.source == "fit" and c46.status != "critical"  # far below 8 mrad
    r = build_report(url, tmp_path / "r.html", now=_NOW)
    text = r.path.read_text()
    # C23, C34, C45 are never identified (27) and C46 three times: the headline counts them
    assert "30 of 54 element fits did not identify their gap" in text


def test_bounded_fits_give_the_trend_where_no_fit_identified_the_gap(tmp_path, mill,
                                                                    monkeypatch):
    """No fit identifies C46; two bounded it (their verdicts' source is the fit): those two
    are in the trend with the diagnosis' other verdicts and not also hollow points, the
    third unidentified fit is; the panel says so."""
    import sqlalchemy as sa

    from ident.store import schema as S

    for i in range(3):
        write_double_recording(tmp_path / "c" / f"r{i}.mcap", day=5 * i, seed=i,
                               identified=["C12", "C57"])
    url = f"sqlite:///{tmp_path}/r.db"
    run_campaign(tmp_path / "c", mill, url, workers=0, process=double_process, progress=False)
    d, r = S.diagnoses.c, S.recordings.c
    with sa.create_engine(url).begin() as c:
        first_two = c.execute(sa.select(r.id).order_by(r.t0_ns).limit(2)).scalars().all()
        c.execute(S.diagnoses.update().where((d.target == "C46")
                                             & d.recording_pk.in_(first_two))
                  .values(source="fit"))
    import ident.report.build as B
    drawn = []
    monkeypatch.setattr(B.F, "gap_trends", lambda panels, **kw: drawn.extend(panels) or "")
    sec = analyse_mill("hsm-f1", load_results(url), figures=True)
    c46 = next(x for x in sec.assessments if x.id == "C46")
    assert c46.source == "diagnosis" and c46.n_identified == 0 and c46.n == 3
    assert c46.n_rejected == 1  # the third: not bounded, hollow
    panel = next(p for p in drawn if p.title.startswith("C46"))
    assert panel.note.startswith("no fit identified the gap; 2 fit(s) bounded it")
    assert panel.rejected_t.size == 1


def test_unknown_only_without_evidence(tmp_path, mill):
    """C23's fits are all rejected and no diagnosis is stored: unknown, the others are not."""
    for i in range(3):
        write_double_recording(tmp_path / "c" / f"r{i}.mcap", day=i, seed=i)
    url = f"sqlite:///{tmp_path}/r.db"
    run_campaign(tmp_path / "c", mill, url, workers=0, process=double_process, progress=False)
    import sqlalchemy as sa

    from ident.store import schema as S

    with sa.create_engine(url).begin() as c:
        c.execute(S.diagnoses.delete())
    r = build_report(url, tmp_path / "r.html", now=_NOW)
    els = r.status["mills"]["hsm-f1"]["elements"]
    assert els["C23"]["status"] == "unknown" and els["C23"]["n_rejected"] == 3
    assert els["C23"]["days_left"] is None
    assert {els[e]["status"] for e in ("C12", "C46", "C57")} == {"good"}
    assert r.status["mills"]["hsm-f1"]["bearings"]["B23"]["status"] == "unknown"


def test_remaining_life_words():
    from ident.report.html import life_words

    assert life_words({"status": "unknown"}) == "not known: no evidence"
    assert life_words({"status": "critical", "critical_reached": True,
                       "critical_at": "2026-03-01"}).startswith("critical limit reached (2026-03-01)")
    assert life_words({"status": "good", "next_limit": "worn", "days_left": None}) == \
        "no rising trend: no date for the worn limit"
    assert life_words({"status": "worn", "next_limit": "critical", "days_left": 23.4,
                       "days_left_ci95": [12.0, None]}) == \
        "about 23 days to the critical limit (95 %: 12 days to no end)"
    assert life_words({"status": "worn", "next_limit": "critical", "days_left": 0.0,
                       "critical_at": "2026-03-01"}) == \
        "critical limit probably reached since the last recording, on 2026-03-01 by the trend: " \
        "check now"
    assert life_words({"status": "good", "next_limit": "worn", "days_left": 1.6e6}) == \
        "more than 10 years to the worn limit"


def test_report_cli_json(store, tmp_path):
    import json

    out = tmp_path / "st.json"
    assert main(["report", "--store", store, "--out", str(tmp_path / "r.html"),
                 "--json", str(out), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["mills"]["hsm-f1"]["elements"]["C46"]["status"] == "worn"


def test_plain_words_not_codes(store, tmp_path):
    text = build_report(store, tmp_path / "r.html", now=_NOW).path.read_text()
    assert "Solve_Succeeded" not in text and "converged" in text
    assert "RecordingError" not in text and "bad recording" in text
    assert "recording date (UTC)" not in text  # axis labels are inside the PNGs ...
    from ident.report import figures as F

    assert F.gap_trends  # ... and checked on the panels below


def test_gap_panel_axis_labels_and_range():
    from matplotlib.figure import Figure

    from ident.report import figures as F

    t = np.array([0.0, 5.0, 10.0])
    y = np.array([1.0, 1.5, 2.0])
    p = F.GapPanel(title="C46", unit="mm", t=t, y=y, lo=y - 0.1, hi=y + 0.1, worn=2.4,
                   critical=4.8, trend=None, worn_at=None, critical_at=None, status="good",
                   horizon=7.0, rejected_t=np.array([7.0]), rejected_y=np.array([30.0]),
                   quantity="gap at r = 0.5 m")
    lo, hi = F._y_range(p)
    assert lo == 0.0 and 4.8 < hi <= 2 * 4.8  # both limits shown, a wild rejected fit capped
    assert F._y_range(F.GapPanel(**{**p.__dict__, "y": np.array([1.0, 1.5, 7.0]),
                                    "hi": np.array([1.1, 1.6, 7.5])}))[1] >= 7.5


def test_identified_gaps_decide_over_the_models_verdicts(tmp_path, mill):
    """The model calls C46 (identified, good) critical and C23 (never identified) worn:
    the fit's gaps decide C46, the model decides C23."""
    import sqlalchemy as sa

    from ident.store import schema as S

    for i in range(4):
        write_double_recording(tmp_path / "c" / f"r{i}.mcap", day=i, seed=i)
    url = f"sqlite:///{tmp_path}/r.db"
    run_campaign(tmp_path / "c", mill, url, workers=0, process=double_process, progress=False)
    d = S.diagnoses.c
    with sa.create_engine(url).begin() as c:
        c.execute(S.diagnoses.update().where(d.target == "C46").values(state="critical"))
        c.execute(S.diagnoses.update().where(d.target == "C23").values(state="worn"))
    a = {x.id: x for x in analyse_mill("hsm-f1", load_results(url), figures=False).assessments}
    assert a["C46"].status == "good" and a["C46"].classifier == "critical"
    assert a["C23"].status == "worn" and a["C23"].reason == "diagnosed worn"


def test_an_uncertain_latest_verdict_does_not_override_the_trend(tmp_path, mill):
    """A bearing's clearances give a trend below the worn limit; its latest verdict says
    critical. Uncertain, that verdict is one noisy recording of the trend (status good);
    confident, it decides (critical)."""
    import sqlalchemy as sa

    from ident.store import schema as S

    for i in range(4):
        write_double_recording(tmp_path / "c" / f"r{i}.mcap", day=i, seed=i)
    url = f"sqlite:///{tmp_path}/r.db"
    run_campaign(tmp_path / "c", mill, url, workers=0, process=double_process, progress=False)
    d, r = S.diagnoses.c, S.recordings.c
    bid = mill.bearings[0].id
    with sa.create_engine(url).begin() as c:
        last = c.execute(sa.select(r.id).order_by(r.t0_ns.desc()).limit(1)).scalar_one()
        c.execute(S.diagnoses.update().where((d.target == bid) & (d.recording_pk == last))
                  .values(state="critical", uncertain=True))

    def assess():
        s = analyse_mill("hsm-f1", load_results(url), figures=False)
        return {x.id: x for x in s.assessments}[bid]

    a = assess()
    assert a.n >= 3 and a.now < a.worn
    assert a.classifier == "critical" and a.status == "good" and a.classifier_uncertain
    html = build_report(url, tmp_path / "r.html", now=_NOW).path.read_text()
    assert "critical <span class=note>(uncertain)</span>" in html
    with sa.create_engine(url).begin() as c:
        c.execute(S.diagnoses.update().where(d.target == bid).values(uncertain=False))
    a = assess()
    assert a.status == "critical" and a.reason == "diagnosed critical"


def test_a_noisy_value_above_a_limit_is_no_crossing():
    """The trained model's values scatter: the crossing is the first whose interval is above
    the limit (the first value above it only when no interval is)."""
    from ident.report.build import _first_at_or_above

    t = np.array([0.0, 3.0, 6.0, 9.0])
    y = np.array([1.2, 0.8, 1.1, 1.4])
    lo = y - 0.3
    assert _first_at_or_above(t, y, 1.0) == 0.0  # identified gaps: the first value
    assert _first_at_or_above(t, y, 1.0, lo) == 9.0
    assert _first_at_or_above(t, y, 1.3, lo) == 9.0  # no interval above: the first value
    assert math.isnan(_first_at_or_above(t, y, 2.0, lo))
