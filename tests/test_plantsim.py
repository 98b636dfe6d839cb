"""Tests of the independent plant simulator ``validation.plantsim`` itself.

Each test simulates one or two short recordings (well under a second of CPU each at
20 kHz); none is slow.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

import ident
from ident.io import read_recording
from validation import plantsim as ps

REPO = Path(__file__).resolve().parents[1]
MILLS = {name: ident.load_mill(REPO / "data" / "mills" / f"{name}.toml")
         for name in ("hsm-f1", "cold-s5")}

TWO_MASS = """
[mill]
name = "two-mass"
[operation]
motor_speed_rpm = 300.0
[[mass]]
id = "Q1"
J = 10.0
[[mass]]
id = "Q2"
J = 5.0
[[element]]
id = "C12"
from = "Q1"
to = "Q2"
k = 4.0e5
c = 4.0
[load]
masses = ["Q2"]
share = [1.0]
[motor]
mass = "Q1"
kp = 30.0
ki = 100.0
[[channel]]
name = "T_C12"
quantity = "torque"
element = "C12"
unit = "N*m"
"""


def _record(name: str, seed: int, **kw) -> tuple[ident.Mill, ps.PlantDraw, ps.PlantRecording]:
    mill = MILLS[name]
    draw = ps.draw_plant(mill, np.random.default_rng(seed), **kw)
    return mill, draw, ps.simulate_plant(mill, draw)


def _total_estimate(mill: ident.Mill, rec: ps.PlantRecording, values: np.ndarray) -> np.ndarray:
    """Mean over the channels nearest the rolls of reduced torque / load fraction, N*m."""
    frac = ps.load_fractions(mill)
    near = rec.truth["nearest_channels"]
    out = np.zeros(values.shape[1])
    for c in near:
        i = rec.channels.index(c)
        ch = mill.channel(c)
        out += values[i] * ps.UNIT_TO_SI[ch.unit] / mill.element(ch.element).ratio / frac[ch.element]
    return out / len(near)


# ---- physics -------------------------------------------------------------------------------
def test_never_imports_ident_model_or_fit():
    tree = ast.parse((REPO / "validation" / "plantsim.py").read_text())
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            mods.add(node.module)
    assert not [m for m in mods if m.startswith(("ident.model", "ident.fit"))], mods


def test_step_halving_agrees():
    mill = MILLS["cold-s5"]
    draw = ps.draw_plant(mill, np.random.default_rng(3), n_bars=1, rate_hz=2000.0,
                         accelerometers=False)
    a = ps.simulate_plant(mill, draw, rate_hz=20000.0)
    b = ps.simulate_plant(mill, draw, rate_hz=40000.0)
    pa, pb = a.physics, b.physics[:, ::2][:, :a.physics.shape[1]]
    peak = np.abs(pb).max(axis=1)
    assert np.all(np.abs(pa - pb).max(axis=1) < 2e-3 * peak)
    rms = np.sqrt(np.mean((pa - pb) ** 2, axis=1))
    assert np.all(rms < 2e-4 * peak)
    for sa, sb in zip(a.truth["steps"], b.truth["steps"]):
        assert abs(sa["t_step"] - sb["t_step"]) < 1e-4


def test_two_mass_ring_down_frequency(tmp_path):
    (tmp_path / "m.toml").write_text(TWO_MASS)
    mill = ident.load_mill(tmp_path / "m.toml")
    J1, J2, k = 10.0, 5.0, 4.0e5
    f_true = math.sqrt(k * (J1 + J2) / (J1 * J2)) / (2 * math.pi)
    draw = ps.draw_plant(mill, np.random.default_rng(0), n_bars=1, rate_hz=5000.0, level=2000.0)
    bar = draw.bars[0]
    bite = ps.Ramp(bar.bite.t_start, 0.001, "linear")
    draw = dataclasses.replace(draw, bars=(dataclasses.replace(bar, bite=bite, fluct=(),
                                                              trend=0.0),))
    rec = ps.simulate_plant(mill, draw)
    fs = rec.sim_rate_hz
    t = np.arange(rec.physics.shape[1]) / fs
    m = (t > bite.t_start + 0.01) & (t < bite.t_start + 0.6)
    x = rec.physics[0, m] - np.polyval(np.polyfit(t[m], rec.physics[0, m], 2), t[m])
    s = np.signbit(x)
    i = np.flatnonzero(s[1:] != s[:-1])
    tc = t[m][i] + x[i] / (x[i] - x[i + 1]) / fs          # interpolated zero crossings
    f_est = 1.0 / (2.0 * np.polyfit(np.arange(tc.size), tc, 1)[0])
    assert f_est == pytest.approx(f_true, rel=1e-4)


def test_starts_at_rest_in_steady_state():
    mill, draw, rec = _record("hsm-f1", 4, n_bars=1, accelerometers=False)
    first = rec.physics[:, : int(0.5 * rec.sim_rate_hz)]
    level = np.abs(rec.physics).max(axis=1)
    assert np.all(np.ptp(first, axis=1) < 1e-9 * level)


def test_gap_open_realised_and_reposition_invisible():
    mill, draw, rec = _record("hsm-f1", 11, n_bars=3, accelerometers=False)
    assert set(draw.floating) == {"C46", "C57"}
    bites = [s for s in rec.truth["steps"] if s["kind"] == "bite"]
    for b, (bar, step) in enumerate(zip(draw.bars, bites)):
        for eid, gap in draw.gaps.items():
            go = step["gap_open"][eid]
            assert 0.0 <= go <= gap + 1e-15
            if eid in draw.floating:       # drawn open part, up to the idle drift
                assert abs(go - bar.gap_open[eid]) < 0.25 * gap
            else:                          # held against the drive flank by friction
                assert go == 0.0
        if bar.t_reposition is not None:  # the move shows in no torque channel
            k = int(round(bar.t_reposition * rec.sim_rate_hz))
            jump = np.abs(rec.physics[:, k] - rec.physics[:, k - 1])
            assert np.all(jump < 1e-3 * np.abs(rec.physics).max(axis=1))


def test_gaps_argument_and_draw_ranges():
    mill = MILLS["cold-s5"]
    d = ps.draw_plant(mill, np.random.default_rng(1), gaps={"C45": 0.006})
    assert d.gaps == {"C12": 0.001, "C23": 0.0008, "C34": 0.0, "C45": 0.006}
    for seed in range(5):
        d = ps.draw_plant(mill, np.random.default_rng(seed))
        for e in mill.elements:
            assert (d.gaps[e.id] == 0.0) if e.gap == 0 else (0.5 * e.gap <= d.gaps[e.id] <= 3 * e.gap)
        assert d.rate_hz in ps.RECORD_RATES_HZ
        assert 1.0 <= d.bars[0].bite.t_start <= 2.5


# ---- recording chain -----------------------------------------------------------------------
def test_noise_after_chain_matches_truth_sigma():
    checked = 0
    for name, seed in (("cold-s5", 0), ("hsm-f1", 2)):
        mill, draw, rec = _record(name, seed, n_bars=1, accelerometers=False)
        m = int(rec.rate_hz)                     # the last second: idle
        t = rec.time[-m:]
        for i, c in enumerate(rec.channels):
            y, yc = rec.data[i, -m:], rec.clean[i, -m:]
            res = y - np.polyval(np.polyfit(t, y, 3), t)
            quiet = yc - np.polyval(np.polyfit(t, yc, 3), t)
            sigma = rec.truth["channels"][c]["sigma_with_quantisation"]
            assert quiet.std() < 0.2 * sigma      # physics is still there
            assert res.std() == pytest.approx(sigma, rel=0.1)
            checked += 1
            ch = rec.truth["channels"][c]
            si = ps.UNIT_TO_SI[ch["unit"]] / ch["ratio"]
            assert ch["sigma_si_reduced"] == pytest.approx(ch["sigma"] * si)
            assert 0.002 <= ch["sigma"] / ch["rolling_level"] <= 0.02
    assert checked == 7


def test_quantisation_step_is_full_scale_over_65536():
    mill, draw, rec = _record("cold-s5", 5, n_bars=1, accelerometers=False)
    for i, c in enumerate(rec.channels):
        ch = rec.truth["channels"][c]
        fsc, q = ch["full_scale"], ch["quant_step"]
        assert q == fsc / 65536
        mant = fsc / 10 ** math.floor(math.log10(fsc))
        assert min(abs(mant - v) for v in (1.0, 2.0, 5.0)) < 1e-9
        peak = np.abs(rec.data[i]).max()
        assert 2 * peak <= fsc * (1 + 1e-12) and fsc < 5 * peak
        n = rec.data[i] / q
        assert np.allclose(n, np.round(n), atol=1e-6)
        steps = np.diff(np.unique(rec.data[i]))
        assert steps.min() == pytest.approx(q, rel=1e-6)


def test_t_step_is_at_half_height_of_the_clean_torque():
    mill, draw, rec = _record("hsm-f1", 8, n_bars=2, accelerometers=False)
    est = _total_estimate(mill, rec, rec.clean)
    t = rec.time
    fs = rec.rate_hz
    for s in rec.truth["steps"]:
        a = s["t_load_start"]
        pre = est[(t > a - 0.2) & (t < a - 0.01)].mean()
        if s["kind"] == "bite":            # level after the bite: a second's mean of the ring-down
            w = (t > a + s["rise_s"] + 0.3) & (t < a + s["rise_s"] + 1.3)
        else:
            w = (t > a + s["rise_s"] + 0.8) & (t < a + s["rise_s"] + 1.3)
        post = est[w].mean()
        assert post - pre == pytest.approx(s["step"], rel=0.05)
        half = 0.5 * (pre + post)
        i = int(round(s["t_step"] * fs))
        lo, hi = sorted((est[i - 1], est[i + 1]))
        assert lo - 0.03 * abs(s["step"]) <= half <= hi + 0.03 * abs(s["step"])
        # no earlier crossing since the load began
        j = int(math.floor(a * fs))
        seg = est[j:i - 1] - half
        assert np.all(seg < 0) if s["kind"] == "bite" else np.all(seg > 0)
        assert s["t_load_start"] < s["t_step"] < s["t_load_start"] + s["rise_s"] + 0.05


# ---- files ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["hsm-f1", "cold-s5"])
@pytest.mark.parametrize("fmt", ["csv", "mcap"])
def test_files_round_trip_through_ident_reader(name, fmt, tmp_path):
    mill, draw, rec = _record(name, 21, n_bars=1)
    path = tmp_path / f"rec.{fmt}"
    tp = ps.write_plant(rec, path)
    assert tp == tmp_path / "rec.truth.json"
    truth = json.loads(tp.read_text())
    assert truth["mill"] == name and set(truth["elements"]) == set(mill.element_ids)
    assert set(truth["channels"]) == {c.name for c in mill.channels}
    got = read_recording(path, mill, warn=False)
    assert len(got.frames) == 2
    frames = {("accel" if "accel" in k else "torque"): (f, got.rates_hz[k])
              for k, f in got.frames.items()}
    for dev, key, names in ((rec, "torque", mill.torque_channels()),
                            (rec.accel, "accel", mill.acceleration_channels())):
        frame, rate = frames[key]
        assert rate == pytest.approx(dev.rate_hz)
        assert list(frame.columns) == [c.name for c in names]
        assert len(frame) == dev.data.shape[1]
        assert np.allclose(frame.index.to_numpy(), dev.time, atol=1e-6)
        for i, c in enumerate(dev.channels):
            unit = mill.channel(c).unit
            si = dev.data[i] * (ps.UNIT_TO_SI | ps.ACCEL_UNIT_TO_SI)[unit]
            assert np.allclose(frame[c].to_numpy(np.float64), si, rtol=1e-6,
                               atol=1e-6 * np.abs(si).max())
    assert frames["accel"][0].index[0] == pytest.approx(truth["accel"]["t_offset"], abs=1e-6)
    assert 0.0 <= truth["accel"]["t_offset"] <= 0.05
    assert not [q for q in got.issues if q.kind in ("clipped", "rate_mismatch", "dropout",
                                                    "non_monotonic", "unit_mismatch",
                                                    "missing_channel")]
    if fmt == "csv":
        header = path.read_text().splitlines()[0].split(",")
        assert header == ["time"] + [f"{c.name} [{c.unit}]" for c in mill.torque_channels()]
        assert ps.accel_csv_path(path).exists()
        times = np.loadtxt(path, delimiter=",", skiprows=1, usecols=0)
        assert np.all(np.diff(times) > 0)


# ---- accelerometers ------------------------------------------------------------------------
def test_accelerometers_start_at_rest_and_converge_until_the_rattle():
    mill = MILLS["hsm-f1"]
    draw = ps.draw_plant(mill, np.random.default_rng(3), n_bars=1, rate_hz=2000.0,
                         accel_rate_hz=20000.0)
    a = ps.simulate_plant(mill, draw, rate_hz=20000.0).accel
    b = ps.simulate_plant(mill, draw, rate_hz=40000.0).accel   # bearing model 100 -> 200 kHz
    release = draw.bars[0].release.t_start - draw.t_rec0
    before = a.time < release
    after = (a.time > release) & (a.time < release + 0.5)
    for i in range(len(a.channels)):
        x, y = a.clean[i], b.clean[i]
        assert np.abs(y[a.time < 1.0]).max() < 1e-9           # static start, no transient
        assert np.abs(x[before] - y[before]).max() < 3e-3 * np.abs(y[before]).max()
        # the release rattle (impacts in the clearance) is chaotic: its level converges
        rx, ry = np.sqrt(np.mean(x[after] ** 2)), np.sqrt(np.mean(y[after] ** 2))
        assert rx == pytest.approx(ry, rel=0.3)


def test_accelerometer_noise_and_quantisation():
    mill, draw, rec = _record("cold-s5", 0, n_bars=1)
    acc = rec.accel
    m = int(0.5 * acc.rate_hz)
    w = slice(int((0.3 - acc.t_offset) * acc.rate_hz), None)   # before the first bite
    for i, c in enumerate(acc.channels):
        ch = rec.truth["channels"][c]
        y, yc = acc.data[i, w][:m], acc.clean[i, w][:m]
        assert np.abs(yc).max() < 0.05 * ch["sigma"]
        assert (y - y.mean()).std() == pytest.approx(ch["sigma_with_quantisation"], rel=0.1)
        assert 0.001 <= ch["sigma"] / ch["level"] <= 0.01
        assert ch["sigma_si"] == pytest.approx(ch["sigma"] * ps.G0)
        n = acc.data[i] / ch["quant_step"]
        assert ch["quant_step"] == ch["full_scale"] / 65536
        assert np.allclose(n, np.round(n), atol=1e-6)
    assert set(rec.truth["bearings"]) == {"B23"}
    assert 0.5 * 1.5e-4 <= rec.truth["bearings"]["B23"]["clearance"] <= 10 * 1.5e-4


def test_make_recording_is_deterministic(tmp_path):
    mill = MILLS["cold-s5"]
    t1 = ps.make_recording(mill, 9, tmp_path / "a", n_bars=1, fmt="mcap")
    t2 = ps.make_recording(mill, 9, tmp_path / "b.mcap", n_bars=1, fmt="mcap")
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()
    assert json.dumps(t1, sort_keys=True) == json.dumps(t2, sort_keys=True)
    t3 = ps.make_recording(mill, 10, tmp_path / "c.csv", n_bars=1)
    assert t3["draw"] != t1["draw"]
    with pytest.raises(ValueError):
        ps.make_recording(mill, 9, tmp_path / "d.csv", fmt="mcap")
