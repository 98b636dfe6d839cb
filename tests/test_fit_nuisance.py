"""The fit's nuisance terms (ident.fit.model): drag, channel offsets, the ramp's shape.

Plants record channel zeros that differ per channel and drift, bearing and mesh
losses that make a motor-side channel read more than a roll-side one, and bites
whose torque rises fast and then approaches its level.  These tests pin the terms
down on closed forms; the identification tests (test_fit*.py) fit with them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import ident
from ident.fit.model import (RAMP_KNOTS, RAMP_PARAMS, RAMP_WEIGHT_MAX, build_fit_model,
                             drag_groups, drag_masses, raised_cosine, ramp_shape, skewed_cosine,
                             static_state)


@pytest.fixture(scope="module")
def cold():
    return ident.load_mill("data/mills/cold-s5.toml")


def test_drag_acts_where_only_one_channel_carries_it(mill, cold):
    # hsm-f1: T_C12 alone carries the losses of Q2/Q3, T_C34 those of Q4/Q5; the
    # spindle channels next to the rolls carry none of their own
    assert drag_masses(mill) == ("Q3", "Q5")
    # cold-s5: T_C12 for Q2/Q3 (at Q3, so the unmeasured mesh C23 carries it), T_C34 for Q4
    assert drag_masses(cold) == ("Q3", "Q4")
    m = build_fit_model(cold, nuisance=True)
    assert m.shared_names[-2:] == ("Q3.drag", "Q4.drag")
    assert build_fit_model(cold).drag_masses == ()
    assert not set(RAMP_PARAMS) & set(build_fit_model(cold).window_names)
    assert not set(RAMP_PARAMS) & set(m.window_names)  # only for the polish
    assert set(RAMP_PARAMS) <= set(build_fit_model(cold, nuisance=True,
                                                   ramp_weights=True).window_names)


def _outputs(m, x, level, shared, window):
    p = m.pmap(shared, window, 1e-4)
    return np.asarray(m.y(x, level, p, 0.0, window)).ravel()


def test_static_state_carries_the_drag_and_the_offsets_add(cold):
    """At rest under a load L with drags d3, d4: T_C12 = L + d3 + d4, T_C34 = L + d4, T_C45 = L."""
    m = build_fit_model(cold, nuisance=True)
    shared = np.zeros(m.n_shared)
    for e in cold.elements:
        shared[m.shared_names.index(f"{e.id}.gap")] = max(e.gap, 0.0)
    shared[m.shared_names.index("Q3.drag")] = 700.0
    shared[m.shared_names.index("Q4.drag")] = 150.0
    window = np.zeros(m.n_window)
    level = 20_000.0
    window[:2] = level
    x = static_state(m, level, shared, window)
    y = dict(zip(m.measured, _outputs(m, x, level, shared, window)))
    assert y["C45"] == pytest.approx(level, rel=1e-6)
    assert y["C34"] == pytest.approx(level + 150.0, rel=1e-6)
    assert y["C12"] == pytest.approx(level + 850.0, rel=1e-6)
    # the motor's speed-loop integral holds the whole torque
    assert x[2 * len(cold.masses)] * cold.motor.ki == pytest.approx(level + 850.0, rel=1e-9)
    # at rest the state does not move: the right-hand side vanishes
    p = m.pmap(shared, window, 1e-4)
    assert np.max(np.abs(np.asarray(m.driveline.rhs(x, level, p, 0.0)))) < 1e-6
    off = window.copy()
    for k, v in zip(m.offset_index, (-300.0, 40.0, 900.0)):
        off[k] = v
    y2 = _outputs(m, x, level, shared, off)
    assert y2 - np.array(list(y.values())) == pytest.approx([-300.0, 40.0, 900.0], abs=1e-6)


def test_ramp_shape_is_a_monotone_ramp_and_the_skewed_cosine_without_weights():
    s = np.linspace(-0.5, 1.5, 4001)
    assert np.allclose(ramp_shape(s), raised_cosine(s))
    for skew in (-0.9, -0.3, 0.0, 0.5, 0.9):
        assert np.allclose(ramp_shape(s, skew, [0.0] * len(RAMP_KNOTS)), skewed_cosine(s, skew))
        r = ramp_shape(s, skew, [3.0] * len(RAMP_KNOTS))
        assert np.all(np.diff(r) >= -1e-15) and r[-1] == pytest.approx(1.0)
    rng = np.random.default_rng(3)
    for _ in range(20):
        K = len(RAMP_KNOTS)
        w = rng.uniform(0.0, RAMP_WEIGHT_MAX, K) * (rng.uniform(size=K) < 0.6)
        r = ramp_shape(s, weights=w)
        assert r[s <= 0].max() == 0.0 and r[s >= 1].min() == pytest.approx(1.0)
        assert np.all(np.diff(r) >= -1e-15)  # monotone
    # each hat alone: its integral, normalised -- the rate is the hat (piecewise linear,
    # peaking at its knot); with the first knot's hat the ramp starts at full rate
    for k, knot in enumerate(RAMP_KNOTS):
        w = np.zeros(len(RAMP_KNOTS))
        w[k] = 1e9
        r = ramp_shape(s, weights=w)
        rate = np.gradient(r, s)
        inside = (s > 0.01) & (s < 0.99)
        assert s[inside][np.argmax(rate[inside])] == pytest.approx(knot, abs=0.02)
    w = np.zeros(len(RAMP_KNOTS))
    w[0] = 1e9
    assert np.gradient(ramp_shape(s, weights=w), s)[np.argmin(np.abs(s - 0.002))] > 5.0
    # weights in proportion to the hats' areas: the hats sum to one, so the rate is
    # constant -- a linear ramp
    kn = np.asarray(RAMP_KNOTS)
    area = 0.5 * (np.diff(kn, prepend=kn[0]) + np.diff(kn, append=kn[-1]))
    lin = ramp_shape(s, weights=1e9 * area)
    assert np.allclose(lin, np.clip(s, 0, 1), atol=1e-6)
    # rounded corners: C1 (the rate has no jump), exact away from the ends, still 0 -> 1
    rc = ramp_shape(s, weights=1e9 * area, corner=0.1)
    assert np.allclose(rc[(s > 0.05) & (s < 0.95)], s[(s > 0.05) & (s < 0.95)], atol=1e-6)
    assert rc[s <= -0.05].max() == 0.0 and rc[s >= 1.05].min() == pytest.approx(1.0)
    assert np.max(np.abs(np.diff(np.gradient(rc, s)))) < 0.02


def test_the_cosine_load_does_not_read_the_shape_weights_and_the_shaped_load_does(cold):
    """One layout, two loads: ``load`` (every stage of the continuation) is the skewed
    cosine whatever the weights hold; ``load_shaped`` (the collocation's polish) reads them
    and is the same ramp at weights 0, up to the rounding of its two corners."""
    m = build_fit_model(cold, nuisance=True, ramp_weights=True)
    assert build_fit_model(cold, nuisance=True).load_shaped is None
    win = np.zeros(m.n_window)
    win[:6] = [1_000.0, 21_000.0, 0.2, 0.05, 0.0, 0.0]
    win[m.window_names.index("skew")] = 0.4
    t = np.linspace(0.0, 0.4, 801)
    cos = np.array([float(m.load(tk, win)) for tk in t])
    ref = 1_000.0 + 20_000.0 * skewed_cosine((t - 0.2) / 0.05 + 0.5, 0.4)
    assert np.allclose(cos, ref, atol=1e-6)
    at0 = np.array([float(m.load_shaped(tk, win)) for tk in t])
    assert np.max(np.abs(at0 - cos)) < 1e-3 * 20_000.0
    heavy = win.copy()
    for nm in RAMP_PARAMS:
        heavy[m.window_names.index(nm)] = 20.0
    assert np.allclose([float(m.load(tk, heavy)) for tk in t], cos, atol=1e-9)
    shaped = np.array([float(m.load_shaped(tk, heavy)) for tk in t])
    assert np.max(np.abs(shaped - cos)) > 0.02 * 20_000.0  # the weights move the ramp


def test_the_polish_nlp_has_the_layout_of_the_continuations(cold):
    """The polish warm-starts from the continuation's primal and dual point: both NLPs
    must lay out variables and constraints alike."""
    from ident.fit.collocation import Collocation
    from ident.fit.problem import make_problem
    from ident.fit.windows import FitWindow

    m = build_fit_model(cold, nuisance=True, ramp_weights=True)
    n = 400
    t = np.arange(n) / 2_000.0
    y = np.zeros((n, m.ny))
    y[t >= 0.1] = 20_000.0
    w = FitWindow(t=t, elements=m.measured, y=y, t_step=0.1, kind="bite",
                  static_torque=20_000.0, step=20_000.0)
    problem = make_problem(m, [w])
    meth = Collocation(compile=False, ramp_polish=True)
    a, b = meth.nlp(problem), meth.nlp(problem, shaped=True)
    def places(nlp):  # the layout without the derivatives' sparsity
        return {k: v for k, v in nlp.layout.items() if not k.startswith("nnz")}

    assert a is not b and places(a) == places(b) and (a.n_x, a.n_g) == (b.n_x, b.n_g)
    # the shaped NLP's derivatives carry the weights; the continuation's do not
    assert b.layout["nnz_jac"] > a.layout["nnz_jac"]


def _plant_ramp(kind, p1=0.0, p2=0.0):
    """validation.plantsim's four ramp shapes (written out: ident does not import validation)."""
    from scipy import special

    def f(u):
        u = np.clip(u, 0.0, 1.0)
        if kind == "cosine":
            return 0.5 - 0.5 * np.cos(np.pi * u)
        if kind == "linear":
            return u
        if kind == "exp":
            return -np.expm1(-p1 * u) / -np.expm1(-p1)
        return special.betainc(p1, p2, u)
    return f


@pytest.mark.parametrize("case", [("cosine",), ("linear",), ("exp", 2.0), ("exp", 3.5),
                                  ("exp", 5.0), ("beta", 1.3, 1.3), ("beta", 1.3, 3.0),
                                  ("beta", 3.0, 1.3), ("beta", 2.0, 3.0), ("beta", 3.0, 3.0)])
def test_ramp_shape_spans_the_ramps_plants_record(case):
    """Least squares over shift, duration, skew and weights: within 1 % of the step
    everywhere, where the skewed cosine alone (shift, duration and skew free) misses linear
    and exponential ramps by 4-12 %."""
    from scipy import optimize

    t = np.linspace(-0.3, 1.3, 801)
    y = _plant_ramp(*case)(t)
    K = len(RAMP_KNOTS)

    def worst(fun, x0, lo, hi):
        best = math.inf
        for trial in range(4):
            x = np.clip(np.asarray(x0, float) + (np.random.default_rng(trial).uniform(0, 2, len(x0))
                                                 if trial else 0.0), lo, hi)
            r = optimize.least_squares(lambda p: fun(p) - y, x, bounds=(lo, hi))
            best = min(best, float(np.max(np.abs(r.fun))))
        return best

    lo, hi = [-0.5, 0.3, -0.9] + [0.0] * K, [0.5, 2.0, 0.9] + [RAMP_WEIGHT_MAX] * K
    e = worst(lambda p: ramp_shape((t - p[0]) / p[1], p[2], p[3:]), [0.0, 1.0, 0.0] + [1.0] * K,
              lo, hi)
    assert e < 0.01
    cos_only = worst(lambda p: skewed_cosine((t - p[0]) / p[1], p[2]), [0.0, 1.0, 0.0],
                     lo[:3], hi[:3])
    if case[0] in ("linear", "exp"):
        assert cos_only > 0.04


def test_each_groups_drag_is_spread_over_its_shafts_by_inertia(mill):
    """hsm-f1: T_C12's group is Q2/Q3, T_C34's Q4/Q5 (named Q3.drag, Q5.drag), shares J/sum(J).

    At rest with the load L, the unmeasured mesh C45 (Q4 -> Q5) carries L/2 and Q5's
    share of its group's drag only, the coupling C34 the whole group's."""
    groups = dict(drag_groups(mill))
    assert list(groups) == ["Q3", "Q5"]
    J = {m.id: m.J for m in mill.masses}
    for rep, shares in groups.items():
        assert sum(w for _, w in shares) == pytest.approx(1.0)
        tot = sum(J[mid] for mid, _ in shares)
        for mid, w in shares:
            assert w == pytest.approx(J[mid] / tot)
    assert [mid for mid, _ in groups["Q3"]] == ["Q2", "Q3"]
    assert [mid for mid, _ in groups["Q5"]] == ["Q4", "Q5"]
    m = build_fit_model(mill, nuisance=True)
    shared = np.zeros(m.n_shared)
    for e in mill.elements:
        shared[m.shared_names.index(f"{e.id}.gap")] = e.gap
    shared[m.shared_names.index("Q3.drag")] = 4000.0
    shared[m.shared_names.index("Q5.drag")] = 2000.0
    assert sum(m.drag_torques(shared).values()) == pytest.approx(6000.0)
    window = np.zeros(m.n_window)
    level = 100_000.0
    window[:2] = level
    x = static_state(m, level, shared, window)
    p = m.pmap(shared, window, 1e-4)
    tau = np.asarray(m.driveline.out(x, level, p, 0.0)).ravel()
    out = {n[4:]: v for n, v in zip(m.driveline.output_names, tau) if n.startswith("tau:")}
    w5 = dict(groups["Q5"])["Q5"]
    assert out["C34"] == pytest.approx(level + 2000.0, rel=1e-6)
    assert out["C45"] == pytest.approx(0.5 * level + w5 * 2000.0, rel=1e-6)
    assert out["C12"] == pytest.approx(level + 6000.0, rel=1e-6)
    assert np.max(np.abs(np.asarray(m.driveline.rhs(x, level, p, 0.0)))) < 1e-6
