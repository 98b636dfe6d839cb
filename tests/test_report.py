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
                                                       reason="r")
                                       for i, st in enumerate(statuses)], tables={})
    assert says in _headline(sec)
