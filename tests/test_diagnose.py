"""Wear diagnosis end to end: library, model artefact, explanations, the CLI, and accuracy on
held-out simulated recordings (other seeds, static torques, nuisance draws)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ident.cli import main
from ident.diagnose import (describe_feature, diagnose_features, draw_sample, load_model,
                            model_cache_path, save_model, simulate_library, train_model)
from ident.diagnose.library import LibraryRanges, Nuisance, simulate_sample
from ident.diagnose.states import STATES, bearing_state, element_state
from ident.errors import ModelArtifactError
from ident.io import load_mill
from ident.model.dynamics import ModelOptions
from ident.model.simulate import simulate

#: library sizes of the accuracy test (simulated once per session)
N_TRAIN = 280
N_TEST = 100


# ---- session fixtures ----------------------------------------------------------------------

@pytest.fixture(scope="session")
def tiny_library(mill):
    """A dozen recordings with bearings: enough to train, save, load and explain."""
    return simulate_library(mill, n=12, random_state=11, bearings=True)


@pytest.fixture(scope="session")
def tiny_model(mill, tiny_library):
    return train_model(tiny_library, mill, random_state=0, max_iter=30)


@pytest.fixture(scope="session")
def accuracy_libraries(mill, tmp_path_factory):
    """Training and held-out libraries (different seeds), cached for the session."""
    import joblib

    d = tmp_path_factory.mktemp("libraries")
    jobs = 2 if (os.cpu_count() or 1) >= 2 else 1
    train = simulate_library(mill, n=N_TRAIN, random_state=101, n_jobs=jobs)
    test = simulate_library(mill, n=N_TEST, random_state=202, n_jobs=jobs)
    joblib.dump((train, test), d / "libraries.joblib")
    return train, test


@pytest.fixture(scope="session")
def accuracy_model(mill, accuracy_libraries):
    train, _ = accuracy_libraries
    return train_model(train, mill, random_state=0)


# ---- states and library --------------------------------------------------------------------

def test_states_follow_the_mill_limits(mill):
    e = mill.element("C46")
    assert element_state(e, 0.003).value == "good"
    assert element_state(e, 0.0041).value == "worn"
    assert element_state(e, 0.0081).value == "critical"
    b = mill.bearing("B23")
    assert bearing_state(b, 0.9e-3).value == "good"
    assert bearing_state(b, 1.5e-3).value == "worn"
    assert bearing_state(b, 2.0e-3).value == "critical"
    assert STATES == ("good", "worn", "critical")


def test_nuisance_effect_equals_a_stiffer_damper_mill(mill):
    """The stiffness/damping nuisance as model parameters = the mill file with k, c changed."""
    spec = draw_sample(mill, np.random.default_rng(0))
    e = mill.element("C46")
    m2 = mill.with_overrides({"C46.k": e.k * 1.08, "C46.c": e.c * 0.75})
    p = {"C46.gap": 0.006, "C46.gap_open": 0.003}
    r1 = simulate(m2, spec.scenario, options=ModelOptions(bearings=False), params=p)
    eff = Nuisance(("C46",))
    p2 = dict(p, **eff.params(mill, {"C46": 0.006}, {"C46": 0.003}, {"C46": 1.08},
                              {"C46": 0.75}))
    r2 = simulate(mill, spec.scenario, options=ModelOptions(bearings=False, effects=(eff,)),
                  params=p2)
    scale = np.abs(r1.outputs["tau:C46"]).max()
    assert np.abs(r1.outputs["tau:C46"] - r2.outputs["tau:C46"]).max() < 1e-6 * scale


def test_library_draws_few_faults_and_reproduces(mill, tiny_library):
    lib = tiny_library
    assert len(lib) == 12 and lib.mill_hash == mill.content_hash()
    for e in mill.elements:
        assert set(lib.truth[f"{e.id}.state"]) <= set(STATES)
        assert (lib.truth[f"{e.id}.gap_open"] <= lib.truth[f"{e.id}.gap"] + 1e-15).all()
        assert lib.truth[f"{e.id}.gap"].max() <= e.gap_critical * LibraryRanges().critical_span
    faulty = sum((lib.truth[f"{e.id}.state"] != "good").astype(int) for e in mill.elements)
    assert faulty.max() <= len(LibraryRanges().faults) - 1
    assert lib.truth["B23.clearance"].between(LibraryRanges().min_clearance, 3.0e-3).all()
    for f in ("bite.C46.A20.ratio", "bite.B23:v.f_peak", "release.C12.back04_sq.min",
              "bite.C46-C57.rise20_ms", "bite.near.peak", "release.B23:h.after.rate",
              "bite.idle_level"):
        assert f in lib.features, f
    rng = np.random.default_rng(5)
    a = draw_sample(mill, rng)
    b = draw_sample(mill, np.random.default_rng(5))
    assert a.gaps == b.gaps and a.scenario == b.scenario
    with pytest.raises(ValueError, match="'n' parameter of simulate_library must be >= 1"):
        simulate_library(mill, n=0)
    with pytest.raises(ValueError, match="'faults' range of LibraryRanges must be"):
        draw_sample(mill, rng, ranges=LibraryRanges(faults=(0.0, -1.0)))


def test_simulated_recording_has_the_mill_channels(mill):
    spec = draw_sample(mill, np.random.default_rng(1))
    rec, res = simulate_sample(mill, spec)
    assert set(rec.channels) == {c.name for c in mill.channels}
    t46 = rec.channel("T_C46").to_numpy()
    ref = res.outputs["tau:C46"].to_numpy()[:t46.size] * mill.element("C46").ratio
    assert np.corrcoef(t46, ref)[0, 1] > 0.99  # physical torque in N*m, with noise


# ---- model, artefact, explanations ---------------------------------------------------------

def test_model_diagnoses_every_element_and_bearing(mill, tiny_model, tiny_library):
    d = diagnose_features(tiny_model, tiny_library.features.iloc[0])
    assert set(d.elements) == set(mill.element_ids)
    assert set(d.bearings) == {b.id for b in mill.bearings}
    seen = {c.element for c in mill.torque_channels()}
    for eid, t in d.elements.items():
        assert t.state in STATES and 0.0 <= t.probability <= 1.0
        assert sum(t.probabilities.values()) == pytest.approx(1.0)
        assert t.observable == (eid in seen)
        assert t.interval[0] <= t.size + 1e-12 or t.size == 0.0
    assert d.elements["C23"].observable is False


def test_explanations_name_features(tiny_model, tiny_library):
    d = diagnose_features(tiny_model, tiny_library.features.iloc[1], n_explain=3)
    expl = [x for t in d.elements.values() for x in t.explanation]
    assert expl, "some decision must have a driving feature"
    for x in expl:
        assert x["effect"] > 0 and x["feature"] in tiny_model.feature_names
        assert isinstance(x["description"], str) and x["description"]
    assert describe_feature("bite.C46.A20.phase") == (
        "phase shift at 20 Hz against the linear baseline (deg) in C46's torque, at bites")
    assert "accelerometer B23:v" in describe_feature("release.B23:v.rms")


def test_out_of_range_recording_is_uncertain(mill, tiny_model, tiny_library):
    """Features far outside the library: probabilities shrink towards 1/3, flagged."""
    x = tiny_library.features.iloc[0].copy()
    x = x + 50.0 * (x.abs() + 1.0)  # every feature far beyond anything simulated
    d = diagnose_features(tiny_model, x)
    for t in d.elements.values():
        assert t.uncertain and t.novelty > 2.0
        assert t.probability < 0.5


def test_dont_know_is_not_good():
    """A recording far beyond the library: the probabilities become uniform (uncertain), and
    the state is still the one the trees point to -- a tie is no reason to say "good" (a
    clearance regressed at 1.2 mm beyond the library's range was reported good, p 0.33)."""
    from threadpoolctl import threadpool_limits

    from ident.diagnose.estimators import GapRegressor, WearClassifier
    from ident.diagnose.model import DiagnosticModel, TargetModel

    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 3.0e-3, 300)
    X = np.column_stack([x, rng.normal(0.0, 1.0, 300)])
    y = np.where(x > 1.8e-3, "critical", np.where(x > 1.0e-3, "worn", "good"))
    with threadpool_limits(1):
        tm = TargetModel(kind="bearing", features=("f0", "f1"),
                         classifier=WearClassifier(max_iter=20, calibration=None,
                                                   random_state=0).fit(X, y),
                         regressor=GapRegressor(max_iter=20, random_state=0).fit(X, x),
                         limits=(1.0e-3, 1.8e-3), importances=(), class_medians={})
    model = DiagnosticModel(mill_name="m", mill_hash="h", versions={}, feature_names=("f0", "f1"),
                            targets={"B1": tm}, n_samples=300)
    d = diagnose_features(model, {"f0": 2.5e-3, "f1": 40.0}, explain=False).bearings["B1"]
    assert d.novelty > 2.0 and d.uncertain
    assert d.probabilities == pytest.approx({s: 1 / 3 for s in STATES})
    assert d.state == "critical" and d.size > 1.8e-3
    inside = diagnose_features(model, {"f0": 2.5e-3, "f1": 0.0}, explain=False).bearings["B1"]
    assert inside.state == "critical" and not inside.uncertain


def test_decide_state_calls_a_dim_wear_worn_below_the_alarm():
    from ident.diagnose.model import decide_state

    assert decide_state([0.55, 0.30, 0.15]) == "good"  # the most probable state by default
    assert decide_state([0.55, 0.30, 0.15], alarm=0.6) == "worn"
    assert decide_state([0.55, 0.20, 0.25], alarm=0.6) == "critical"  # the likelier of the two
    assert decide_state([0.65, 0.30, 0.05], alarm=0.6) == "good"
    # a threshold never turns "not good" into good
    assert decide_state([0.40, 0.45, 0.15], alarm=0.1) == "worn"
    assert decide_state([0.30, 0.30, 0.40], alarm=0.0) == "critical"


def test_alarm_threshold_keeps_the_false_alarms_at_the_rate():
    from ident.diagnose.model import alarm_threshold, decide_state

    rng = np.random.default_rng(4)
    n = 400
    states = rng.choice(np.array(STATES), size=n, p=[0.6, 0.25, 0.15])
    # good samples mostly confident, worn ones often dimly seen (p(good) around 0.5-0.7)
    pg = np.where(states == "good", rng.beta(8, 2, n), rng.beta(4, 4, n))
    rest = 1.0 - pg
    proba = np.column_stack([pg, 0.7 * rest, 0.3 * rest])
    for rate in (0.05, 0.10, 0.20):
        t = alarm_threshold(proba, states, rate=rate)
        said = np.array([decide_state(p, t) for p in proba])
        good = states == "good"
        fa = np.mean(said[good] != "good")
        assert fa <= rate + 1e-12
        assert fa >= rate - 2.0 / good.sum()  # the highest such threshold, not any
        recall = np.mean(said[~good] != "good")
        by_max = np.mean(np.argmax(proba[~good], axis=1) > 0)
        assert recall > by_max + 0.1, (rate, recall, by_max)
    # where the most probable state already raises too many alarms, it alone decides
    bad = np.tile([[0.3, 0.5, 0.2]], (10, 1))
    assert alarm_threshold(bad, np.array(["good"] * 10)) == 0.0
    assert alarm_threshold(proba, np.array(["worn"] * n)) == 0.0


def test_alarm_is_calibrated_out_of_fold():
    """Trained on 120 samples of a dimly seen gap: the out-of-fold threshold lets about the
    allowed share of a fresh draw's good samples be called worn, and finds more of the
    worn ones than the most probable state."""
    from threadpoolctl import threadpool_limits

    from ident.diagnose.model import FALSE_ALARM_RATE, TargetModel, _calibrated_alarm

    def draw(n, seed):  # mostly good, as in the library; the feature reads the gap +-0.3 mrad
        r = np.random.default_rng(seed)
        y = r.choice(np.array(STATES), size=n, p=[0.7, 0.2, 0.1])
        gap = np.where(y == "good", r.uniform(0.0, 1.5e-3, n),
                       np.where(y == "worn", r.uniform(1.5e-3, 2.4e-3, n),
                                r.uniform(2.4e-3, 4.0e-3, n)))
        X = np.column_stack([gap + r.normal(0.0, 0.3e-3, n), r.normal(0.0, 1.0, n)])
        return X, y, gap

    X, y, gap = draw(120, 0)
    with threadpool_limits(1):
        alarm = _calibrated_alarm(X, y, gap, (1.5e-3, 2.4e-3), blend=0.75, max_iter=20,
                                  leaf=5, random_state=0)
        from ident.diagnose.model import _fit_estimators

        reg, clf = _fit_estimators(X, y, gap, max_iter=20, leaf=5, random_state=0)
        tm = TargetModel(kind="element", features=("f0", "f1"), classifier=clf, regressor=reg,
                         limits=(1.5e-3, 2.4e-3), importances=(), class_medians={},
                         alarm=alarm)
        Xt, yt, _ = draw(600, 1)
        p = tm.state_proba_in_range(Xt)
    assert 0.3 < alarm < 1.0
    said = np.array([tm.decide(row) for row in p])
    good = yt == "good"
    fa = np.mean(said[good] != "good")
    assert fa <= 2.0 * FALSE_ALARM_RATE, fa  # measured 0.07
    recall = np.mean(said[~good] != "good")
    by_max = np.mean(np.argmax(p[~good], axis=1) > 0)
    assert recall > by_max + 0.05, (recall, by_max)  # measured 0.89 against 0.76
    # too small a library: the most probable state decides
    assert _calibrated_alarm(X[:40], y[:40], gap[:40], (1.5e-3, 2.4e-3), blend=0.75,
                             max_iter=20, leaf=5, random_state=0) == 0.0


def test_artefact_roundtrip_and_refusals(mill, tiny_model, tmp_path):
    p = save_model(tiny_model, tmp_path / "m.joblib")
    from ident.io.writers import new_file_mode

    assert p.stat().st_mode & 0o777 == new_file_mode()  # the umask's, not mkstemp's 0600
    m2 = load_model(p, mill)
    assert m2.mill_hash == mill.content_hash() and m2.feature_names == tiny_model.feature_names
    other = mill.with_overrides({"C46.k": 2.0e7})
    with pytest.raises(ModelArtifactError,
                       match=f"trained for another mill description .content hash "
                             f"{mill.content_hash()}"):
        load_model(p, other)
    import joblib

    data = joblib.load(p)
    data["versions"]["scikit-learn"] = "0.0.1"
    joblib.dump(data, tmp_path / "old.joblib")
    with pytest.raises(ModelArtifactError, match=r"scikit-learn 0\.0\.1 \(now "):
        load_model(tmp_path / "old.joblib", mill)
    data = joblib.load(p)
    del data["recipe"]  # an artefact of the first library (no drag, 6-8 bars): retrained
    joblib.dump(data, tmp_path / "recipe1.joblib")
    with pytest.raises(ModelArtifactError, match=r"older library recipe \(1, now \d+\); retrain"):
        load_model(tmp_path / "recipe1.joblib", mill)
    with pytest.raises(ModelArtifactError, match="does not exist"):
        load_model(tmp_path / "missing.joblib", mill)
    (tmp_path / "junk.joblib").write_text("not a model")
    with pytest.raises(ModelArtifactError, match="cannot be read"):
        load_model(tmp_path / "junk.joblib", mill)


def test_training_refuses_a_library_of_another_mill(mill, tiny_library):
    other = mill.with_overrides({"C46.k": 2.0e7})
    with pytest.raises(ModelArtifactError, match="library was simulated from another mill description"):
        train_model(tiny_library, other)


def test_model_cache_path(mill, monkeypatch, tmp_path):
    monkeypatch.setenv("IDENT_CACHE", str(tmp_path))
    assert model_cache_path(mill) == tmp_path / "models" / f"{mill.content_hash()}.joblib"


def test_model_cache_follows_the_description_not_the_file_bytes(mill_path, tmp_path,
                                                                 monkeypatch):
    """A comment or a reformatted file finds the same cached model; a changed value a new one
    (issue 13: any edit of the mill file retrained the model)."""
    monkeypatch.setenv("IDENT_CACHE", str(tmp_path))
    text = mill_path.read_text()
    commented = tmp_path / "commented.toml"
    commented.write_text("# inspected 2026-11-30, no change\n\n" + text.replace(" = ", "   =   "))
    changed = tmp_path / "changed.toml"
    changed.write_text(text.replace("k = 1.815e7", "k = 1.9e7", 1))
    a, b, c = (load_mill(p) for p in (mill_path, commented, changed))
    assert a.sha256 != b.sha256                      # the bytes differ ...
    assert model_cache_path(a) == model_cache_path(b)  # ... the description does not
    assert model_cache_path(c) != model_cache_path(a)


# ---- command line ------------------------------------------------------------------------------

@pytest.fixture(scope="session")
def recording(mill_path, tmp_path_factory):
    """A simulated recording with a worn lower spindle (ident simulate)."""
    d = tmp_path_factory.mktemp("rec")
    rec = d / "worn.mcap"
    assert main(["simulate", "--mill", str(mill_path), "--out", str(rec), "--bars", "3",
                 "--seed", "4", "--set", "C46.gap=0.010", "--set", "C46.gap_open=0.010",
                 "--quiet"]) == 0
    return rec


def test_cli_diagnose_with_a_model(mill, mill_path, tiny_model, recording, tmp_path):
    model = save_model(tiny_model, tmp_path / "m.joblib")
    out = tmp_path / "d.json"
    assert main(["diagnose", str(recording), "--mill", str(mill_path), "--model", str(model),
                 "--no-fit", "--out", str(out), "--quiet"]) == 0
    d = json.loads(out.read_text())
    assert set(d["elements"]) == set(mill.element_ids)
    assert set(d["bearings"]) == {"B23", "B45"}
    for v in d["elements"].values():
        assert {"state", "probability", "gap", "observable", "uncertain"} <= set(v)
    for v in d["bearings"].values():
        assert {"state", "probability", "clearance"} <= set(v)
    f = d["features"]
    assert len(f["frequencies_hz"]) == len(f["amplitude_ratio"]) == len(f["phase_shift_deg"]) == 6
    assert d["transients"]["bites"] == 3


def test_cli_diagnose_refuses_a_model_of_another_mill(mill, tiny_model, recording, tmp_path,
                                                       capsys):
    other_path = tmp_path / "other.toml"
    text = Path(mill.source).read_text().replace("k = 1.815e7", "k = 1.9e7")
    other_path.write_text(text)
    model = save_model(tiny_model, tmp_path / "m.joblib")
    code = main(["diagnose", str(recording), "--mill", str(other_path), "--model", str(model),
                 "--no-fit", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "was trained for another mill description" in err and "retrain" in err


def test_cli_train_then_diagnose_trains_and_caches(mill_path, recording, tmp_path, monkeypatch,
                                                   capsys):
    """``ident train`` writes an artefact; ``ident diagnose`` without --model trains one on
    first use (progress on stderr) and reuses it after."""
    out = tmp_path / "m.joblib"
    assert main(["train", "--mill", str(mill_path), "--out", str(out), "--samples", "10",
                 "--jobs", "1", "--no-bearings", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["samples"] == 10 and Path(summary["model"]) == out and out.exists()
    # 10 samples calibrate no alarm: every target decides by its most probable state
    assert set(summary["alarms"]) == set(summary["elements"]) | set(summary["bearings"])
    assert set(summary["alarms"].values()) == {0.0}
    assert main(["train", "--mill", str(mill_path), "--out", str(out), "--samples", "3"]) == 2
    assert "--samples must be at least 10" in capsys.readouterr().err

    monkeypatch.setenv("IDENT_CACHE", str(tmp_path / "cache"))
    assert main(["diagnose", str(recording), "--mill", str(mill_path), "--samples", "10",
                 "--jobs", "1", "--no-fit", "--out", str(tmp_path / "a.json")]) == 0
    err = capsys.readouterr().err
    assert "training one on 10 simulated recordings" in err
    cached = list((tmp_path / "cache" / "models").glob("*.joblib"))
    assert len(cached) == 1
    assert main(["diagnose", str(recording), "--mill", str(mill_path), "--no-fit", "--out",
                 str(tmp_path / "b.json")]) == 0
    assert "training" not in capsys.readouterr().err
    a = json.loads((tmp_path / "a.json").read_text())
    b = json.loads((tmp_path / "b.json").read_text())
    assert a["elements"] == b["elements"]


# ---- accuracy on held-out simulated recordings ------------------------------------------------

def _confusion(y_true, y_pred) -> pd.DataFrame:
    cm = pd.crosstab(pd.Categorical(y_true, STATES), pd.Categorical(y_pred, STATES),
                     rownames=["true"], colnames=["predicted"], dropna=False)
    return cm


@pytest.mark.slow
def test_held_out_accuracy(mill, accuracy_libraries, accuracy_model):
    """Held-out recordings: other seeds, static torques, rise times, drags, noise and
    stiffness and damping draws than the training library's.  Elements a torque channel sees
    >= 80 %, bearings from their accelerometers >= 75 %; confusion matrices printed (pytest -s).

    Measured 2026-12-04 (library recipe 2): observable elements 0.83-0.90, bearings 0.77 and
    0.81.  The first library (recipe 1: 6-8 bars, 10-40 ms ramps, no drag between bars) gave
    >= 0.90 and >= 0.80 here, and read the independent plant simulator's bearings 0.27 mm
    small; recipe 2 covers 2-bar recordings, 5-80 ms ramps and loads between bars, and its
    simulated recordings are harder to tell apart with 280 of them (on 6-8-bar held-out
    recordings alone: 0.85-0.89 and 0.75/0.87).
    """
    from sklearn.metrics import balanced_accuracy_score

    _, test = accuracy_libraries
    seen = {c.element for c in mill.torque_channels()}
    acc = {}
    pred = [diagnose_features(accuracy_model, test.features.iloc[i], explain=False)
            for i in range(len(test))]
    for tid, tm in accuracy_model.targets.items():
        y = test.truth[f"{tid}.state"].to_numpy()
        p = np.array([(d.elements.get(tid) or d.bearings.get(tid)).state for d in pred])
        acc[tid] = float(np.mean(p == y))
        print(f"\n{tid} ({tm.kind}{', observable' if tid in seen or tm.kind == 'bearing' else ''})"
              f": accuracy {acc[tid]:.3f}, balanced {balanced_accuracy_score(y, p):.3f}"
              f"\n{_confusion(y, p)}")
    for e in seen:
        assert acc[e] >= 0.80, (e, acc[e])
    for b in mill.bearings:
        assert acc[b.id] >= 0.75, (b.id, acc[b.id])


def test_held_out_alarms(mill, accuracy_libraries, accuracy_model):
    """The calibrated alarm thresholds on held-out recordings: of the good elements at most
    about FALSE_ALARM_RATE called worn or critical, and more of the worn and critical ones
    found than by the most probable state alone (pooled over the elements)."""
    from ident.diagnose.model import FALSE_ALARM_RATE

    _, test = accuracy_libraries
    fa = [0, 0]
    found = {"alarm": 0, "most probable": 0, "of": 0}
    for e in mill.elements:
        tm = accuracy_model.targets[e.id]
        assert 0.0 < tm.alarm < 1.0, (e.id, tm.alarm)
        X = test.features[list(tm.features)].to_numpy(dtype=float)
        p = tm.state_proba_in_range(X)
        said = np.array([tm.decide(row) for row in p])
        y = test.truth[f"{e.id}.state"].to_numpy()
        good = y == "good"
        fa[0] += int(np.sum(said[good] != "good"))
        fa[1] += int(good.sum())
        found["alarm"] += int(np.sum(said[~good] != "good"))
        found["most probable"] += int(np.sum(np.argmax(p[~good], axis=1) > 0))
        found["of"] += int((~good).sum())
    print(f"\nfalse alarms {fa[0]}/{fa[1]}, found {found}")
    # binomial sampling of ~400 good samples: 3 standard deviations above the rate
    assert fa[0] / fa[1] <= FALSE_ALARM_RATE + 3 * np.sqrt(0.1 * 0.9 / fa[1])
    assert found["alarm"] >= found["most probable"] + 0.05 * found["of"], found
