"""The simulator against independent truth: closed forms, step halving, statics, the seed's Fig. 3."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import ident
from ident.model.dynamics import Family, ModelOptions, build_driveline
from ident.model.linear import natural_modes
from ident.model.scenario import Bar, Scenario, load_profile, random_scenario
from ident.model.simulate import sensor_devices, simulate, taf_table

ROOT = Path(__file__).resolve().parents[1]
HSM = ROOT / "data" / "mills" / "hsm-f1.toml"

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


@pytest.fixture(scope="module")
def hsm():
    return ident.load_mill(HSM)


def _gapped(mill, gap, open_frac=1.0, elements=("C12", "C34", "C46", "C57")):
    ov = {}
    for e in elements:
        ov[f"{e}.gap"] = gap
        ov[f"{e}.gap_open"] = gap * open_frac
    return mill.with_overrides(ov)


def test_two_mass_ring_frequency_and_amplitude_match_closed_form():
    """Free undamped two-mass system, (near) step load T on the roll: the shaft torque
    oscillates at f = sqrt(k (J1+J2)/(J1 J2)) / 2 pi about T*J_M/(J_M+J_R) with an amplitude
    equal to that mean (it swings between 0 and twice the mean)."""
    mill = ident.parse_mill(TWO_MASS)
    T = 1.0e5
    sc = Scenario(duration=1.0, bars=(Bar(t_bite=0.1, t_release=10.0, static_torque=T,
                                          rise_time=1e-4),))
    r = simulate(mill, sc, rate_hz=20_000.0, max_step=2.5e-5)
    t = r.time
    tau = r.outputs["tau:S"].to_numpy()
    sel = t > 0.2
    J1, J2, k = 2.0e3, 6.0e3, 4.0e7
    f_true = math.sqrt(k * (J1 + J2) / (J1 * J2)) / (2 * math.pi)
    mean_true = T * J1 / (J1 + J2)
    hi, lo = tau[sel].max(), tau[sel].min()
    assert 0.5 * (hi + lo) == pytest.approx(mean_true, rel=2e-3)
    assert 0.5 * (hi - lo) == pytest.approx(mean_true, rel=2e-3)  # undamped: TAF 2 about 0
    # frequency from zero crossings of the oscillation about the mean
    x = tau[sel] - mean_true
    zc = np.where(np.diff(np.sign(x)) > 0)[0]
    f_meas = (len(zc) - 1) / (t[sel][zc[-1]] - t[sel][zc[0]])
    assert f_meas == pytest.approx(f_true, rel=1e-3)
    assert natural_modes(mill).frequencies_hz[0] == pytest.approx(f_true, rel=1e-9)


def test_step_halving_converges_for_nonsmooth_g1(hsm):
    """Exact g1 kinks integrated by fixed-step RK4: halving the step from the default
    5e-5 s changes no torque by more than 1e-4 of the static torque, and the changes shrink."""
    mill = _gapped(hsm, 0.008)
    T = 2.0e5
    sc = Scenario(duration=1.0, bars=(Bar(t_bite=0.2, t_release=0.8, static_torque=T),))
    ys = {h: simulate(mill, sc, options=ModelOptions(), max_step=h).outputs.filter(like="tau:")
          .to_numpy() for h in (1e-4, 5e-5, 2.5e-5)}
    d1 = np.max(np.abs(ys[1e-4] - ys[5e-5])) / T
    d2 = np.max(np.abs(ys[5e-5] - ys[2.5e-5])) / T
    assert d2 < 1e-4
    assert d2 < d1


def test_compiled_and_virtual_machine_agree(hsm):
    mill = _gapped(hsm, 0.006)
    sc = Scenario(duration=0.6, bars=(Bar(t_bite=0.1, t_release=0.5, static_torque=2e5),))
    a = simulate(mill, sc, options=ModelOptions(), compile=True)
    b = simulate(mill, sc, options=ModelOptions(), compile=False)
    np.testing.assert_allclose(a.outputs.to_numpy(), b.outputs.to_numpy(), rtol=1e-9, atol=1e-3)


def test_static_load_split_and_speed_loop(hsm):
    """Steady rolling: every element carries its static share of the load (motor shaft the
    whole, each spindle its share), the motor supplies it, and the PI loop brings the motor
    speed back to nominal (integral action)."""
    T = 3.0e5
    sc = Scenario(duration=4.0, bars=(Bar(t_bite=0.2, t_release=10.0, static_torque=T),))
    r = simulate(hsm, sc, options=ModelOptions())
    last = r.outputs.iloc[-1]
    assert last["tau:C12"] == pytest.approx(T, rel=1e-3)
    assert last["tau:C34"] == pytest.approx(T, rel=1e-3)
    assert last["tau:C46"] == pytest.approx(0.5 * T, rel=1e-3)
    assert last["tau:C57"] == pytest.approx(0.5 * T, rel=1e-3)
    assert last["T_motor"] == pytest.approx(T, rel=1e-3)
    w = r.states["omega:Q1"].to_numpy()
    assert w.min() < -1e-3  # the bite slows the motor down ...
    assert abs(w[-1]) < 1e-2 * abs(w.min())  # ... and the speed loop recovers


@pytest.mark.parametrize("gap", [0.004, 0.008, 0.012])
def test_seed_fig3_lower_static_torque_gives_larger_taf(hsm, gap):
    """Seed Fig. 3: for a given angular gap, the TAF in the motor shaft (C12) falls as the
    static torque rises; with the gap closed it hardly depends on the static torque."""
    mill = _gapped(hsm, gap)
    tafs = []
    for T in (1.0e5, 2.0e5, 4.0e5):
        sc = Scenario(duration=1.2, bars=(Bar(t_bite=0.2, t_release=1.1, static_torque=T),))
        tafs.append(taf_table(simulate(mill, sc, options=ModelOptions()))
                    .set_index("element").loc["C12", "taf"])
    assert tafs[0] > tafs[1] > tafs[2] > 1.0


def test_seed_fig3_larger_gap_gives_larger_taf_and_closed_gap_is_flat(hsm):
    T = 2.0e5
    sc = Scenario(duration=1.2, bars=(Bar(t_bite=0.2, t_release=1.1, static_torque=T),))
    tafs = [taf_table(simulate(_gapped(hsm, g), sc, options=ModelOptions()))
            .set_index("element").loc["C12", "taf"] for g in (0.0, 0.004, 0.008, 0.012)]
    assert all(a < b for a, b in zip(tafs, tafs[1:]))
    closed = []
    for T in (1.0e5, 4.0e5):
        sc = Scenario(duration=1.2, bars=(Bar(t_bite=0.2, t_release=1.1, static_torque=T),))
        closed.append(taf_table(simulate(_gapped(hsm, 0.0), sc, options=ModelOptions()))
                      .set_index("element").loc["C12", "taf"])
    assert closed[0] == pytest.approx(closed[1], rel=0.02)


def test_bearing_rests_on_its_clearance_and_carries_mesh_force(hsm):
    """Idle: the shaft lies on the bottom of its clearance and nothing moves.  Rolling:
    the bearing force balances the mesh force along the pressure angle plus the weight."""
    T = 3.0e5
    sc = Scenario(duration=2.5, bars=(Bar(t_bite=0.5, t_release=10.0, static_torque=T),))
    r = simulate(hsm, sc)
    b = hsm.bearing("B23")
    out = r.outputs
    idle = out.loc[0.1:0.4]
    assert np.max(np.abs(idle["acc:B23:v"])) < 1e-3
    assert idle["shaft:B23:y"].iloc[-1] < -b.clearance
    assert abs(idle["shaft:B23:x"].iloc[-1]) < 1e-9
    W = b.shaft_mass * 9.80665
    F_mesh = T * b.ratio / b.base_radius  # C23 carries the whole load
    a = math.radians(b.pressure_angle_deg)
    expected = math.hypot(F_mesh * math.sin(a), F_mesh * math.cos(a) - W)
    assert out["F:B23"].iloc[-1] == pytest.approx(expected, rel=1e-3)
    # the shaft has moved up and sideways, towards the line of action
    assert out["shaft:B23:y"].iloc[-1] > 0 and out["shaft:B23:x"].iloc[-1] > 0
    # the bite shakes the housing
    assert np.max(np.abs(out.loc[0.5:0.7, "acc:B23:v"])) > 1.0


def test_load_profile_half_height_at_t_step():
    bar = Bar(t_bite=1.0, t_release=3.0, static_torque=1e5, rise_time=0.03, fall_time=0.02)
    sc = Scenario(duration=4.0, bars=(bar,))
    assert load_profile(sc, np.array([bar.t_step_bite]))[0] == pytest.approx(5e4)
    assert load_profile(sc, np.array([bar.t_step_release]))[0] == pytest.approx(5e4)
    assert load_profile(sc, np.array([0.5, 2.0, 3.5])) == pytest.approx([0.0, 1e5, 0.0])


def test_random_scenario_bars_do_not_overlap(hsm):
    sc = random_scenario(hsm, n_bars=6, rng=np.random.default_rng(3))
    ends = [b.t_release + b.fall_time for b in sc.bars]
    for bar, prev_end in zip(sc.bars[1:], ends):
        assert bar.t_bite > prev_end
    assert sc.duration >= ends[-1]
    torques = [b.static_torque for b in sc.bars]
    assert max(torques) > 1.2 * min(torques)


def test_sensor_devices_units_noise_and_quantisation(hsm):
    sc = Scenario(duration=2.0, bars=(Bar(t_bite=0.3, t_release=1.7, static_torque=2e5),))
    r = simulate(hsm, sc)
    devs = {d.name: d for d in sensor_devices(r, rng=np.random.default_rng(0), snr_db=35.0)}
    tq = devs["/telemetry/torque"]
    acc = devs["/telemetry/accel"]
    assert tq.rate_hz == 2000.0 and acc.rate_hz == 10000.0
    assert tq.channels == ("T_C12", "T_C34", "T_C46", "T_C57")
    assert tq.units == ("kN*m",) * 4
    i46 = tq.channels.index("T_C46")
    truth_kNm = r.outputs["tau:C46"].to_numpy()[::5] * 2.5 / 1e3  # physical = reduced * ratio
    x = tq.data[i46]
    noise = x - truth_kNm
    snr = 20 * np.log10(np.sqrt(np.mean(truth_kNm ** 2)) / np.std(noise))
    assert snr == pytest.approx(35.0, abs=1.0)
    # 16-bit quantisation: values sit on a grid
    steps = np.diff(np.unique(x))
    lsb = steps.min()
    assert np.allclose(np.round(steps / lsb), steps / lsb, atol=1e-3)
    assert len(np.unique(x)) <= 2 ** 16
    assert acc.units == ("g",) * 4


@pytest.mark.parametrize("family", [Family.G2, Family.G3, Family.G4])
def test_other_families_run_and_carry_the_static_load(hsm, family):
    mill = _gapped(hsm, 0.006, open_frac=0.5)
    sc = Scenario(duration=2.5, bars=(Bar(t_bite=0.2, t_release=10.0, static_torque=2e5),))
    r = simulate(mill, sc, options=ModelOptions(family=family))
    assert r.outputs["tau:C12"].iloc[-1] == pytest.approx(2e5, rel=1e-3)


def test_driveline_parameters_named_per_element(hsm):
    drv = build_driveline(hsm, ModelOptions())
    assert drv.param_names[:2] == ("C12.gap", "C12.gap_open")
    assert drv.params({"C46.gap": 0.01})[drv.param_index("C46.gap")] == 0.01
    assert drv.state_names[0] == "theta:Q1" and drv.state_names[7] == "omega:Q1"
