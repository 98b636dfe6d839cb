"""The effects of effects.md as model terms: each does what effects.md's "typical signature" says.

Independent truth: closed forms on a two-mass system (Coulomb friction's
linear decay of 4F/k per cycle; the ring frequency sqrt(k (1/J1 + 1/J2)) and
its change to sqrt(k_after ...) beyond a knee), the mill file's own gap law
(an added backlash equals a gap in the mill file), a first-order lag solved
independently, and the physics the effects.md table names (strip coupling
locks the spindle torques in phase; spindle imbalance rattles at twice the
roll speed while idling and is weak under load).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import find_peaks

import ident
from ident.errors import IdentError
from ident.model import effects as E
from ident.model.dynamics import ModelOptions, build_driveline
from ident.model.scenario import Bar, Scenario, nominal_torque
from ident.model.simulate import simulate

TWO_MASS = """
[mill]
name = "two-mass"
[operation]
motor_speed_rpm = 100.0
[[mass]]
id = "M"
J = 2.0e3
[[mass]]
id = "R"
J = 6.0e3
[[element]]
id = "S"
from = "M"
to = "R"
k = 4.0e7
c = 0.0
[load]
masses = ["R"]
share = [1.0]
[motor]
mass = "M"
kp = 0.0
ki = 0.0
"""
K2, J1, J2 = 4.0e7, 2.0e3, 6.0e3
F_RING = math.sqrt(K2 * (1 / J1 + 1 / J2)) / (2 * math.pi)  # 26.0 Hz


@pytest.fixture(scope="module")
def two():
    return ident.parse_mill(TWO_MASS)


def _peak_hz(x: np.ndarray, rate: float) -> float:
    y = x - np.polyval(np.polyfit(np.arange(x.size), x, 1), np.arange(x.size))
    n = 1 << 16
    f = np.fft.rfftfreq(n, 1 / rate)
    return float(f[np.argmax(np.abs(np.fft.rfft(y * np.hanning(y.size), n)))])


# ---- the protocol ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", E.EFFECT_NAMES)
def test_every_effect_has_its_parameters_in_the_model_vector(mill, name):
    loc = E.candidate_locations(mill, name)[0] if name != "backlash" else "C23"
    eff = E.make_effect(name, loc)
    assert eff.name == name and eff.location == loc
    drv = build_driveline(mill, ModelOptions(effects=(eff,)))
    for pn, v in zip(eff.param_names, eff.param_defaults):
        assert drv.p_default[drv.param_index(f"{name}@{loc}.{pn}")] == pytest.approx(v)
    specs = eff.specs(mill)
    assert {s.name for s in specs} == set(eff.param_names)
    assert all(s.lower <= s.upper and s.scale > 0 for s in specs)


@pytest.mark.parametrize("name", [n for n in E.EFFECT_NAMES if n != "torque_loop_lag"])
def test_neutral_parameters_and_a_closed_gate_leave_the_model_unchanged(mill, name):
    loc = E.candidate_locations(mill, name)[0] if name != "backlash" else "C23"
    eff = E.make_effect(name, loc)
    base = build_driveline(mill, ModelOptions(smoothing=1e-4))
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1e-3, base.n_states)
    x[len(mill.masses):2 * len(mill.masses)] *= 100
    y0 = np.asarray(base.rhs(x, 2e5, base.p_default, 0.7)).ravel()
    for wrapped, params in ((eff, eff.neutral(mill)), (E.Gated(eff, 0.0), {})):
        drv = build_driveline(mill, ModelOptions(smoothing=1e-4, effects=(wrapped,)))
        p = drv.params({f"{eff.key}.{k}": v for k, v in params.items()})
        y = np.asarray(drv.rhs(x, 2e5, p, 0.7)).ravel()
        np.testing.assert_allclose(y, y0, rtol=1e-12, atol=1e-9)


def test_make_effect_and_locations_refuse_bad_input(mill):
    with pytest.raises(IdentError, match="unknown effect 'gear_whine'"):
        E.make_effect("gear_whine", "C12")
    with pytest.raises(IdentError, match="has no parameter"):
        E.make_effect("coulomb_friction", "C12", stiffness=1.0)
    with pytest.raises(IdentError, match="location must be an element"):
        build_driveline(mill, ModelOptions(effects=(E.CoulombFriction("C99"),)))
    with pytest.raises(IdentError, match="two different masses"):
        build_driveline(mill, ModelOptions(effects=(E.StripCoupling("Q6"),)))
    with pytest.raises(IdentError, match="the motor mass 'Q1'"):
        build_driveline(mill, ModelOptions(effects=(E.TorqueLoopLag("Q2"),)))


def test_candidate_locations_follow_the_mill(mill):
    assert E.candidate_locations(mill, "spindle_imbalance") == ("C46", "C57")
    assert E.candidate_locations(mill, "strip_coupling") == ("Q6-Q7",)
    assert E.candidate_locations(mill, "torque_loop_lag") == ("Q1",)
    assert E.candidate_locations(mill, "backlash") == ()  # every hsm-f1 element has a gap
    tight = mill.with_overrides({"C23.gap": 0.0})
    assert E.candidate_locations(tight, "backlash") == ("C23",)


# ---- signatures (effects.md, "typical signature") ----------------------------------------------
def test_coulomb_friction_decays_linearly_by_4F_over_k_per_cycle(two):
    F = 2e3
    opts = ModelOptions(effects=(E.CoulombFriction("S", force=F, v_smooth=1e-4),))
    x0 = build_driveline(two, opts).x_idle.copy()
    x0[0] = 2e-3  # twisted by 2 mrad, released from rest, no load, no controller
    r = simulate(two, Scenario(duration=0.6, bars=()), options=opts, x0=x0, compile=False,
                 rate_hz=10_000, max_step=2e-5)
    d = r.states["theta:M"].to_numpy() - r.states["theta:R"].to_numpy()
    pk, _ = find_peaks(d)
    peaks = d[pk][:6]
    # amplitude-independent decrement (a linear envelope), 4 F / k per cycle
    np.testing.assert_allclose(np.diff(peaks), -4 * F / K2, rtol=0.01)


@pytest.mark.parametrize("cls, ratio", [(E.SofteningStiffness, 0.5), (E.HardeningStiffness, 2.0)])
def test_knee_stiffness_changes_the_ring_frequency_only_at_large_torque(two, cls, ratio):
    opts = ModelOptions(effects=(cls("S", knee=1e-3, k_ratio=ratio),))
    freqs = []
    for L in (2e4, 4e5):  # element torque 5 kN*m (0.13 mrad) and 100 kN*m (2.5 mrad)
        sc = Scenario(duration=1.5, bars=(Bar(t_bite=0.1, t_release=5.0, static_torque=L,
                                              rise_time=0.1),))
        r = simulate(two, sc, options=opts, compile=False)
        freqs.append(_peak_hz(r.outputs["tau:S"].to_numpy()[r.time > 0.3], r.rate_hz))
    res = 1 / (1.2 * 1.0)  # FFT resolution over the 1.2 s analysed, Hz
    assert freqs[0] == pytest.approx(F_RING, abs=res)
    assert freqs[1] == pytest.approx(F_RING * math.sqrt(ratio), abs=res)


def test_backlash_on_a_tight_element_is_the_mill_files_gap(mill):
    tight = mill.with_overrides({f"{e}.{k}": 0.0 for e in mill.element_ids
                                 for k in ("gap", "gap_open")})
    gapped = tight.with_overrides({"C34.gap": 3e-3, "C34.gap_open": 1e-3})
    sc = Scenario(duration=1.2, bars=(Bar(t_bite=0.1, t_release=0.6, static_torque=3e5),))
    a = simulate(tight, sc, options=ModelOptions(bearings=False, effects=(
        E.Backlash("C34", gap=3e-3, gap_open=1e-3),)))
    b = simulate(gapped, sc, options=ModelOptions(bearings=False))
    c = simulate(tight, sc, options=ModelOptions(bearings=False))
    cols = ["tau:C12", "tau:C34", "tau:C46", "tau:C57"]
    scale = b.outputs[cols].abs().max().max()
    np.testing.assert_allclose(a.outputs[cols].to_numpy(), b.outputs[cols].to_numpy(),
                               atol=1e-6 * scale)
    # and the gap shows as impacts: high harmonics after the release (the load reverses
    # across the gap), which the driveline without gaps does not have
    def hf_share(r):
        x = r.outputs["tau:C34"].to_numpy()[r.time > 0.63]
        X = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(x.size))) ** 2
        f = np.fft.rfftfreq(x.size, 1 / r.rate_hz)
        return float(X[f > 100].sum() / X[f > 5].sum())
    assert hf_share(a) > 1e-4
    assert hf_share(a) > 1000 * hf_share(c)


def test_strip_coupling_locks_the_spindle_torques_in_phase(mill):
    sc = Scenario(duration=1.2, bars=(Bar(t_bite=0.2, t_release=5.0, static_torque=3e5),))

    def corr(effects):
        r = simulate(mill, sc, options=ModelOptions(bearings=False, effects=effects))
        m = r.time > 0.25
        t = r.time[m]
        x, y = (r.outputs[c].to_numpy()[m] for c in ("tau:C46", "tau:C57"))
        x = x - np.polyval(np.polyfit(t, x, 2), t)
        y = y - np.polyval(np.polyfit(t, y, 2), t)
        return float(np.corrcoef(x, y)[0, 1])
    assert corr(()) < 0.0
    assert corr((E.StripCoupling("Q6-Q7", k=1.5e7, c=3e3),)) > 0.8


def test_spindle_imbalance_rattles_at_twice_roll_speed_idling_and_is_weak_under_load(mill):
    eff = E.SpindleImbalance("C46", amplitude=1e-3, phase=0.3)
    f2 = 2 * eff.roll_speed_hz(mill)  # 2.4 Hz
    assert f2 == pytest.approx(2 * 180 / 60 / 2.5)
    sc = Scenario(duration=8.0, bars=(Bar(t_bite=4.0, t_release=7.5, static_torque=3e5),),
                  idle_torque=3e3)
    r = simulate(mill, sc, options=ModelOptions(bearings=False, effects=(eff,)))
    x = r.outputs["tau:C46"].to_numpy()

    def amp(a, b):
        m = (r.time > a) & (r.time < b)
        y = x[m] - x[m].mean()
        f = np.fft.rfftfreq(y.size, 1 / r.rate_hz)
        P = np.abs(np.fft.rfft(y * np.hanning(y.size))) * 4 / y.size
        return float(P[np.argmin(abs(f - f2)) - 1:np.argmin(abs(f - f2)) + 2].max()), \
            float(f[1 + np.argmax(P[1:])]), float(x[m].mean())
    a_idle, f_idle, mean_idle = amp(1.0, 3.9)
    a_load, _, mean_load = amp(5.0, 7.4)
    assert f_idle == pytest.approx(f2, abs=0.5)  # the idle spectrum peaks at 2x roll speed
    assert a_idle > 0.1 * abs(mean_idle)         # a rattle, large against the idle torque
    assert a_load < 0.01 * mean_load             # weak under load


def test_spindle_imbalance_swings_the_open_gap_with_twice_the_roll_angle(mill):
    eff = E.SpindleImbalance("C57", amplitude=5e-4, phase=0.7)
    drv = build_driveline(mill, ModelOptions(effects=(eff,)))
    i = mill.element_ids.index("C57")
    n = len(mill.masses)
    e = mill.element("C57")
    # the spindle pressed 1 mrad beyond its (nominal) drive-side contact, at rest
    x = drv.x_idle.copy()
    x[mill.mass_index("Q5")] = 1e-3
    ts = np.linspace(0, 1 / eff.roll_speed_hz(mill), 41)
    tau = np.array([float(drv.out(x, 0.0, drv.p_default, t)[i]) for t in ts])
    phi = mill.motor_speed * ts / e.ratio
    np.testing.assert_allclose(tau, e.k * (1e-3 - 5e-4 * np.sin(2 * phi + 0.7)),
                               rtol=1e-9)


def test_torque_loop_lag_is_a_first_order_lag_of_the_speed_loop_command(mill):
    tau = 0.015
    sc = Scenario(duration=0.8, bars=(Bar(t_bite=0.1, t_release=5.0, static_torque=3e5),))
    r = simulate(mill, sc, options=ModelOptions(bearings=False, effects=(
        E.TorqueLoopLag("Q1", tau=tau),)), rate_hz=10_000)
    cmd = (-mill.motor.kp * r.states["omega:Q1"].to_numpy()
           + mill.motor.ki * r.states["z"].to_numpy())
    tm = r.outputs["T_motor"].to_numpy()
    # integrate T' = (cmd - T) / tau independently (trapezoid) from the same start
    dt = 1 / r.rate_hz
    ref = np.empty_like(tm)
    ref[0] = tm[0]
    a = dt / (2 * tau)
    for k in range(1, tm.size):
        ref[k] = (ref[k - 1] * (1 - a) + a * (cmd[k] + cmd[k - 1])) / (1 + a)
    np.testing.assert_allclose(tm, ref, atol=2e-3 * np.max(np.abs(tm)))
    # the motor torque lags: it reaches half the load later than the ideal loop's
    ideal = simulate(mill, sc, options=ModelOptions(bearings=False), rate_hz=10_000)

    def t_half(y):
        return float(r.time[np.argmax(y > 1.5e5)])
    delay = t_half(tm) - t_half(ideal.outputs["T_motor"].to_numpy())
    assert 0.3 * tau < delay < 1.5 * tau


def test_sensor_filter_is_a_causal_low_pass_starting_at_rest():
    filt = E.SensorFilter("C46", cutoff_hz=25.0, order=2)
    rate = 2000.0
    t = np.arange(4000) / rate
    for f, gain in ((25.0, 1 / math.sqrt(2)), (2.0, 1.0), (200.0, 0.0)):
        y = filt.apply(np.sin(2 * math.pi * f * t), rate)[2000:]
        assert np.max(np.abs(y)) == pytest.approx(gain, abs=0.02)
    step = np.r_[np.zeros(100), np.ones(100)] + 5.0
    y = filt.apply(step, rate)
    np.testing.assert_allclose(y[:100], 5.0)  # at rest on the first value, nothing before the step
    with pytest.raises(IdentError, match="cutoff_hz must lie in"):
        E.SensorFilter("C46", cutoff_hz=1500.0).apply(step, rate)


def test_knee_guesses_spread_over_the_deflections_the_load_reaches(mill):
    """Guesses come from the data's load (not from any generator's ranges): fractions of
    the element's static deflection under the largest torque, up to that deflection."""
    from ident.segment.loadshare import load_fractions

    for cls in (E.SofteningStiffness, E.HardeningStiffness):
        eff = cls("C46")
        t = 2.0e5
        d = load_fractions(mill)["C46"] * t / mill.element("C46").k
        got = eff.knee_guesses(mill, torque=t)
        assert got == pytest.approx(tuple(f * d for f in eff.KNEE_FRACTIONS))
        assert max(got) == pytest.approx(d) and min(got) < 0.1 * d
        assert list(got) == sorted(got)
        assert eff.knee_guesses(mill, torque=2 * t) == pytest.approx(tuple(2 * g for g in got))
        # without a torque: the mill's nominal one
        assert eff.knee_guesses(mill) == pytest.approx(
            tuple(g * nominal_torque(mill) / t for g in got))
