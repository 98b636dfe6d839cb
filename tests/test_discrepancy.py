"""The discrepancy workflow's parts: windows, window model against the simulator, fits,
residual analysis, decision rule, hidden-effect generator, errors.

The full workflow on recordings with hidden effects is in
``tests/test_discrepancy_hidden.py`` (slow).
"""

from __future__ import annotations

import math
import types

import numpy as np
import pandas as pd
import pytest

from ident.discrepancy import (CONTROLS, STRENGTHS, DecisionRule, Refit, Window,
                               analyse_residuals, as_windows, discrepancy, hidden_effect_case)
from ident.discrepancy import engine as G
from ident.discrepancy.windows import windows_from_frame
from ident.errors import FitError, IdentError, RecordingError
from ident.model.dynamics import ModelOptions
from ident.model.effects import EFFECT_NAMES, candidate_locations
from ident.model.linear import natural_modes
from ident.model.scenario import Bar, Scenario
from ident.model.simulate import simulate

TORQUES = ("C12", "C34", "C46", "C57")
BARS = (Bar(t_bite=0.5, t_release=2.0, static_torque=3e5, rise_time=0.02, fall_time=0.03),
        Bar(t_bite=3.2, t_release=4.6, static_torque=1.5e5, rise_time=0.03, fall_time=0.02))


def _segments(bars):
    out = []
    for b in bars:
        out.append(types.SimpleNamespace(t_step=b.t_step_bite, kind="bite",
                                         static_torque=b.static_torque, step=b.static_torque,
                                         rise_s=0.59 * b.rise_time))
        out.append(types.SimpleNamespace(t_step=b.t_step_release, kind="release",
                                         static_torque=b.static_torque, step=-b.static_torque,
                                         rise_s=0.59 * b.fall_time))
    return out


@pytest.fixture(scope="module")
def truth(mill):
    """Noise-free simulation (exact g1 kinks, 50 us steps) of two bars, and its windows."""
    r = simulate(mill, Scenario(duration=5.4, bars=BARS), options=ModelOptions(bearings=False))
    frame = r.outputs[[f"tau:{e}" for e in TORQUES]]
    return r, windows_from_frame(frame, mill, _segments(BARS))


# ---- windows -----------------------------------------------------------------------------------
def test_windows_are_cut_per_step_resampled_and_grouped_by_bar(truth):
    _, wins = truth
    assert [w.kind for w in wins] == ["bite", "release", "bite", "release"]
    assert [w.bar for w in wins] == [0, 0, 1, 1]
    assert {w.n_samples for w in wins} == {450}
    assert wins[0].dt == pytest.approx(1e-3)
    assert wins[0].elements == TORQUES
    assert wins[0].level_before == 0.0 and wins[0].level_after == 3e5
    assert wins[1].level_before == 3e5 and wins[1].level_after == 0.0
    assert wins[0].t[0] == pytest.approx(BARS[0].t_step_bite - 0.05, abs=1e-3)
    # a bite after a release remembers that release (for roll-angle effects)
    assert wins[0].history is None
    t_rel, before, after, rise = wins[2].history
    assert (t_rel, before, after) == (BARS[0].t_step_release, 3e5, 0.0)
    assert rise == pytest.approx(0.03)


def test_as_windows_takes_fit_windows_and_assigns_bars_in_time_order(truth):
    _, wins = truth
    fws = [types.SimpleNamespace(t=w.t, y=w.y, elements=w.elements, t_step=w.t_step,
                                 kind=w.kind, static_torque=w.static_torque,
                                 step=w.level_after - w.level_before, label=w.label)
           for w in reversed(wins)]
    got = as_windows(fws)
    assert [w.bar for w in got] == [0, 0, 1, 1]
    assert [w.level_before for w in got] == [w.level_before for w in wins]


def test_window_refuses_bad_shapes_and_kinds():
    t = np.arange(20) * 1e-3
    with pytest.raises(FitError, match=r"y must have shape \(20, 2\)"):
        Window(t=t, elements=("C12", "C34"), y=np.zeros((20, 3)), t_step=0.01, kind="bite",
               level_before=0, level_after=1, bar=0)
    with pytest.raises(FitError, match="kind must be 'bite' or 'release'"):
        Window(t=t, elements=("C12",), y=np.zeros(20), t_step=0.01, kind="coast",
               level_before=0, level_after=1, bar=0)
    with pytest.raises(FitError, match="NaN or inf"):
        Window(t=t, elements=("C12",), y=np.full(20, np.nan), t_step=0.01, kind="bite",
               level_before=0, level_after=1, bar=0)


def test_windows_from_frame_refuses_frames_without_torques(mill):
    frame = pd.DataFrame({"A_B23_v": np.zeros(100)}, index=np.arange(100) * 1e-3)
    with pytest.raises(FitError, match="no torque column matches an element"):
        windows_from_frame(frame, mill, [])


# ---- the window model against the simulator ------------------------------------------------------
def test_window_model_reproduces_the_simulator_at_the_true_parameters(mill, truth):
    """Independent truth: ident.model.simulate at 50 us steps with exact kinks."""
    _, wins = truth
    eng = G.build_engine(mill, (), dt=wins[0].dt, n_samples=wins[0].n_samples)
    W = G.initial_window_params(eng, wins)
    W[:, 3] = [0.02, 0.03, 0.03, 0.02]  # the true ramps
    W[0, 4] = 0.0  # the first bite starts at rest on the drive flanks (x_idle)
    W[2, 4] = 1.0  # after a release the elements rest on their back flanks
    sims = G.simulate_windows(eng, wins, G.State(p=eng.base_params(), W=W))
    # what is left: the 1 ms steps and 10 urad kink rounding, and the ring-down of the
    # previous step still running when a window starts (the model starts at rest)
    assert G.nrmse(eng, wins, sims) < 0.04
    assert G.nrmse(eng, wins[:1], sims[:1]) < 0.01


def test_fit_recovers_the_gaps_from_a_wrong_start(mill, truth):
    _, wins = truth
    eng = G.build_engine(mill, (), dt=wins[0].dt, n_samples=wins[0].n_samples)
    p = eng.base_params()
    for e in ("C46", "C57"):
        p[eng.p_index(f"{e}.gap")] = 0.8e-3  # the truth is 2 mrad
    start = G.State(p=p, W=G.initial_window_params(eng, wins))
    pre = G.fit(eng, wins, G.Setup.baseline(eng), start, free_shared=False, max_nfev=8)
    out = G.fit(eng, wins, G.Setup.baseline(eng), G.scan_frac(eng, wins, pre.state),
                max_nfev=20)
    assert out.nrmse < 0.04
    for e in ("C46", "C57"):
        assert out.state.p[eng.p_index(f"{e}.gap")] == pytest.approx(2e-3, rel=0.15)


@pytest.mark.parametrize("i, bar", [(1, 0), (3, 1)])
def test_ramp_grid_finds_a_release_the_segmenter_mistimed(mill, truth, i, bar):
    """The segmenter times the measured torque, which lags the load, and a ringing torque
    makes its ramp long; fits from the best rows of a grid over ramp duration and instant
    land on the true ramp (seed scenario: raised cosine of ``fall_time``)."""
    import dataclasses

    _, wins = truth
    b = BARS[bar]
    w = dataclasses.replace(wins[i], t_step=b.t_step_release + 0.012)  # 12 ms late
    eng = G.build_engine(mill, (), dt=w.dt, n_samples=w.n_samples)
    p = eng.base_params()
    row = G.initial_window_params(eng, [w])[0]

    def fit_from(r):
        return G.fit(eng, [w], G.Setup.baseline(eng), G.State(p=p, W=r[None, :]),
                     free_shared=False, max_nfev=10)

    true_row = row.copy()
    true_row[2:4] = b.t_step_release, b.fall_time
    reference = fit_from(true_row)  # what is left: ring-down of the bite, 1 ms RK4
    row[3] = 3.0 * b.fall_time  # three times too long
    starts = G.ramp_starts(eng, w, p, row, k=2)
    assert len(starts) == 2 and starts[0][3] != starts[1][3]
    best = min((fit_from(r) for r in starts), key=lambda o: o.cost)
    assert best.nrmse < 1.02 * reference.nrmse < 0.04
    assert best.state.W[0, 3] == pytest.approx(b.fall_time, rel=0.15)
    assert best.state.W[0, 2] == pytest.approx(b.t_step_release, abs=2e-3)


def test_engine_states_move_between_engines_by_parameter_name(mill):
    from ident.model.effects import CoulombFriction

    a = G.build_engine(mill, (), dt=1e-3, n_samples=50, compile=False)
    b = G.build_engine(mill, (CoulombFriction("C46"),), dt=1e-3, n_samples=50, compile=False)
    p = a.base_params()
    p[a.p_index("C46.gap")] = 3e-3
    st = G.State(p=p, W=np.zeros((1, 20))).moved(a, b)
    assert st.p[b.p_index("C46.gap")] == 3e-3
    assert st.p[b.p_index("coulomb_friction@C46.gate")] == 0.0
    su = G.Setup.for_candidate(b, "coulomb_friction@C46")
    assert b.p_index("coulomb_friction@C46.force") in su.shared
    assert b.p_index("coulomb_friction@C46.v_smooth") not in su.shared  # held, not fitted
    assert su.apply_gates(b, st.p)[b.p_index("coulomb_friction@C46.gate")] == 1.0
    with pytest.raises(KeyError):
        G.Setup.for_candidate(a, "coulomb_friction@C46")


@pytest.mark.parametrize("imbalance", [False, True])
def test_idle_runs_float_the_rolls_as_the_simulator_does(mill, imbalance):
    """Independent truth: ident.model.simulate with exact kinks at 50 us steps, from its own
    state 0.1 s before a release through 1.5 s of idling.  The windows' 10 urad rounding
    leaves a faint spring across the open gaps that floats the rolls by a good part of a
    millirad over that time; the idle runs' rounding does not."""
    from ident.model.effects import SpindleImbalance
    from ident.model.scenario import load_profile

    eff = (SpindleImbalance("C46"),) if imbalance else ()
    prm = ({"spindle_imbalance@C46.amplitude": 1e-3, "spindle_imbalance@C46.phase": 1.0}
           if imbalance else {})
    sc = Scenario(duration=2.6, bars=(Bar(t_bite=0.2, t_release=1.0, static_torque=2e5),))
    r = simulate(mill, sc, options=ModelOptions(bearings=False, effects=eff), params=prm)
    eng = G.build_engine(mill, eff, dt=1e-3, n_samples=450)
    t = r.states.index.to_numpy()
    j0, j1 = int(np.argmin(abs(t - 0.9))), int(np.argmin(abs(t - 2.5)))
    T = G.stage_times(eng.stepper, int(round((t[j1] - t[j0]) / 1e-3)) + 1, t[j0])
    err = {}
    for width in (eng.smoothing, eng.idle_smoothing):
        p = eng.base_params()
        p[eng.p_index("smoothing")] = width
        for k, v in prm.items():
            p[eng.p_index(k)] = v
        if imbalance:
            p[eng.p_index("spindle_imbalance@C46.gate")] = 1.0
        X, _ = G._run(eng, r.states.iloc[j0].to_numpy(), load_profile(sc, T), p, t[j0])
        err[width] = np.max(np.abs(X[:7, -1] - r.states.iloc[j1].to_numpy()[:7]))
    assert err[eng.idle_smoothing] < 2e-5  # rad, a hundredth of the spindle gap
    if not imbalance:
        assert err[eng.smoothing] > 1e-4


def test_idle_elements_start_inside_their_swinging_gaps(mill):
    from ident.model.effects import SpindleImbalance

    eng = G.build_engine(mill, (SpindleImbalance("C46"),), dt=1e-3, n_samples=50,
                         compile=False)
    w = Window(t=1.3 + np.arange(50) * 1e-3, elements=("C46",), y=np.zeros(50), t_step=1.33,
               kind="bite", level_before=0.0, level_after=2e5, bar=0)
    p = eng.base_params()
    p[eng.p_index("spindle_imbalance@C46.gate")] = 1.0
    p[eng.p_index("spindle_imbalance@C46.amplitude")] = 1.5e-3
    shift = SpindleImbalance("C46").open_shift(mill, 1.5e-3, 0.0, float(w.t[0]))
    assert abs(shift) > 5e-4  # the case worth testing: the gap has swung
    j = mill.element_ids.index("C46")
    a, b = mill.mass_index("Q4"), mill.mass_index("Q6")
    for frac in (0.0, 0.5, 1.0):
        wp = G.initial_window_params(eng, [w])[0]
        wp[G.WINDOW_PARAMS.index("frac")] = frac
        x = G.initial_state(eng, w, p, wp)
        delta = x[a] - x[b]
        gap = mill.elements[j].gap
        assert shift - gap - 1e-9 <= delta <= shift + 1e-9
        assert delta == pytest.approx(shift - frac * gap)


def test_a_bite_after_a_release_may_start_from_its_simulated_idle_or_at_rest(mill):
    """An idle rattle is sensitive: the simulated start is offered, not forced."""
    from ident.model.effects import SpindleImbalance

    eng = G.build_engine(mill, (SpindleImbalance("C46"),), dt=1e-3, n_samples=100)
    w = Window(t=3.0 + np.arange(100) * 1e-3, elements=TORQUES, y=np.ones((100, 4)),
               t_step=3.05, kind="bite", level_before=0.0, level_after=2e5, bar=1,
               history=(1.5, 2e5, 0.0, 0.02))
    p = eng.base_params()
    p[eng.p_index("spindle_imbalance@C46.gate")] = 1.0
    p[eng.p_index("spindle_imbalance@C46.amplitude")] = 1e-3
    rows = G.ramp_starts(eng, w, p, G.initial_window_params(eng, [w])[0], k=1)
    assert sorted(G.uses_history(eng, w, p, r) for r in rows) == [False, True]
    off = eng.base_params()  # candidate gated off: nothing ties the idle to the roll angle
    assert not G.can_use_history(eng, w, off)
    assert len(G.ramp_starts(eng, w, off, G.initial_window_params(eng, [w])[0], k=1)) == 1


@pytest.mark.parametrize("bars, folds", [((0, 1), ((0,), (1,))),
                                         ((0, 1, 2), ((0,), (1,), (2,))),
                                         ((0, 1, 2, 3, 4), ((0, 2, 4), (1, 3)))])
def test_every_fold_trains_on_two_bars_where_there_are_three(bars, folds):
    from ident.discrepancy.workflow import fold_bars

    got = fold_bars(bars)
    assert got == folds
    assert sorted(b for f in got for b in f) == list(bars)


# ---- residual analysis -------------------------------------------------------------------------
def test_residual_analysis_locates_phase_frequency_load_and_roll_angle(mill):
    dt, n = 1e-3, 450
    f1 = natural_modes(mill).frequencies_hz[0]
    roll = mill.motor_speed / 2.5  # rad/s of the rolls (ratio 2.5)
    wins, res = [], []
    for k, load in enumerate((1e5, 2e5, 3e5, 4e5)):
        t0 = 1.0 + 3.3 * k
        t = t0 + np.arange(n) * dt
        w = Window(t=t, elements=("C12",), y=np.zeros(n), t_step=t0 + 0.05, kind="bite",
                   level_before=0.0, level_after=load, bar=k, label=f"bar{k}")
        s = t - (w.t_step + 0.01)
        impact = (s >= 0) & (s < 0.06)
        r = np.where(impact, 1e-6 * load * np.sin(2 * np.pi * f1 * t), 0.0)
        wins.append(w)
        res.append(r[:, None])
    rep = analyse_residuals(mill, wins, res, ("C12",), rises=[0.02] * 4)
    assert rep.by_phase["impact"] > 10 * max(rep.by_phase["ring_down"], 1e-12)
    assert rep.by_phase["steady"] == 0.0
    assert rep.load_correlation > 0.95
    assert rep.by_window["bar3"] > rep.by_window["bar0"]
    # a ringing residual shows in its mode's band
    f6 = natural_modes(mill).frequencies_hz[-1]
    ring = [np.sin(2 * np.pi * f6 * w.t)[:, None] for w in wins]
    rep1 = analyse_residuals(mill, wins, ring, ("C12",))
    assert max(rep1.bands, key=rep1.bands.get) == f"mode {f6:.1f} Hz"
    assert rep1.peak_hz == pytest.approx(f6, abs=1.0)
    # a residual that follows twice the roll angle is explained by it
    res2 = [np.sin(2 * roll * w.t)[:, None] + 0.0 for w in wins]
    rep2 = analyse_residuals(mill, wins, res2, ("C12",))
    assert rep2.roll_angle_share > 0.95
    d = rep.to_dict()
    assert set(d) >= {"nrmse", "by_window", "by_channel", "by_phase", "bands",
                      "load_correlation", "roll_angle_share"}


# ---- decision rule ------------------------------------------------------------------------------
def _refit(key, imp, folds, bic=-100.0, score=1.0):
    e, loc = key.split("@")
    return Refit(effect=e, location=loc, score=score, params=(), nrmse=1 - imp,
                 improvement=imp, fold_improvements=folds, train_nrmse=(), delta_bic=bic)


@pytest.mark.parametrize("refits, named, why", [
    ([_refit("coulomb_friction@C46", 0.5, (0.4, 0.6)),
      _refit("coulomb_friction@C57", 0.1, (0.1, 0.1), score=0.5)], "coulomb_friction@C46",
     "lower"),
    ([_refit("spindle_imbalance@C57", 0.5, (0.4, 0.6)),
      _refit("spindle_imbalance@C46", 0.1, (0.1, 0.1), score=0.95)], None, "cannot tell"),
    ([_refit("coulomb_friction@C46", 0.1, (0.1, 0.1))], None, "< 30 %"),
    ([_refit("coulomb_friction@C46", 0.5, (0.9, 0.01))], None, "every fold"),
    ([_refit("coulomb_friction@C46", 0.5, (0.5, 0.5), bic=50.0)], None, "pay for"),
    ([_refit("coulomb_friction@C46", 0.5, (0.5, 0.5)),
      _refit("coulomb_friction@C57", 0.49, (0.5, 0.5))], None, "alike"),
    ([], None, "no candidate"),
])
def test_decision_rule_names_only_a_clear_winner_on_held_out_data(refits, named, why):
    effect, loc, explained, reason = DecisionRule().decide(refits)
    assert explained == (named is not None)
    assert (f"{effect}@{loc}" if explained else None) == named
    assert why in reason


# ---- hidden-effect generator --------------------------------------------------------------------
def test_hidden_backlash_is_a_gap_where_the_given_mill_says_tight(mill):
    case = hidden_effect_case(mill, "backlash", seed=5, n_bars=1)
    loc = case.location
    assert case.mill.element(loc).gap == 0.0
    assert case.truth_mill.element(loc).gap == pytest.approx(case.params["gap"])
    lo, hi = STRENGTHS["backlash"]["gap"]
    assert lo <= case.params["gap"] <= hi
    assert case.expected == ("backlash", loc)
    assert case.recording.channels == tuple(c.name for c in mill.torque_channels())


@pytest.mark.parametrize("effect", [e for e in EFFECT_NAMES if e != "backlash"])
def test_hidden_effects_are_drawn_from_the_seed_and_absent_from_the_mill(mill, effect):
    a = hidden_effect_case(mill, effect, seed=11, n_bars=1)
    assert a.mill == mill  # the mill file given to the workflow does not mention it
    assert a.location in candidate_locations(mill, effect)
    assert a.expected == (effect, a.location)


def test_hidden_effect_cases_repeat_with_their_seed(mill):
    a = hidden_effect_case(mill, "coulomb_friction", seed=11, n_bars=1)
    b = hidden_effect_case(mill, "coulomb_friction", seed=11, n_bars=1)
    c = hidden_effect_case(mill, "coulomb_friction", seed=12, n_bars=1)
    assert a.params == b.params and a.location == b.location
    np.testing.assert_array_equal(a.devices[0].data, b.devices[0].data)
    assert c.params != a.params
    lo, hi = STRENGTHS["coulomb_friction"]["v_smooth"]
    assert lo <= a.params["v_smooth"] <= hi


def test_controls_have_nothing_to_name(mill):
    for effect in CONTROLS:
        case = hidden_effect_case(mill, effect, seed=3, n_bars=1)
        assert case.expected == (None, None)
    f = hidden_effect_case(mill, "sensor_filter", seed=3, n_bars=1)
    assert f.location in TORQUES and 18.0 <= f.params["cutoff_hz"] <= 35.0


def test_hidden_effect_case_refuses_unknown_effects(mill):
    with pytest.raises(IdentError, match="effect must be one of"):
        hidden_effect_case(mill, "gear_whine", seed=1)


# ---- workflow input errors ----------------------------------------------------------------------
def test_discrepancy_needs_two_bars(mill, truth):
    _, wins = truth
    with pytest.raises(FitError, match="at least two bars. Got 1 bar"):
        discrepancy(wins[:2], mill)


def test_discrepancy_needs_torque_channels(mill):
    from ident.io.recording import Recording

    rec = Recording(frames={"/telemetry/accel": pd.DataFrame({"A_B23_v": np.zeros(10)})},
                    rates_hz={"/telemetry/accel": 10_000.0})
    with pytest.raises(RecordingError, match="needs torque channels"):
        discrepancy(rec, mill)


def test_cli_refuses_bad_options_with_exit_2(mill_path, tmp_path, capsys):
    from ident.cli import main

    rec = tmp_path / "missing.mcap"
    assert main(["discrepancy", str(rec), "--mill", str(mill_path), "--n-refit", "0"]) == 2
    assert "--n-refit must be at least 1" in capsys.readouterr().err
    assert main(["discrepancy", str(rec), "--mill", str(mill_path)]) == 2
    assert "missing.mcap" in capsys.readouterr().err
