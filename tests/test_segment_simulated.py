"""Segmentation on recordings of the project simulator (not the segmenter's own synthetic
generator): every bite and release found, t_step within 5 ms of the instant the noise-free
torque nearest the rolls (the spindles, averaged) crosses half its step (cli.md).  With a
gap open in a spindle that instant lags the load's own half height by the time it takes
to close the gap (18 ms here), which is why the truth is taken from the torque."""

from __future__ import annotations

import numpy as np
import pytest

from ident.io import read_recording, write_recording
from ident.model.dynamics import ModelOptions
from ident.model.scenario import random_scenario
from ident.model.simulate import sensor_devices, simulate
from ident.segment import segment_transients


@pytest.mark.parametrize("seed", [11, 12])
def test_bites_and_releases_of_simulated_bars(tmp_path, mill, seed):
    rng = np.random.default_rng(seed)
    worn = mill.with_overrides({"C46.gap": 0.006, "C46.gap_open": 0.006, "C12.gap": 0.003})
    sc = random_scenario(worn, n_bars=4, rng=rng)
    res = simulate(worn, sc, options=ModelOptions())
    path = tmp_path / "rec.mcap"
    write_recording(path, sensor_devices(res, rng=rng, snr_db=32.0))
    segs = segment_transients(read_recording(path, mill), mill)
    t = res.time
    tau = 0.5 * (res.outputs["tau:C46"].to_numpy() + res.outputs["tau:C57"].to_numpy())

    def half_height(t_from, before, after):
        level = 0.5 * (before + after)
        i0 = np.searchsorted(t, t_from)
        rising = after > before
        cross = (tau[i0:] >= level) if rising else (tau[i0:] <= level)
        return t[i0 + int(np.argmax(cross))]

    def level(a, b):
        sel = (t >= a) & (t < b)
        return float(np.median(tau[sel]))

    bites = [s for s in segs if s.kind == "bite"]
    releases = [s for s in segs if s.kind == "release"]
    assert len(bites) == len(sc.bars) and len(releases) == len(sc.bars)
    for s, bar in zip(bites, sc.bars):
        before = level(bar.t_bite - 0.3, bar.t_bite)
        after = level(bar.t_release - 0.5, bar.t_release)
        assert abs(s.t_step - half_height(bar.t_bite, before, after)) < 5e-3
        assert s.static_torque == pytest.approx(bar.static_torque, rel=0.05)
        assert s.t_start < s.t_step < s.t_end
    for s, bar in zip(releases, sc.bars):
        before = level(bar.t_release - 0.5, bar.t_release)
        after = level(bar.t_release + bar.fall_time + 0.6, bar.t_release + bar.fall_time + 0.9)
        assert abs(s.t_step - half_height(bar.t_release, before, after)) < 5e-3
        assert s.step < 0
