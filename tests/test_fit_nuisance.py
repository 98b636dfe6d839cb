"""The fit's nuisance terms (ident.fit.model): drag, channel offsets, the ramp's skew.

Plants record channel zeros that differ per channel and drift, bearing and mesh
losses that make a motor-side channel read more than a roll-side one, and bites
whose torque rises fast and then approaches its level.  These tests pin the terms
down on closed forms; the identification tests (test_fit*.py) fit with them.
"""

from __future__ import annotations

import numpy as np
import pytest

import ident
from ident.fit.model import (build_fit_model, drag_groups, drag_masses, raised_cosine,
                             skewed_cosine, static_state)


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
    assert build_fit_model(cold).drag_masses == () and "skew" not in build_fit_model(cold).window_names


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


def test_skewed_cosine_is_a_c1_ramp():
    s = np.linspace(-0.5, 1.5, 4001)
    assert np.allclose(skewed_cosine(s, 0.0), raised_cosine(s))
    for skew in (-0.9, -0.3, 0.5, 0.9):
        r = skewed_cosine(s, skew)
        assert r[s <= 0].max() == 0.0 and r[s >= 1].min() == pytest.approx(1.0)
        assert np.all(np.diff(r) >= -1e-15)  # monotone
        slope = np.gradient(r, s)
        inside = (s > 0) & (s < 1)
        assert abs(slope[np.argmin(np.abs(s))]) < 0.02 and abs(slope[np.argmin(np.abs(s - 1))]) < 0.02
        assert slope[inside].max() < 3 * np.pi / 2  # finite: no kink
    # a positive skew front-loads the ramp (half done before half the time)
    assert skewed_cosine(0.35, 0.9) > 0.5 > skewed_cosine(0.35, 0.0)


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
