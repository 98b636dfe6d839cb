"""Stiffness laws of seed section 1.2 and Fig. 1 (ident.model.laws).

Property tests (hypothesis) for the invariants STYLE.md section 6 names, closed
forms at chosen points, and agreement of the numpy and CasADi evaluations.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ident.model import laws

# --- strategies: reduced gaps (rad) and stiffnesses (N*m/rad) of a mill driveline ----------
gaps = st.floats(min_value=0.0, max_value=0.02, allow_nan=False)
pos_gaps = st.floats(min_value=1e-5, max_value=0.02, allow_nan=False)
stiff = st.floats(min_value=1e5, max_value=1e9, allow_nan=False)
unit = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)
SETTINGS = settings(max_examples=60, deadline=None)


def _grid(a: float, b: float, extra: float = 0.05, n: int = 4001) -> np.ndarray:
    """Deflections across the gap and well beyond it, rad, kinks included."""
    d = np.linspace(-a - extra, b + extra, n)
    return np.sort(np.concatenate([d, [-a, b, 0.0]]))


# --- closed-form values ---------------------------------------------------------------------

def test_g1_closed_form_values():
    a, b, k1, k2, k3 = 0.001, 0.002, 1.0e7, 1.0e5, 2.0e7
    # beyond b: k3*(d - b) + k2*b ; inside: k2*d ; below -a: k1*(d + a) - k2*a (seed 1.2)
    assert laws.g1(0.005, a, b, k1, k2, k3) == pytest.approx(2.0e7 * 0.003 + 1.0e5 * 0.002)
    assert laws.g1(0.0015, a, b, k1, k2, k3) == pytest.approx(1.0e5 * 0.0015)
    assert laws.g1(-0.004, a, b, k1, k2, k3) == pytest.approx(1.0e7 * -0.003 - 1.0e5 * 0.001)
    assert laws.g1(np.array([0.002, -0.001]), a, b, k1, 0.0, k3) == pytest.approx([0.0, 0.0])


def test_smooth_laws_closed_form_values():
    assert laws.g2(2.0, 1.0, -0.5, 0.25) == pytest.approx(2.0 - 2.0 + 2.0)
    assert laws.g3(1.0, 1.0, 1.0) == pytest.approx(math.pi / 4)
    assert laws.g3(-2.0, 3.0, 0.5) == pytest.approx(-2.0 * 3.0 * math.atan(1.0))
    assert laws.g4(1.0, 1.0, 1.0) == pytest.approx(math.tanh(1.0))
    assert laws.g4(-0.5, 2.0, 4.0) == pytest.approx(-0.5 * 2.0 * math.tanh(2.0))
    assert laws.smooth_max(0.0, 0.2) == pytest.approx(0.1)   # the w/2 bound at the kink
    assert laws.smooth_min(0.0, 0.2) == pytest.approx(-0.1)
    assert laws.smooth_max(3.0, 8.0) == pytest.approx((3.0 + math.hypot(3.0, 8.0)) / 2)


def test_piecewise_closed_form_and_without_knee_is_g1():
    a, b, k, knee, k_after = 0.001, 0.001, 1.0e7, 0.002, 4.0e6
    # 0.005 rad: 0.004 beyond contact, of which 0.002 past the knee
    assert laws.piecewise(0.005, a, b, k, 0.0, k, knee, k_after) == pytest.approx(
        1.0e7 * 0.002 + 4.0e6 * 0.002)
    assert laws.piecewise(-0.005, a, b, k, 0.0, k, knee, k_after) == pytest.approx(
        -(1.0e7 * 0.002 + 4.0e6 * 0.002))
    d = _grid(a, b)
    np.testing.assert_array_equal(laws.piecewise(d, a, b, k, 0.0, k),
                                  laws.g1(d, a, b, k, 0.0, k))


# --- invariants -----------------------------------------------------------------------------

@SETTINGS
@given(a=gaps, b=gaps, k1=stiff, k3=stiff, u=unit)
def test_zero_torque_inside_gap_without_k_gap(a, b, k1, k3, u):
    # any deflection in [-a, b], the kinks included
    d = -a + (u + 1.0) / 2.0 * (a + b)
    d = min(max(d, -a), b)
    assert laws.g1(d, a, b, k1, 0.0, k3) == 0.0
    assert laws.piecewise(d, a, b, k1, 0.0, k3, 0.003, 0.5 * k3) == 0.0


@SETTINGS
@given(a=gaps, b=gaps, k1=stiff, k2=st.floats(0.0, 1e7), k3=stiff,
       knee=st.floats(1e-4, 0.01), ratio=st.floats(0.1, 5.0))
def test_restoring_torque_is_monotone(a, b, k1, k2, k3, knee, ratio):
    d = _grid(a, b)
    scale = max(k1, k2, k3) * 0.1  # N*m: round-off allowance below
    for g in (laws.g1(d, a, b, k1, k2, k3),
              laws.piecewise(d, a, b, k1, k2, k3, knee, ratio * min(k1, k3))):
        assert np.all(np.diff(g) >= -1e-12 * scale)


@SETTINGS
@given(a=gaps, k1=stiff, k2=st.floats(0.0, 1e7), d=st.floats(-0.05, 0.05),
       knee=st.floats(1e-4, 0.01), w=st.floats(1e-6, 1e-3))
def test_symmetric_gap_gives_odd_characteristic(a, k1, k2, d, knee, w):
    # a = b and k1 = k3: g(-d) = -g(d) for every law built on g1
    tol = 1e-9 * k1 * (abs(d) + a) + 1e-12
    assert laws.g1(-d, a, a, k1, k2, k1) == pytest.approx(-laws.g1(d, a, a, k1, k2, k1), abs=tol)
    assert laws.piecewise(-d, a, a, k1, k2, k1, knee, 0.3 * k1) == pytest.approx(
        -laws.piecewise(d, a, a, k1, k2, k1, knee, 0.3 * k1), abs=tol)
    assert laws.g1_smooth(-d, a, a, k1, k2, k1, w) == pytest.approx(
        -laws.g1_smooth(d, a, a, k1, k2, k1, w), abs=tol)


def test_asymmetric_gap_is_not_odd():
    # guards the test above: it must be able to tell
    assert laws.g1(-0.004, 0.001, 0.003, 1e7, 0, 1e7) != -laws.g1(0.004, 0.001, 0.003, 1e7, 0, 1e7)


@SETTINGS
@given(a=gaps, b=gaps, k1=stiff, k2=st.floats(0.0, 1e8), k3=stiff, w=st.floats(1e-7, 1e-2))
def test_g1_smooth_within_error_bound(a, b, k1, k2, k3, w):
    d = _grid(a, b, extra=0.02)
    err = np.abs(laws.g1_smooth(d, a, b, k1, k2, k3, w) - laws.g1(d, a, b, k1, k2, k3))
    bound = laws.g1_smooth_error_bound(k1, k2, k3, w)
    assert np.max(err) <= bound * (1 + 1e-9) + 1e-9 * max(k1, k3) * 0.05


@SETTINGS
@given(a=pos_gaps, b=pos_gaps, k1=stiff, k3=stiff)
def test_g1_smooth_converges_linearly_in_w(a, b, k1, k3):
    # the worst error sits on a kink and is ~ k*w/2: halving w halves it (error ∝ w)
    d = np.sort(np.concatenate([_grid(a, b, extra=0.01), [-a, b]]))
    g = laws.g1(d, a, b, k1, 0.0, k3)
    w0 = 1e-3 * min(a, b, 1e-3)
    errs = [np.max(np.abs(laws.g1_smooth(d, a, b, k1, 0.0, k3, w) - g)) for w in (w0, w0 / 2,
                                                                                w0 / 4)]
    assert errs[2] < errs[1] < errs[0]
    assert errs[0] / errs[1] == pytest.approx(2.0, rel=0.02)
    assert errs[1] / errs[2] == pytest.approx(2.0, rel=0.02)
    assert errs[0] == pytest.approx(max(k1, k3) * w0 / 2, rel=0.02)


@SETTINGS
@given(a0=st.floats(1e5, 1e8), sigma=st.floats(10.0, 1e4))
def test_g3_far_field_is_g1_with_apparent_gap(a0, sigma):
    # g3 -> (pi/2)*a0*(d - sign(d)*2/(pi*sigma)): g1 with k = pi*a0/2, a = b = 2/(pi*sigma);
    # the remainder is a0/(3*sigma**3*d**2) + O(d**-4)
    k, half = math.pi * a0 / 2, 2.0 / (math.pi * sigma)
    d = np.array([-1.0, -0.3, 0.3, 1.0]) * 20.0 / sigma
    err = np.abs(laws.g3(d, a0, sigma) - laws.g1(d, half, half, k, 0.0, k))
    np.testing.assert_allclose(err, a0 / (3 * sigma ** 3 * d ** 2), rtol=0.02)


@pytest.mark.parametrize("law", [laws.g3, laws.g4])
def test_g3_g4_approach_tight_g1_as_sigma_grows(law):
    # seed 1.2: "the larger sigma, the closer g3, g4 to the piecewise linear g1"; far from
    # zero (|d| >= 1e-3 rad) the distance to the tight law falls towards zero
    k = 1.0e7
    a0 = 2 * k / math.pi if law is laws.g3 else k
    d = np.concatenate([np.linspace(-0.05, -1e-3, 500), np.linspace(1e-3, 0.05, 500)])
    dist = [np.max(np.abs(law(d, a0, s) - laws.g1(d, 0.0, 0.0, k, 0.0, k))) / (k * 0.05)
            for s in (1e2, 1e3, 1e4, 1e5, 1e6)]
    assert all(x >= y for x, y in zip(dist, dist[1:]))
    assert dist[0] > 1e-2 > 1e-4 > dist[-1]


@SETTINGS
@given(a=gaps, b=gaps, k=stiff, knee=st.floats(1e-4, 0.01), ratio=st.floats(0.05, 20.0),
       side=st.sampled_from([-1.0, 1.0]))
def test_slope_beyond_knee_is_k_after(a, b, k, knee, ratio, side):
    k_after = ratio * k
    contact = b if side > 0 else -a
    d0 = contact + side * (knee + 1e-3)
    h = 1e-5
    slope = (laws.piecewise(d0 + h, a, b, k, 0.0, k, knee, k_after)
             - laws.piecewise(d0 - h, a, b, k, 0.0, k, knee, k_after)) / (2 * h)
    assert slope == pytest.approx(k_after, rel=1e-6)
    # and k between contact and knee
    d1 = contact + side * knee / 2
    slope1 = (laws.piecewise(d1 + knee / 8, a, b, k, 0.0, k, knee, k_after)
              - laws.piecewise(d1 - knee / 8, a, b, k, 0.0, k, knee, k_after)) / (knee / 4)
    assert slope1 == pytest.approx(k, rel=1e-6)


def test_piecewise_smooth_tends_to_piecewise():
    a, b, k, knee, k_after = 0.001, 0.002, 1e7, 0.003, 3e6
    d = _grid(a, b)
    exact = laws.piecewise(d, a, b, k, 0.0, k, knee, k_after)
    errs = [np.max(np.abs(laws.piecewise_smooth(d, a, b, k, 0.0, k, w, knee, k_after) - exact))
            for w in (1e-4, 1e-5, 1e-6)]
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < k * 1e-6


# --- numpy and casadi agree -----------------------------------------------------------------

_P = dict(a=0.0012, b=0.0007, k1=2.0e7, k2=3.0e5, k3=1.5e7, w=2e-4, knee=0.002, k_after=6e6)
_LAWS = {
    "g1": (lambda d, p, xp: laws.g1(d, p["a"], p["b"], p["k1"], p["k2"], p["k3"], xp)),
    "g2": (lambda d, p, xp: laws.g2(d, p["k1"], 3e8, 4e11, xp)),
    "g3": (lambda d, p, xp: laws.g3(d, p["k1"], 500.0, xp)),
    "g4": (lambda d, p, xp: laws.g4(d, p["k1"], 300.0, xp)),
    "piecewise": (lambda d, p, xp: laws.piecewise(d, p["a"], p["b"], p["k1"], p["k2"], p["k3"],
                                                  p["knee"], p["k_after"], xp)),
    "smooth_max": (lambda d, p, xp: laws.smooth_max(d, p["w"], xp)),
    "smooth_min": (lambda d, p, xp: laws.smooth_min(d, p["w"], xp)),
    "g1_smooth": (lambda d, p, xp: laws.g1_smooth(d, p["a"], p["b"], p["k1"], p["k2"], p["k3"],
                                                  p["w"], xp)),
    "piecewise_smooth": (lambda d, p, xp: laws.piecewise_smooth(
        d, p["a"], p["b"], p["k1"], p["k2"], p["k3"], p["w"], p["knee"], p["k_after"], xp)),
}
_D = np.concatenate([np.linspace(-0.01, 0.01, 201), [-0.0012, 0.0007, 0.0]])


@pytest.mark.parametrize("sym", [ca.SX, ca.MX], ids=["SX", "MX"])
@pytest.mark.parametrize("name", sorted(_LAWS))
def test_numpy_and_casadi_agree(name, sym):
    law = _LAWS[name]
    d = sym.sym("d")
    # the gap and smoothing parameters as symbols too, as in the collocation fit
    ps = {key: sym.sym(key) for key in _P}
    f = ca.Function("f", [d, *ps.values()], [law(d, ps, ca)])
    got = np.array(f.map(len(_D))(_D[None, :], *_P.values())).ravel()
    np.testing.assert_allclose(got, law(_D, _P, np), rtol=1e-12, atol=1e-9)


def test_element_torque_law_matches_piecewise(mill):
    e = mill.element("C46")
    d = _grid(e.a, e.b)
    np.testing.assert_array_equal(laws.element_torque_law(e, d),
                                  laws.g1(d, e.a, e.b, e.k, e.k_gap, e.k))
    sm = laws.element_torque_law(e, d, smoothing=1e-5)
    assert np.max(np.abs(sm - laws.g1(d, e.a, e.b, e.k, 0.0, e.k))) <= \
        laws.g1_smooth_error_bound(e.k, 0.0, e.k, 1e-5) * (1 + 1e-9)
