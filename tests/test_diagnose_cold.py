"""Diagnosis on the second mill (cold-s5: 5-mass unbranched chain, channels in kN*m and
N*m, C23 unmeasured, bearing B23) and on recordings of the independent plant simulator.

The figures per mill come from ``python -m validation.diagnose_study``; this is its small
version: the spectral features read the cold stand's 138 Hz mode (a fixed decimation by 8
put it above the 125 Hz Nyquist frequency of 2 kHz torque), a small model of the cold
stand is trained, saved and applied by ``ident diagnose`` to plantsim recordings, and the
study's truth and scoring are checked.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import ident
from ident.cli import main
from ident.diagnose import save_model, simulate_library, train_model
from ident.diagnose.states import STATES, bearing_state, element_state
from ident.features.baseline import LinearReference
from ident.features.extract import FeatureOptions
from ident.features.spectral import MatrixPencil
from ident.model.scenario import nominal_torque
from validation import diagnose_study


@pytest.fixture(scope="module")
def cold_path(repo_root: Path) -> Path:
    return repo_root / "data" / "mills" / "cold-s5.toml"


@pytest.fixture(scope="module")
def cold(cold_path):
    return ident.load_mill(cold_path)


def _modes(mill):
    return LinearReference(mill).poles


def _ringing(freqs, damping, rate_hz, phases, window_s=0.5):
    tau = np.arange(int(window_s * rate_hz)) / rate_hz
    x = 0.3 + 0.1 * tau
    for f, z, p in zip(freqs, damping, phases):
        w = 2 * np.pi * f
        x = x + np.exp(-z * w * tau) * np.cos(w * np.sqrt(1 - z * z) * tau + p)
    return x


@pytest.mark.parametrize("name, rate_hz", [("cold-s5", 2000.0), ("cold-s5", 1000.0),
                                           ("cold-s5", 5000.0), ("hsm-f1", 1000.0),
                                           ("hsm-f1", 2000.0)])
def test_default_pencil_reads_every_mode_of_either_mill(repo_root, name, rate_hz):
    mill = ident.load_mill(repo_root / "data" / "mills" / f"{name}.toml")
    freqs, damping = _modes(mill)
    est = FeatureOptions().estimator
    q = est.decimation(rate_hz, freqs)
    # at least 2.5 samples per period of the highest mode after decimation (no aliasing)
    assert rate_hz / q >= 2.5 * freqs.max()
    rng = np.random.default_rng(3)
    ph = rng.uniform(-np.pi, np.pi, freqs.size)
    amp, phase = est.estimate(_ringing(freqs, damping, rate_hz, ph), rate_hz, freqs, damping)
    np.testing.assert_allclose(amp, 1.0, rtol=0.05)
    err = np.degrees(np.abs(np.angle(np.exp(1j * (phase - ph)))))
    assert err.max() < 5.0


def test_fixed_decimation_by_8_loses_the_cold_stands_top_mode(cold):
    """What the default did before: 2 kHz / 8 = 250 Hz cannot hold 138 Hz."""
    freqs, damping = _modes(cold)
    assert freqs.max() > 125.0
    ph = np.zeros(freqs.size)
    x = _ringing(freqs, damping, 2000.0, ph)

    class Fixed(MatrixPencil):
        def decimation(self, rate_hz, freqs_hz):
            return 8

    amp, _ = Fixed(decimate=8).estimate(x, 2000.0, freqs, damping)
    assert abs(amp[-1] - 1.0) > 0.2
    # hsm-f1 at 2 kHz keeps its decimation by 8 (models trained before stay valid)
    assert FeatureOptions().estimator.decimation(2000.0, np.array([11.3, 80.8])) == 8


def test_study_truth_lies_inside_the_state_bands(cold):
    seen = set()
    for seed in range(40):
        gaps, cl, states, bstates = diagnose_study.draw_truth(cold, np.random.default_rng(seed))
        for e in cold.elements:
            assert states[e.id] == element_state(e, gaps[e.id]).value
            # clear of the limits by 10 % of the band
            for lim in (e.gap_worn, e.gap_critical):
                assert abs(gaps[e.id] - lim) > 0.05 * e.gap_worn
            seen.add(states[e.id])
        for b in cold.bearings:
            assert bstates[b.id] == bearing_state(b, cl[b.id]).value
            seen.add("b-" + bstates[b.id])
    assert seen == set(STATES) | {f"b-{s}" for s in STATES}


def test_study_scores_count_states():
    class M:
        def torque_channels(self):
            class C:
                element = "C12"
            return [C()]

    cases = [{"states": {"C12": "worn", "C23": "good"}, "bearing_states": {"B23": "critical"},
              "diagnosis": {"elements": {"C12": {"state": "worn"}, "C23": {"state": "worn"}},
                            "bearings": {"B23": {"state": "good"}}}},
             {"states": {"C12": "critical", "C23": "good"}, "bearing_states": {"B23": "good"},
              "diagnosis": {"elements": {"C12": {"state": "worn"}, "C23": {"state": "good"}},
                            "bearings": {"B23": {"state": "good"}}}},
             {"states": {"C12": "good"}, "bearing_states": {}, "diagnosis": None}]
    f = diagnose_study.score(cases, M())
    assert f["recordings"] == 2 and f["failed"] == 1
    assert f["element_accuracy"] == (2, 4)
    assert f["observable_accuracy"] == (1, 2)
    assert f["worn_recall"] == (1, 1)
    assert f["critical_recall"] == (0, 1)
    assert f["faulty_recall"] == (2, 2)
    assert f["false_alarm"] == (1, 2)
    assert f["bearing_accuracy"] == (1, 2)
    assert f["fit_right"] == (0, 2) and f["fit_wrong"] == (0, 0)


def test_study_scores_the_gaps_the_fit_identified():
    """The fit study's figures on the measured gaps: right within max(10 %, 0.3 mrad), wrong
    of those identified, covered by the 95 % interval; unmeasured gaps not counted."""
    def el(gap, lo, hi, source="fit", identified=True):
        return {"state": "worn", "source": source, "gap": gap, "gap_ci95": [lo, hi],
                "identified": identified}

    cases = [{"gaps": {"C12": 5.0e-3, "C34": 2.0e-3, "C23": 1.0e-3},
              "diagnosis": {"elements": {"C12": el(5.4e-3, 5.2e-3, 5.6e-3),    # right, missed
                                         "C34": el(2.5e-3, 1.9e-3, 3.1e-3),    # wrong, covered
                                         "C23": el(3.0e-3, 2.9e-3, 3.1e-3)}}},  # unmeasured
             {"gaps": {"C12": 1.0e-3, "C34": 9.0e-3},
              "diagnosis": {"elements": {"C12": el(1.25e-3, 1.0e-3, 1.5e-3),   # right: 0.3 mrad
                                         "C34": el(4.0e-3, 0, 1, "diagnosis")}}},
             {"gaps": {"C12": 1.0e-3, "C34": 3.0e-3},  # bounded: a state, no value
              "diagnosis": {"elements": {"C34": el(3.0e-3, 2.5e-3, 3.5e-3, identified=False)}}},
             {"gaps": {"C12": 1.0e-3}, "diagnosis": None}]
    f = diagnose_study.fit_gap_figures(cases, {"C12", "C34"})
    assert f == {"fit_right": (2, 5), "fit_wrong": (1, 3), "fit_covered": (2, 3),
                 "fit_bounded": (1, 5)}


@pytest.fixture(scope="module")
def cold_model_path(cold, tmp_path_factory):
    """A small cold-s5 model (40 simulated recordings with the bearing)."""
    lib = simulate_library(cold, n=40, random_state=5, bearings=True)
    model = train_model(lib, cold, random_state=0, max_iter=40)
    return save_model(model, tmp_path_factory.mktemp("cold-model") / "cold.joblib")


def test_cli_diagnoses_plantsim_recordings_of_the_cold_stand(cold, cold_path, cold_model_path,
                                                             tmp_path):
    """``ident diagnose`` on the independent simulator's cold-stand files, CSV and MCAP."""
    for seed in (3, 4):  # one CSV, one MCAP
        path, case = diagnose_study.make_case(cold, seed, tmp_path, n_bars=3)
        out = tmp_path / f"diag{seed}.json"
        code = main(["diagnose", str(path), "--mill", str(cold_path), "--model",
                     str(cold_model_path), "--no-fit", "--out", str(out), "--quiet"])
        assert code == 0
        d = json.loads(out.read_text())
        assert list(d["elements"]) == ["C12", "C23", "C34", "C45"]
        assert {e: v["observable"] for e, v in d["elements"].items()} == \
            {"C12": True, "C23": False, "C34": True, "C45": True}
        assert "gap_mm" in d["elements"]["C45"] and "gap_mm" not in d["elements"]["C34"]
        assert set(d["bearings"]) == {"B23"}
        assert d["transients"]["bites"] == 3
        for v in (*d["elements"].values(), *d["bearings"].values()):
            assert v["state"] in STATES
            assert abs(sum(v["probabilities"].values()) - 1.0) < 1e-6
        # the cold stand's own four modes label the features (not hsm-f1's six)
        fs = d["features"]
        assert len(fs["frequencies_hz"]) == 4 and fs["frequencies_hz"][-1] > 130.0
        f = diagnose_study.score([dict(case, diagnosis=d)], cold)
        assert f["element_accuracy"][1] == 4 and f["bearing_accuracy"][1] == 1


# ---- idle drag in the library (half its samples) -------------------------------------------

def test_idle_drag_loads_the_upstream_elements_between_bars(cold):
    """Drag on the masses upstream of the spindle: the couplings carry it at idle, the
    spindle does not; without it the library's samples are what they were."""
    from ident.diagnose.library import (LibraryRanges, LibrarySimulator, draw_sample,
                                        drag_masses)

    assert drag_masses(cold) == ("Q1", "Q2", "Q3", "Q4")
    plain = draw_sample(cold, np.random.default_rng(2), ranges=LibraryRanges(drag_fraction=0.0))
    dragged = draw_sample(cold, np.random.default_rng(2),
                          ranges=LibraryRanges(drag_fraction=1.0, drag=(0.04, 0.04)))
    assert plain.drag == {} and plain.gaps == dragged.gaps and plain.seed == dragged.seed
    total = sum(dragged.drag.values())
    assert total == pytest.approx(0.04 * nominal_torque(cold))
    sim = LibrarySimulator(cold)
    r0, r1 = sim.simulate(plain), sim.simulate(dragged)
    t_bite = dragged.scenario.bars[0].t_bite
    idle = (r1.time > t_bite - 0.1) & (r1.time < t_bite - 0.01)
    tau = {e: r1.outputs[f"tau:{e}"].to_numpy()[idle].mean() for e in ("C12", "C34", "C45")}
    # C12 carries everything beyond the motor, C34 the drag of Q4, C45 nothing
    assert tau["C12"] == pytest.approx(total - dragged.drag["Q1"], rel=0.15)
    assert tau["C34"] == pytest.approx(dragged.drag["Q4"], rel=0.5, abs=0.02 * total)
    assert abs(tau["C45"]) < 0.02 * total
    tb0 = plain.scenario.bars[0].t_bite
    t0 = r0.outputs["tau:C12"].to_numpy()[(r0.time > tb0 - 0.1) & (r0.time < tb0 - 0.01)].mean()
    assert abs(t0) < 0.02 * total
    # the pauses are long enough for the drag to close the couplings again before bar 2
    b2 = dragged.scenario.bars[1].t_bite
    idle2 = (r1.time > b2 - 0.1) & (r1.time < b2 - 0.01)
    assert r1.outputs["tau:C12"].to_numpy()[idle2].mean() == \
        pytest.approx(total - dragged.drag["Q1"], rel=0.15)
    assert b2 - dragged.scenario.bars[0].t_release > 1.4


def _lift_between_bars(mill, bearing, on_mass: dict[str, float]) -> float:
    """Share of a bearing's shaft weight that the mesh force of a load between bars lifts."""
    import math

    from validation import plantsim

    tree = plantsim._tree(mill)
    ext = np.zeros(len(tree.ids))
    for m, v in on_mass.items():
        ext[list(tree.ids).index(m)] += v
    tau = plantsim._static_torques(tree, ext)[mill.element_ids.index(bearing.mesh)]
    force = abs(tau) * bearing.ratio / bearing.base_radius
    return force * math.cos(math.radians(bearing.pressure_angle_deg)) / (bearing.shaft_mass * 9.81)


@pytest.mark.parametrize("name", ["cold-s5", "hsm-f1"])
def test_library_loads_the_gear_bearings_between_bars_as_a_plant_does(repo_root, name):
    """Bearing friction between bars puts a load on the gear meshes that lifts part of each
    gear shaft's weight (plantsim: 0.2-1.3 of it on cold-s5's B23, 0.5-3.3 on hsm-f1's), and
    the shaft then falls and rattles more softly after a release.  The library's drags must
    span those loads, not only the unloaded case.  Without a drag (the default before) only
    the idle load lifted, at most 0.4 of B23's weight, and the plant's clearances were read
    small (validation.diagnose_study, seeds 800-815: 0.27 mm low on average, critical B23
    called worn); with drags spread J-weighted (~3/4 on the motor rotor) at most 0.55."""
    from ident.diagnose.library import draw_sample
    from validation import plantsim

    mill = ident.load_mill(repo_root / "data" / "mills" / f"{name}.toml")
    rng = np.random.default_rng(0)
    samples = [draw_sample(mill, rng) for _ in range(200)]
    plants = [plantsim.draw_plant(mill, np.random.default_rng(s), n_bars=1, accelerometers=False)
              for s in range(8)]
    for b in mill.bearings:
        lib = []
        for sp in samples:
            on = dict(sp.drag)
            for m, share in zip(mill.load.masses, mill.load.share):
                on[m] = on.get(m, 0.0) + share * sp.scenario.idle_torque
            lib.append(_lift_between_bars(mill, b, on))
        plant = [_lift_between_bars(mill, b, p.friction) for p in plants]
        lo, hi = np.percentile(lib, [5, 95])
        assert np.mean(np.array(lib) == 0.0) > 0.2  # stands with nothing between bars too
        assert lo <= min(plant) and np.median(plant) <= hi, (b.id, plant, lo, hi)


# ---- the discrepancy workflow on the cold stand ----------------------------------------------

@pytest.mark.slow
def test_cli_discrepancy_on_the_cold_stand(cold, cold_path, tmp_path):
    """Plantsim recordings of cold-s5 (~70 s): nothing missing -> null.  A softening knee
    on the spindle C45 that the mill file lacks: the refit at C45 ranks first and recovers
    the knee and stiffness ratio, but the answer is null, never a wrong name -- the
    signatures of softening at C34 and at C45, in series around the light spindle mass
    Q4, are alike (C34 scores higher), and DecisionRule names no location its signature
    does not lead (see the issue note)."""
    soft, near = diagnose_study.hidden_softening(cold)
    assert near == "C45"
    path, _ = diagnose_study.make_case(cold, 1499, tmp_path, n_bars=4, truth_gaps=False)
    code, d, err = diagnose_study.run_cli(["discrepancy", str(path), "--mill", str(cold_path),
                                           "--no-plots", "--quiet"])
    assert code == 0, err
    assert not d["explained"] and d["effect"] is None, d["reason"]
    assert max(r["improvement"] for r in d["refits"]) < 0.3

    path, _ = diagnose_study.make_case(cold, 1499, tmp_path, n_bars=4, truth_gaps=False,
                                       plant_mill=soft)
    code, d, err = diagnose_study.run_cli(["discrepancy", str(path), "--mill", str(cold_path),
                                           "--no-plots", "--quiet"])
    assert code == 0, err
    assert d["effect"] in (None, "softening_stiffness") and d["location"] in (None, "C45")
    best = min(d["refits"], key=lambda r: r["nrmse"])
    assert (best["effect"], best["location"]) == ("softening_stiffness", "C45")
    assert best["improvement"] > 0.8
    knee = soft.element("C45").knee
    for p in best["params"]:
        assert p["k_ratio"] == pytest.approx(0.6, abs=0.05)
        assert p["knee"] == pytest.approx(knee, rel=0.25)
