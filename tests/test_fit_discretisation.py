"""The collocation's element length follows the mill's highest mode (ident.fit.collocation).

A degree-3 Radau polynomial per element must follow the fastest oscillation the
driveline can ring at; the element length is set from the highest natural frequency
and the sample interval, not as a fixed number of samples.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import ident
from ident.fit import Collocation, build_fit_model, make_problem
from ident.fit.collocation import MAX_PER_BLOCK, element_shape
from ident.fit.windows import FitWindow
from ident.model.linear import natural_modes

pytestmark = pytest.mark.timeout(60)


def test_element_shape_bounds_the_phase_of_the_highest_mode():
    # hsm-f1's 81 Hz at 2 kHz: 1.5 rad per element is 5.9 samples -> 5
    assert element_shape(81.0, 1 / 2000, 1.5) == (5, 1)
    # cold-s5's 138.5 Hz at 2 kHz: 3.4 samples -> 3; at 1 kHz 1.7 -> 1
    assert element_shape(138.5, 1 / 2000, 1.5) == (3, 1)
    assert element_shape(138.5, 1 / 1000, 1.5) == (1, 1)
    # slower than the mode allows: one sample split into elements
    assert element_shape(138.5, 1 / 400, 1.5) == (1, 2)
    # fast recordings: at most MAX_PER_BLOCK samples per element; no mode: no bound
    assert element_shape(81.0, 1 / 20000, 1.5) == (MAX_PER_BLOCK, 1)
    assert element_shape(0.0, 1 / 2000, 1.5) == (MAX_PER_BLOCK, 1)
    for f, fs in ((81.0, 1000.0), (138.5, 2500.0), (300.0, 1000.0), (45.0, 5000.0)):
        ns, ne = element_shape(f, 1 / fs, 1.5)
        h = ns / ne / fs
        assert 2 * math.pi * f * h <= 1.5 + 1e-9 or (ns, ne) == (1, MAX_PER_BLOCK)


@pytest.mark.parametrize("phase, bound", [(1.0, 0.0008), (1.5, 0.004), (2.0, 0.012)])
def test_a_cubic_through_the_radau_points_follows_a_sine(phase, bound):
    """The docstring's figures: the largest miss of a sine by the element's polynomial."""
    c = np.array([0.0, (4 - math.sqrt(6)) / 10, (4 + math.sqrt(6)) / 10, 1.0])
    t = np.linspace(0.0, 1.0, 401)
    worst = 0.0
    for ph in np.linspace(0.0, math.pi, 25):
        p = np.polyfit(c, np.sin(phase * c + ph), 3)
        worst = max(worst, float(np.max(np.abs(np.polyval(p, t) - np.sin(phase * t + ph)))))
    assert worst < bound


def test_the_nlp_takes_its_blocks_from_the_mill_and_the_rate():
    cold = ident.load_mill("data/mills/cold-s5.toml")
    f_max = float(np.max(natural_modes(cold).frequencies_hz))
    model = build_fit_model(cold)
    for fs in (1000.0, 2000.0, 5000.0):
        t = np.arange(300) / fs
        w = FitWindow(t=t, elements=model.measured, y=np.zeros((t.size, model.ny)),
                      t_step=t[100], kind="bite")
        problem = make_problem(model, [w])
        assert Collocation().block_shape(problem) == element_shape(f_max, 1 / fs, 1.5)
        assert Collocation(elements_per_sample=0.5).block_shape(problem) == (2, 1)


def test_a_bound_reached_at_a_stationary_cost_counts_as_converged():
    """Collocation.stationary: the cost flat over the last 30 iterations and feasible."""
    from ident.fit.collocation import STATIONARY_ITER, stationary

    flat = [0.394 + 1e-9 * k for k in range(40, 0, -1)]
    st = {"return_status": "Maximum_Iterations_Exceeded",
          "iterations": {"obj": flat, "inf_pr": [1e-9] * 40}}
    assert stationary(st)
    assert stationary({**st, "return_status": "Maximum_CpuTime_Exceeded"})
    # still descending: 1e-5 of itself over the last 30 iterations
    falling = [0.404 + 1.5e-7 * k for k in range(40, 0, -1)]
    assert not stationary({**st, "iterations": {"obj": falling, "inf_pr": [1e-9] * 40}})
    # infeasible at the end, too few iterations, or another status
    assert not stationary({**st, "iterations": {"obj": flat, "inf_pr": [1e-3] * 40}})
    short = flat[-STATIONARY_ITER:]
    assert not stationary({**st, "iterations": {"obj": short, "inf_pr": [1e-9] * len(short)}})
    assert not stationary({**st, "return_status": "Infeasible_Problem_Detected"})
