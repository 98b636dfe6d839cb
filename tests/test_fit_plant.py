"""Gap identification on recordings of the independent plant simulator (issue 12).

The small version of ``make validate`` (``validation/fit_study.py``): plantsim was
written from the specs alone -- its own physics (exact piecewise-linear steps at
20 kHz, a PI speed loop, losses spread over the shafts, floating spindles), its own
recording chain (anti-alias FIR or IIR filter and decimation, offsets, drift and
random walk, 16-bit quantisation) and its own load ramps of four shapes -- so it is
not the fit's model.  Its parameters are drawn at random from each seed; the seeds
were not used to set any threshold of the fit (those were set on seeds 1000-1011
of ``make validate`` and checked on 2000 onwards).

Per mill one recording of two bars, fitted the way ``ident fit`` does (from the mill
file's gaps).  Tolerances are the issue's: a gap is right within max(10 %, 0.3 mrad);
of the directly measured gaps (7 here) at least 6 accepted and right, none accepted
but wrong, and the 95 % intervals of the accepted ones miss the truth at most once
(plant hsm-f1 4101 is a hard case: the model error biases C12, C34 and C57
by 11-25 %, within the issue's 0.3 mrad; at a model-error gain of 1 three of its
four intervals missed.  Its C46, 2.45 mrad against 2.56, has an interval of +-19 %,
wider than an identified gap's accuracy: the verdict bounds it and does not accept
it; cold-s5 4102's C34, 0.04 mrad against a closed gap, is the one miss).

Stability (item 7): the hot strip mill's recording refitted from starts nudged by
1e-6 gives the same verdicts on the measured gaps and the same gaps within their 95 %
intervals.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from ident import load_mill
from ident.fit import fit_gaps, windows_from_recording
from ident.fit.uncertainty import Z95
from ident.io import read_recording
from ident.segment import segment_transients
from validation import plantsim

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

SEEDS = {"hsm-f1": 4101, "cold-s5": 4102}


def tolerance(truth: float) -> float:
    return max(0.1 * truth, 3e-4)


def _windows(mill, draw, path):
    rec = plantsim.simulate_plant(mill, draw)
    plantsim.write_plant(rec, path)
    r = read_recording(path, mill, warn=False)
    w = windows_from_recording(r, mill, segment_transients(r, mill))
    return w, {k: float(v["gap"]) for k, v in rec.truth["elements"].items()}


@pytest.fixture(scope="module")
def plant_fit(repo_root, tmp_path_factory):
    """``plant_fit(name)``: the mill's recording and its fit, made once per module."""
    d = tmp_path_factory.mktemp("plantfit")
    cache = {}

    def get(name):
        if name not in cache:
            seed = SEEDS[name]
            mill = load_mill(repo_root / "data" / "mills" / f"{name}.toml")
            draw = plantsim.draw_plant(mill, np.random.default_rng(seed), accelerometers=False)
            windows, truth = _windows(mill, draw, d / f"{name}-{seed}.csv")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = fit_gaps(mill, windows)
            cache[name] = (mill, draw, windows, truth, res)
        return cache[name]
    return get


@pytest.fixture(scope="module")
def fits(plant_fit):
    return {name: plant_fit(name) for name in SEEDS}


@pytest.mark.timeout(1500)  # hsm-f1 4101: 661 s measured, more with the ramp polish
@pytest.mark.parametrize("name", list(SEEDS))
def test_each_mills_fit_converges(plant_fit, name):
    """One fit per test (each within the module's timeout); the tests below pool them."""
    res = plant_fit(name)[4]
    assert res.converged, (name, res.solver.status)


def _measured(mill):
    return [c.element for c in mill.torque_channels()]


def _tally(fits):
    right = wrong = covered = accepted = total = 0
    rows = []
    for name, (mill, _, _, truth, res) in fits.items():
        assert res.converged, (name, res.solver.status)
        for eid in _measured(mill):
            el, g = res.elements[eid], truth[eid]
            ok = abs(el.gap - g) <= tolerance(g)
            total += 1
            if el.identified:
                accepted += 1
                right += ok
                wrong += not ok
                covered += el.gap_ci95[0] <= g <= el.gap_ci95[1]
            rows.append((name, eid, round(g * 1e3, 3), round(el.gap * 1e3, 3),
                         [round(v * 1e3, 3) for v in el.gap_ci95], el.identified, el.reason))
    return total, accepted, right, wrong, covered, rows


def test_measured_gaps_are_accepted_and_right(fits):
    total, accepted, right, wrong, _, rows = _tally(fits)
    assert total == 7
    assert right >= 6 and wrong == 0, rows


def test_intervals_of_accepted_gaps_cover_the_truth(fits):
    _, accepted, _, _, covered, rows = _tally(fits)
    assert accepted >= 6 and covered >= accepted - 1, rows


@pytest.mark.timeout(1500)
def test_a_nudged_start_gives_the_same_answer(plant_fit):
    """The outcome does not hang on rounding: a start moved by 1e-6 of each gap ends where
    the designed start did, within what the fit says it knows.  (Another noise draw of the
    same plant was refitted here too; the fixture's two mills and ``make validate``'s draws
    cover that, and the suite could not afford a fourth fit of the plant.)"""
    mill, _, windows, _, res = plant_fit("hsm-f1")
    rng = np.random.default_rng(7)
    nudged = {e.id: max(e.gap, 5e-4) * (1.0 + 1e-6 * rng.standard_normal())
              for e in mill.elements}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = fit_gaps(mill, windows, starts=[nudged])
    for eid in _measured(mill):
        a, b = res.elements[eid], again.elements[eid]
        assert b.identified == a.identified, (eid, a.reason, b.reason)
        assert abs(b.gap - a.gap) <= Z95 * max(a.gap_se, b.gap_se), (eid, a.gap, b.gap)
