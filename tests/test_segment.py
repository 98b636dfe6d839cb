"""Segmentation scored against the synthetic truth (tests/synth_telemetry.py), load shares.

Truth: each bar's bite/release half-height time, rolling torque (total, reduced to
the motor shaft) and step.  Tolerances: 5 ms for torque timing (the brief), 3 % for
levels (the synthetic load fluctuates by up to 2 % while rolling).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ident.description import Element
from ident.errors import RecordingError
from ident.io import RawDevice, read_recording, write_recording
from ident.segment import Segment, distance_to_load, load_fractions, segment_transients
from synth_telemetry import T0_NS, make_synth

SEEDS = (0, 1, 2, 3, 4)
ACCEL = ["A_B23_v", "A_B23_h", "A_B45_v", "A_B45_h"]


@pytest.fixture(scope="module")
def recordings(mill, tmp_path_factory):
    out = {}
    d = tmp_path_factory.mktemp("segment")
    for seed in SEEDS:
        s = make_synth(mill, seed=seed, duration_s=40.0)
        p = d / f"seed{seed}.mcap"
        write_recording(p, s.devices)
        out[seed] = (s, p)
    return out


def match(segments, truth):
    """Each truth step's nearest segment; also the segments matched by none."""
    pairs = []
    used = set()
    for tr in truth:
        k = int(np.argmin([abs(s.t_step - tr.t_step) for s in segments]))
        pairs.append((tr, segments[k]))
        used.add(k)
    extra = [s for k, s in enumerate(segments) if k not in used]
    return pairs, extra


@pytest.mark.parametrize("seed", SEEDS)
def test_torque_segments_match_truth(mill, recordings, seed):
    synth, path = recordings[seed]
    rec = read_recording(path, mill, channels=["T_C12", "T_C34", "T_C46", "T_C57"])
    segs = segment_transients(rec, mill)
    assert len(segs) == len(synth.truth)
    pairs, extra = match(segs, synth.truth)
    assert not extra
    for tr, s in pairs:
        assert s.kind == tr.kind
        assert abs(s.t_step - tr.t_step) < 0.005, (tr, s)
        assert s.static_torque == pytest.approx(tr.static, rel=0.03)
        assert s.step == pytest.approx(tr.step, rel=0.03)
        assert s.channel == "T_C46" and s.channels == ("T_C46", "T_C57")  # nearest the rolls
        assert 0.5 * tr.rise_s < s.rise_s / 0.59 < 1.5 * tr.rise_s + 0.003
    # no transient in the idle stretches with noise
    for a, b in synth.idle:
        assert not [s for s in segs if a < s.t_step < b]
    # windows: in order, never overlapping, within the bounds
    for k, s in enumerate(segs):
        assert s.t_start < s.t_step < s.t_end
        assert s.t_step - s.t_start == pytest.approx(0.1)
        assert s.t_end - s.t_step <= 0.8 + 1e-9
        if k + 1 < len(segs):
            assert s.t_end <= segs[k + 1].t_start + 1e-9
            if segs[k + 1].t_step - s.t_step > 1.0:
                assert s.t_end - s.t_step >= 0.3 - 1e-9


@pytest.mark.parametrize("seed", SEEDS[:3])
def test_accelerometer_only_segments(mill, recordings, seed):
    synth, path = recordings[seed]
    rec = read_recording(path, mill, channels=ACCEL)
    segs = segment_transients(rec, mill)
    pairs, extra = match(segs, synth.truth)
    assert not extra and len(segs) == len(synth.truth)
    for tr, s in pairs:
        assert s.kind == tr.kind
        err = s.t_step - tr.t_step
        # the precision the docstring states: bites 5 ms, releases 40 ms
        assert abs(err) < (0.005 if tr.kind == "bite" else 0.040), (tr, err)
        assert math.isnan(s.static_torque) and math.isnan(s.step)
        assert s.channel == "A_B23_v"


def test_idle_recording_has_no_transients(tmp_path, mill):
    s = make_synth(mill, seed=11, duration_s=40.0)
    idle = [dataclasses.replace(d, data=d.data[:, : int(d.rate_hz * 1.4)]) for d in s.devices]
    p = tmp_path / "idle.mcap"
    write_recording(p, idle)
    rec = read_recording(p, mill)
    assert segment_transients(rec, mill) == ()
    rec_a = read_recording(p, mill, channels=ACCEL)
    assert segment_transients(rec_a, mill) == ()


def test_far_channel_alone_gives_total_torque(mill, recordings):
    synth, path = recordings[0]
    rec = read_recording(path, mill, channels=["T_C12"])
    segs = segment_transients(rec, mill)
    pairs, extra = match(segs, synth.truth)
    assert not extra
    for tr, s in pairs:
        assert s.channel == "T_C12"
        assert abs(s.t_step - tr.t_step) < 0.005
        assert s.static_torque == pytest.approx(tr.static, rel=0.03)


def test_dropout_over_a_step_skips_it(tmp_path, mill, recordings):
    synth, _ = recordings[1]
    dev = synth.devices[0]
    tr = synth.truth[2]
    data = dev.data.copy()
    i = int(tr.t_step * dev.rate_hz)
    data[:, i - 100:i + 100] = np.nan
    tr_next = synth.truth[3]
    j = int((tr_next.t_step + 0.2) * dev.rate_hz)
    data[:, j:j + 50] = np.nan  # a dropout during the next ring-down
    p = tmp_path / "drop.mcap"
    write_recording(p, [dataclasses.replace(dev, data=data)])
    rec = read_recording(p, mill, warn=False)
    segs = segment_transients(rec, mill)
    assert len(segs) == len(synth.truth) - 1
    assert not [s for s in segs if abs(s.t_step - tr.t_step) < 0.5]
    nxt = min(segs, key=lambda s: abs(s.t_step - tr_next.t_step))
    assert abs(nxt.t_step - tr_next.t_step) < 0.005
    assert nxt.t_end < j / dev.rate_hz  # the window stops before the dropout


def test_segment_to_dict_and_frozen():
    s = Segment(t_start=1.0, t_step=1.1, t_end=1.6, kind="bite", static_torque=3e5, step=3e5,
                channel="T_C46")
    d = s.to_dict()
    assert {"t_start", "t_step", "t_end", "kind", "static_torque", "step"} <= set(d)
    assert d["kind"] == "bite" and d["step"] == 3e5
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.t_step = 2.0  # type: ignore[misc]


def test_nothing_to_segment(tmp_path, mill):
    dev = RawDevice("/x", 100.0, T0_NS, ("X1",), ("kN*m",), np.zeros((1, 50), np.float32))
    p = tmp_path / "x.mcap"
    write_recording(p, [dev])
    rec = read_recording(p, warn=False)
    with pytest.raises(RecordingError, match=r"nothing to segment: the recording has no torque "
                       r"channel with a static load and no acceleration channel"):
        segment_transients(rec, mill)


def test_bad_options(mill, recordings):
    _, path = recordings[0]
    rec = read_recording(path, mill, channels=["T_C12"])
    with pytest.raises(ValueError, match=r"max_window_s must be a positive number of seconds; "
                       r"got -1"):
        segment_transients(rec, mill, max_window_s=-1)
    with pytest.raises(ValueError, match=r"min_window_s \(0\.9\) must not exceed max_window_s"):
        segment_transients(rec, mill, min_window_s=0.9, max_window_s=0.5)


# ---- load shares and distances ---------------------------------------------------------------
def test_load_fractions_of_the_tree(mill):
    f = load_fractions(mill)
    assert f == pytest.approx({"C12": 1.0, "C23": 1.0, "C34": 1.0, "C45": 0.5, "C46": 0.5,
                               "C57": 0.5})
    assert distance_to_load(mill) == {"C12": 3, "C23": 2, "C34": 1, "C45": 1, "C46": 0,
                                      "C57": 0}
    flipped = dataclasses.replace(mill.element("C46"), from_="Q6", to="Q4")
    m2 = dataclasses.replace(mill, elements=tuple(flipped if e.id == "C46" else e
                                                  for e in mill.elements))
    assert load_fractions(m2)["C46"] == pytest.approx(-0.5)


def test_load_fractions_with_a_closed_loop(mill):
    """Rolls meeting through the strip: equilibrium at every mass is the independent truth."""
    strip = Element(id="S67", from_="Q6", to="Q7", k=2.0e7)
    looped = dataclasses.replace(mill, elements=mill.elements + (strip,))
    f = load_fractions(looped)
    share = dict(zip(mill.load.masses, mill.load.share))
    for m in mill.masses:
        inflow = sum(f[e.id] for e in looped.elements if e.to == m.id)
        outflow = sum(f[e.id] for e in looped.elements if e.from_ == m.id)
        expect = -1.0 if m.id == mill.motor.mass else share.get(m.id, 0.0)
        assert inflow - outflow == pytest.approx(expect, abs=1e-9), m.id
    assert f["C34"] == pytest.approx(1.0)  # a bridge carries everything
    assert f["C46"] != pytest.approx(0.5, abs=1e-3)  # the loop redistributes
    weak = dataclasses.replace(strip, k=1e-3)
    f_weak = load_fractions(dataclasses.replace(mill, elements=mill.elements + (weak,)))
    tree = load_fractions(mill)
    assert {k: f_weak[k] for k in tree} == pytest.approx(tree, abs=1e-6)


def test_lowest_mode_is_the_linear_baselines(mill, repo_root):
    """segment may not import model: its own eigenproblem must agree with natural_modes."""
    from ident import load_mill
    from ident.model.linear import natural_modes
    from ident.segment.timescales import lowest_mode

    for m in (mill, load_mill(repo_root / "data" / "mills" / "cold-s5.toml")):
        ref = natural_modes(m)
        got = lowest_mode(m)
        assert got.freq_hz == pytest.approx(ref.frequencies_hz[0], rel=1e-9)
        assert got.damping_ratio == pytest.approx(ref.damping_ratios[0], rel=1e-9)
    assert lowest_mode(mill).freq_hz == pytest.approx(12.0, abs=0.1)  # seed Fig. 2
