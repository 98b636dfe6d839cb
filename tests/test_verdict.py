"""One wear verdict per element and bearing: the fit's identified gap first, the trained model otherwise."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from ident.diagnose import (Diagnosis, TargetDiagnosis, diagnosis_json, fit_verdicts,
                            state_probabilities, verdicts)


def _td(state: str, size: float, *, p: float = 0.8, uncertain: bool = False) -> TargetDiagnosis:
    probs = {"good": 0.1, "worn": 0.1, "critical": 0.1}
    probs[state] = p
    tot = sum(probs.values())
    probs = {k: v / tot for k, v in probs.items()}
    return TargetDiagnosis(state=state, probability=probs[state], probabilities=probs,
                           size=size, interval=(size * 0.8, size * 1.2), observable=True,
                           uncertain=uncertain, novelty=0.5)


def _diagnosis(mill, element_state: str = "good", bearing_state: str = "worn") -> Diagnosis:
    return Diagnosis(elements={e.id: _td(element_state, 0.002) for e in mill.elements},
                     bearings={b.id: _td(bearing_state, 1.2e-3) for b in mill.bearings},
                     warnings=("out of range",))


def _fit(mill, **identified: tuple[float, float, float]) -> dict:
    """A cli.md fit JSON: the named elements identified at (gap, lo, hi), the rest not."""
    els = {}
    for e in mill.elements:
        if e.id in identified:
            g, lo, hi = identified[e.id]
            els[e.id] = {"gap": g, "gap_ci95": [lo, hi], "identified": True}
        else:
            els[e.id] = {"gap": 0.0123, "gap_ci95": [0.0, 0.02], "identified": False,
                         "reason": "interval wider than the gap"}
    return {"mill": mill.name, "elements": els}


# ---- state probabilities from an interval -------------------------------------------
def test_symmetric_interval_is_a_normal():
    # gap 5 mrad, 95 % half-width 1.96 mrad -> sigma 1 mrad; limits 4 and 8 mrad
    p = state_probabilities(5e-3, (5e-3 - 1.96e-3, 5e-3 + 1.96e-3), (4e-3, 8e-3))
    assert p["good"] == pytest.approx(stats.norm.cdf(-1.0), abs=1e-4)
    assert p["critical"] == pytest.approx(stats.norm.sf(3.0), abs=1e-5)
    assert sum(p.values()) == pytest.approx(1.0)


def test_split_normal_mass_matches_sampling():
    """Each side of the interval is its own half normal, weighted so the density is continuous."""
    value, lo, hi = 6e-3, 5e-3, 9e-3
    s_lo, s_hi = (value - lo) / 1.959964, (hi - value) / 1.959964
    rng = np.random.default_rng(0)
    n = 400_000
    side = rng.random(n) < s_lo / (s_lo + s_hi)
    x = np.where(side, value - np.abs(rng.normal(0, s_lo, n)), value + np.abs(rng.normal(0, s_hi, n)))
    p = state_probabilities(value, (lo, hi), (4e-3, 8e-3))
    assert p["good"] == pytest.approx(np.mean(x <= 4e-3), abs=3e-3)
    assert p["critical"] == pytest.approx(np.mean(x > 8e-3), abs=3e-3)
    # the interval really is a 95 % one of that distribution
    assert np.mean((x >= lo) & (x <= hi)) == pytest.approx(0.95, abs=3e-3)


def test_zero_width_and_missing_interval_is_certain():
    assert state_probabilities(9e-3, (9e-3, 9e-3), (4e-3, 8e-3))["critical"] == 1.0
    assert state_probabilities(2e-3, (math.nan, math.nan), (4e-3, 8e-3))["good"] == 1.0
    # an estimate a rounding error outside its own interval counts as zero width there
    p = state_probabilities(5e-3, (5.0001e-3, 7e-3), (4e-3, 8e-3))
    assert p["good"] == 0.0 and p["worn"] > 0.9


# ---- where a verdict comes from -------------------------------------------------------
def test_identified_gap_decides_over_the_model(mill):
    fit = _fit(mill, C46=(9.0e-3, 8.7e-3, 9.3e-3), C12=(2.0e-3, 1.8e-3, 2.2e-3))
    els, brs = verdicts(mill, _diagnosis(mill, "good"), fit=fit)
    assert list(els) == [e.id for e in mill.elements]  # the mill file's order
    assert els["C46"].state == "critical" and els["C46"].source == "fit"
    assert els["C46"].probability > 0.99 and not els["C46"].uncertain
    assert els["C46"].value == 9.0e-3 and els["C46"].ci95 == (8.7e-3, 9.3e-3)
    assert els["C46"].diagnosis is not None and els["C46"].diagnosis.state == "good"
    assert els["C12"].state == "good" and els["C12"].source == "fit"
    # not identified: the model's state, with the fit's reason
    assert els["C23"].source == "diagnosis" and els["C23"].state == "good"
    assert els["C23"].reason == "interval wider than the gap"
    assert els["C23"].value == 0.002
    # bearings always from the diagnosis (accelerometers)
    assert set(brs) == {b.id for b in mill.bearings}
    assert all(v.source == "diagnosis" and v.state == "worn" for v in brs.values())


def test_fit_alone_gives_verdicts_only_where_it_identified(mill):
    fit = _fit(mill, C46=(5e-3, 4.5e-3, 5.5e-3))
    els, brs = verdicts(mill, None, fit=fit)
    assert set(els) == {"C46"} and els["C46"].state == "worn" and brs == {}
    assert set(fit_verdicts(mill, fit)) == {"C46"}
    assert verdicts(mill, None, fit=None) == ({}, {})
    # an identified flag without a finite gap is no evidence
    bad = _fit(mill)
    bad["elements"]["C46"] = {"gap": None, "identified": True}
    assert fit_verdicts(mill, bad) == {}


def test_a_bounded_gap_gives_the_state_not_the_value(mill):
    """A gap the fit bounds (its interval trusted, wider than an identified gap's) decides the
    state from its interval, says it is not identified and why; a gap neither identified nor
    bounded leaves the state to the model."""
    fit = _fit(mill)
    why = "its 95 % interval (+-1.80 mrad) is wider than max(10 %, 0.3 mrad)"
    fit["elements"]["C23"] = {"gap": 9.1e-3, "gap_ci95": [7.3e-3, 10.9e-3], "identified": False,
                              "bounded": True, "reason": why}
    els, _ = verdicts(mill, _diagnosis(mill, "good"), fit=fit)
    c23, e = els["C23"], mill.element("C23")
    assert e.gap_worn < 7.3e-3 and e.gap_critical < 9.1e-3  # the case is as meant
    assert c23.source == "fit" and not c23.identified and c23.reason == why
    assert c23.state == "critical" and c23.probabilities == pytest.approx(
        state_probabilities(9.1e-3, (7.3e-3, 10.9e-3), (e.gap_worn, e.gap_critical)))
    assert els["C46"].source == "diagnosis"  # neither: the model's
    block = diagnosis_json(mill, _diagnosis(mill, "good"), fit=fit)["elements"]["C23"]
    assert block["source"] == "fit" and block["identified"] is False and block["reason"] == why
    fit["elements"]["C23"]["bounded"] = False
    assert verdicts(mill, _diagnosis(mill, "good"), fit=fit)[0]["C23"].source == "diagnosis"


def test_model_alone(mill):
    els, brs = verdicts(mill, _diagnosis(mill, "worn"))
    assert all(v.source == "diagnosis" and v.state == "worn" and v.reason == ""
               for v in els.values())
    assert len(brs) == len(mill.bearings)


def test_uncertain_follows_the_diagnosis_or_the_probability(mill):
    d = _diagnosis(mill)
    d.elements["C23"] = _td("good", 0.002, p=0.9, uncertain=True)
    # a gap at the worn limit with a wide interval: about even odds
    fit = _fit(mill, C46=(4.0e-3, 2.0e-3, 6.0e-3))
    els, _ = verdicts(mill, d, fit=fit)
    assert els["C23"].uncertain
    assert els["C46"].uncertain and els["C46"].probability < 0.6


# ---- the diagnose JSON -----------------------------------------------------------------
def test_diagnosis_json_blocks(mill):
    fit = _fit(mill, C46=(9.0e-3, 8.7e-3, 9.3e-3))
    out = diagnosis_json(mill, _diagnosis(mill), fit=fit, features={"frequencies_hz": [12.0]},
                         warnings=("w2",))
    c46 = out["elements"]["C46"]
    assert c46["state"] == "critical" and c46["source"] == "fit" and c46["identified"]
    assert c46["gap"] == 9.0e-3 and c46["gap_ci95"] == [8.7e-3, 9.3e-3]
    assert c46["gap_mm"] == pytest.approx(mill.element("C46").gap_mm(9.0e-3))
    assert c46["diagnosis"]["state"] == "good"  # what the model said, for comparison
    c23 = out["elements"]["C23"]
    assert c23["source"] == "diagnosis" and c23["reason"] == "interval wider than the gap"
    assert {"novelty", "explanations", "probabilities", "observable"} <= set(c23)
    b = out["bearings"]["B23"]
    assert b["state"] == "worn" and b["source"] == "diagnosis"
    assert b["clearance"] == 1.2e-3 and b["clearance_mm"] == pytest.approx(1.2)
    assert out["features"] == {"frequencies_hz": [12.0]}
    assert out["warnings"] == ["out of range", "w2"]


def test_diagnosis_json_of_the_fit_alone(mill):
    out = diagnosis_json(mill, None, fit=_fit(mill, C46=(3e-3, 2.8e-3, 3.2e-3)))
    assert list(out["elements"]) == ["C46"] and out["bearings"] == {}
    assert out["elements"]["C46"]["state"] == "good" and out["warnings"] == []


# ---- ident diagnose --fit ---------------------------------------------------------------
def test_read_fit_refuses_what_is_no_fit_of_this_mill(mill, tmp_path):
    import json

    from ident.cli.diagnose import read_fit
    from ident.errors import IdentError

    with pytest.raises(IdentError, match="fit result not found: .*nope.json"):
        read_fit(tmp_path / "nope.json", mill)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(IdentError, match="bad.json: not a fit result \\(JSON of 'ident fit'\\)"):
        read_fit(tmp_path / "bad.json", mill)
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(IdentError, match="needs an 'elements' object"):
        read_fit(tmp_path / "list.json", mill)
    (tmp_path / "other.json").write_text(json.dumps({"mill": "cold-s5", "elements": {}}))
    with pytest.raises(IdentError, match="the fit is of mill 'cold-s5', not of 'hsm-f1'"):
        read_fit(tmp_path / "other.json", mill)
    (tmp_path / "ok.json").write_text(json.dumps(_fit(mill, C46=(9e-3, 8.7e-3, 9.3e-3))))
    assert read_fit(tmp_path / "ok.json", mill)["elements"]["C46"]["identified"]


@pytest.fixture(scope="module")
def worn_case(mill, mill_path, tmp_path_factory):
    """A 2-bar recording with C46 critical (10 mrad) and a tiny model (12 simulated
    recordings) that decides nothing reliably."""
    from ident.cli import main
    from ident.diagnose import save_model, simulate_library, train_model

    d = tmp_path_factory.mktemp("worn")
    rec = d / "worn.mcap"
    assert main(["simulate", "--mill", str(mill_path), "--out", str(rec), "--bars", "2",
                 "--seed", "4", "--set", "C46.gap=0.010", "--set", "C46.gap_open=0.010",
                 "--quiet"]) == 0
    lib = simulate_library(mill, n=12, random_state=11, bearings=True)
    return rec, save_model(train_model(lib, mill, random_state=0, max_iter=30), d / "m.joblib")


@pytest.mark.slow
def test_cli_diagnose_takes_the_fits_identified_gap(mill, mill_path, worn_case, tmp_path):
    """The tiny model decides nothing reliably; the fit's gap does."""
    import json

    from ident.cli import main

    rec, model = worn_case
    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps(_fit(mill, C46=(0.0099, 0.0095, 0.0103))))
    out = tmp_path / "d.json"
    assert main(["diagnose", str(rec), "--mill", str(mill_path), "--model", str(model),
                 "--fit", str(fit), "--out", str(out), "--quiet"]) == 0
    d = json.loads(out.read_text())
    assert d["elements"]["C46"]["state"] == "critical" and d["elements"]["C46"]["source"] == "fit"
    assert d["elements"]["C46"]["gap"] == 0.0099
    assert {v["source"] for k, v in d["elements"].items() if k != "C46"} == {"diagnosis"}
    assert d["elements"]["C23"]["reason"] == "interval wider than the gap"
    assert set(d["bearings"]) == {"B23", "B45"}
    assert all(v["source"] == "diagnosis" for v in d["bearings"].values())
    assert len(d["features"]["frequencies_hz"]) == 6 and d["transients"]["bites"] == 2
    fit_block = d["fit"]
    assert {k: fit_block[k] for k in ("source", "path", "identified")} == \
        {"source": "file", "path": str(fit), "identified": ["C46"]}
    # the fit's evidence on every element, what it did not identify too
    assert fit_block["elements"]["C46"] == {"gap": 0.0099, "gap_ci95": [0.0095, 0.0103],
                                            "identified": True, "bounded": False}
    assert fit_block["elements"]["C23"] == {"gap": 0.0123, "gap_ci95": [0.0, 0.02],
                                            "identified": False, "bounded": False,
                                            "reason": "interval wider than the gap"}


class _FakeFit:
    def __init__(self, doc: dict) -> None:
        self.doc = doc

    def to_dict(self) -> dict:
        return self.doc


@pytest.mark.slow
def test_cli_diagnose_runs_the_fit_itself(mill, mill_path, worn_case, tmp_path, monkeypatch,
                                          capsys):
    """Without --fit, diagnose fits the recording's windows (its budget passed on) and the
    identified gap decides; a fit that cannot run is one warning and the model decides;
    --no-fit runs no fit."""
    import json

    import ident.fit.recording
    from ident.cli import main
    from ident.errors import FitError

    rec, model = worn_case
    calls, starts = [], []

    def fake_fit(mill_, windows, **kw):
        calls.append((len(windows), kw["time_budget_s"]))
        starts.append(kw.get("data_starts"))
        doc = _fit(mill, C46=(0.0099, 0.0095, 0.0103))
        return _FakeFit(dict(doc, solver={"seconds": 12.5, "path": "data"}))

    monkeypatch.setattr(ident.fit.recording, "fit_gaps", fake_fit)
    out = tmp_path / "d.json"
    base = ["diagnose", str(rec), "--mill", str(mill_path), "--model", str(model),
            "--out", str(out)]
    assert main(base + ["--fit-budget", "77"]) == 0
    assert calls == [(4, 77.0)]  # 2 bars: 2 bites and 2 releases
    assert "fitting the gaps (up to 77 s" in capsys.readouterr().err
    d = json.loads(out.read_text())
    assert {k: d["fit"][k] for k in ("source", "seconds", "identified", "solver_path")} == \
        {"source": "run", "seconds": 12.5, "identified": ["C46"], "solver_path": "data"}
    assert set(d["fit"]["elements"]) == set(mill.element_ids)
    # the fit restarts from the trained model's gaps of the elements a channel sees
    measured = {eid for eid, v in d["elements"].items() if v.get("observable")}
    (start,) = starts[0]
    assert set(start) == measured and all(0.0 <= g < 0.03 for g in start.values())
    assert d["elements"]["C46"]["source"] == "fit" and d["elements"]["C46"]["state"] == "critical"

    def failing_fit(mill_, windows, **kw):
        raise FitError("no start converged")

    monkeypatch.setattr(ident.fit.recording, "fit_gaps", failing_fit)
    assert main(base) == 0
    assert "warning: the fit did not run (no start converged)" in capsys.readouterr().err
    d = json.loads(out.read_text())
    assert d["fit"] == {"source": None}
    assert {v["source"] for v in d["elements"].values()} == {"diagnosis"}
    assert any("the fit did not run (no start converged)" in w for w in d["warnings"])

    calls.clear()
    monkeypatch.setattr(ident.fit.recording, "fit_gaps", fake_fit)
    assert main(base + ["--no-fit", "--quiet"]) == 0
    assert calls == [] and json.loads(out.read_text())["fit"] == {"source": None}
    assert main(base + ["--fit-budget", "0"]) == 2
    assert "--fit-budget must be positive" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # argparse: one or the other
        main(base + ["--no-fit", "--fit", "x.json"])
    assert exc.value.code == 2


@pytest.mark.slow
def test_cli_fit_restarts_from_the_wear_models_gaps(mill, mill_path, worn_case, tmp_path,
                                                    monkeypatch):
    """``ident fit --model``: the trained model's gaps of the measured elements become the
    fit's data start; without --model there is none."""
    import ident.fit.recording
    from ident.cli import main
    from ident.errors import FitError

    rec, model = worn_case
    seen = []

    def fake_fit(mill_, windows, **kw):
        seen.append(kw.get("data_starts"))
        raise FitError("stop here")

    monkeypatch.setattr(ident.fit.recording, "fit_gaps", fake_fit)
    base = ["fit", str(rec), "--mill", str(mill_path), "--quiet"]
    assert main(base + ["--model", str(model)]) == 2
    assert main(base) == 2
    (start,), none = seen
    measured = {c.element for c in mill.torque_channels()}
    assert set(start) == measured and all(0.0 <= g < 0.03 for g in start.values())
    assert none == ()
