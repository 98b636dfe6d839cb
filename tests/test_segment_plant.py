"""Segmentation on recordings of the independent plant simulator (validation/plantsim.py).

The small version of ``python -m validation.segment_study``: plantsim was written from
the specs alone (its own physics, recorder chain and truth), so these recordings are not
the segmenter's own generator.  Per mill (hsm-f1, and the 5-mass cold stand cold-s5 with
one channel in N*m) four recordings, two as ``make_recording`` draws them and two with
the first bite in 0.5-1.0 s and 3 bars; a cold stand with every inertia doubled (lowest
mode 10.3 Hz: the outside tester's misses, its first bite and most releases, came back
on it with the 80 ms detection of hsm-f1); and a bite in the first 0.5-1 s of a file.

Tolerances: every load step found with ``t_step`` within 5 ms of the truth's (half
height of the noise-free torque nearest the rolls, cli.md; the segmenter's precision
on these mills is ~0.2 ms median, < 1 ms at most), no false step, kinds alternating,
``static_torque`` within 5 % (the rolling level drifts by up to 3 % over a bar and
fluctuates by up to 2 %; measured at most 2.2 %).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ident import load_mill
from ident.io import read_recording
from ident.segment import segment_file, segment_transients
from validation import plantsim

MILLS = ("hsm-f1", "cold-s5")
SEEDS = (300, 301, 302, 303)


def _mill(repo_root, name):
    return load_mill(repo_root / "data" / "mills" / f"{name}.toml")


def _write(mill, seed, path, **kw):
    """One recording without accelerometers (torque is what is segmented); its truth steps."""
    draw = plantsim.draw_plant(mill, np.random.default_rng(seed), accelerometers=False, **kw)
    rec = plantsim.simulate_plant(mill, draw)
    plantsim.write_plant(rec, path)
    return rec.truth["steps"]


def _check(segs, steps):
    assert [s.kind for s in segs] == [st["kind"] for st in steps], \
        [(s.kind, round(s.t_step, 3)) for s in segs]  # nothing missed, nothing extra
    for s, st in zip(segs, steps):
        assert abs(s.t_step - st["t_step"]) < 0.005, (s, st)
        assert s.static_torque == pytest.approx(st["static_torque"], rel=0.05)
        assert s.step == pytest.approx(st["step"], rel=0.05)
        assert s.t_start < s.t_step < s.t_end


@pytest.fixture(scope="module")
def recordings(repo_root, tmp_path_factory):
    d = tmp_path_factory.mktemp("plant")
    out = {}
    for name in MILLS:
        mill = _mill(repo_root, name)
        for seed in SEEDS:
            if seed % 2 == 0:  # as make_recording draws it: first bite in 1.0-2.5 s
                path = d / f"{name}-{seed}.mcap"
                steps = _write(mill, seed, path, n_bars=2)
            else:
                meta = np.random.default_rng([seed, 1])
                path = d / f"{name}-{seed}.csv"
                steps = _write(mill, seed, path, n_bars=3,
                               first_bite_s=float(meta.uniform(0.5, 1.0)))
            out[name, seed] = (mill, path, steps)
    return out


@pytest.mark.parametrize("name", MILLS)
@pytest.mark.parametrize("seed", SEEDS)
def test_every_plant_step_within_5_ms(recordings, name, seed):
    mill, path, steps = recordings[name, seed]
    segs = segment_file(path, mill).segments  # as ident segment runs it
    _check(segs, steps)
    nearest = {"hsm-f1": ("T_C46", "T_C57"), "cold-s5": ("T_C45",)}[name]
    assert segs[0].channels == nearest


def test_truth_sidecar_is_what_was_checked(recordings):
    mill, path, steps = recordings["cold-s5", SEEDS[0]]
    truth = json.loads(plantsim.truth_path(path).read_text())
    assert [s["t_step"] for s in truth["steps"]] == [s["t_step"] for s in steps]
    assert truth["channels"]["T_C45"]["unit"] == "N*m"


def test_idle_start_of_a_plant_recording_has_no_step(recordings):
    for name in MILLS:
        mill, path, steps = recordings[name, SEEDS[0]]
        rec = read_recording(path, mill, t_start=0.0, t_end=steps[0]["t_step"] - 0.2, warn=False)
        assert segment_transients(rec, mill) == ()


@pytest.mark.parametrize("name,first_bite_s", [("hsm-f1", 0.5), ("cold-s5", 0.5),
                                                ("cold-s5", 0.8)])
def test_bite_in_the_first_second(repo_root, tmp_path, name, first_bite_s):
    mill = _mill(repo_root, name)
    path = tmp_path / "early.mcap"
    steps = _write(mill, 310, path, n_bars=1, first_bite_s=first_bite_s)
    assert steps[0]["t_step"] < first_bite_s + 0.1
    _check(segment_file(path, mill).segments, steps)


def test_cold_stand_with_a_lower_lowest_mode(repo_root, tmp_path):
    """The cold stand with every inertia doubled: 10.3 Hz, a ring-down period past 80 ms.

    The hsm-f1 detection (an 80 ms mean, 25/12 % of the range) missed 1, 3 and 2 of
    the 6 steps of these seeds (and steps in 10 of seeds 320-331): first bites and
    releases, the outside tester's symptom on cold-s5.
    """
    base = _mill(repo_root, "cold-s5")
    mill = base.with_overrides({f"{m.id}.J": 2.0 * m.J for m in base.masses})
    from ident.segment.timescales import lowest_mode

    assert lowest_mode(mill).freq_hz == pytest.approx(10.3, abs=0.1)
    for seed in (322, 323, 324):
        path = tmp_path / f"soft-{seed}.mcap"
        steps = _write(mill, seed, path, n_bars=3,
                       first_bite_s=float(np.random.default_rng([seed, 1]).uniform(0.5, 2.0)))
        _check(segment_transients(read_recording(path, mill, warn=False), mill), steps)
