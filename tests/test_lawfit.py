"""Fitting the smooth laws g2, g3, g4 to g1 (ident.model.lawfit, seed section 1.2).

What the seed says and what we measure (spindle gap a = 0.002, b = 0 rad,
k = 1.815e7 N*m/rad; the table is in ident/model/lawfit.py's docstring):

* g3 and g4 are more accurate than g2 beyond +-2(a+b) -- reproduced;
* g2 is more accurate than g3/g4 within +-2(a+b) -- NOT reproduced by least
  squares: g3 and g4 beat g2 inside too, at every amplitude we tried.  The test
  below pins that finding so that a change in either direction is noticed;
* a2 > sqrt(3*a1*a3) or a1 < 0 gives two extrema: LawShapeWarning.
"""

from __future__ import annotations

import dataclasses
import math
import pickle
import warnings

import casadi as ca
import numpy as np
import pytest

from ident.errors import ConvergenceWarning
from ident.model.lawfit import LawFit, LawShapeWarning, fit_law, g2_is_monotone
from ident.model.laws import g1, g2, g3, g4

K = 1.815e7          # N*m/rad, C46 of hsm-f1
A_GAP, B_GAP = 0.002, 0.0   # rad: the spindle's designed gap, all of it closed


def _fit(family, amplitude, a=A_GAP, b=B_GAP, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning expected on these well-posed fits
        return fit_law(family, a=a, b=b, k1=K, k3=K, amplitude=amplitude, **kw)


def test_result_is_frozen_picklable_and_in_si():
    fit = _fit("g3", 0.01)
    assert isinstance(fit, LawFit)
    with pytest.raises(dataclasses.FrozenInstanceError):
        fit.shift = 0.0
    assert pickle.loads(pickle.dumps(fit)) == fit
    assert set(fit.params) == {"a0", "sigma"}
    assert fit.shift == pytest.approx((B_GAP - A_GAP) / 2)
    # SI: a0 near the closed-form start 2k/pi, sigma near 4/(pi*(a+b)) (1/rad)
    assert fit.params["a0"] == pytest.approx(2 * K / math.pi, rel=0.1)
    assert fit.params["sigma"] == pytest.approx(4 / (math.pi * (A_GAP + B_GAP)), rel=0.3)
    d = np.linspace(-0.01, 0.01, 7)
    np.testing.assert_allclose(fit.torque(d), g3(d - fit.shift, fit.params["a0"],
                                                  fit.params["sigma"]))
    np.testing.assert_allclose(fit.target(d), g1(d, A_GAP, B_GAP, K, 0.0, K))


def test_torque_scale_is_max_abs_g1():
    fit = _fit("g2", 0.01)
    # the open side b = 0 reaches the larger magnitude: k*(amplitude - b), N*m
    assert fit.torque_scale == pytest.approx(K * (0.01 - B_GAP))
    other = _fit("g2", 0.01, a=0.0005, b=0.003)
    assert other.torque_scale == pytest.approx(K * (0.01 - 0.0005))


def test_g2_coefficients_from_linear_least_squares():
    fit = _fit("g2", 0.01)
    d = np.linspace(-0.01, 0.01, 2001)
    coef, *_ = np.linalg.lstsq(np.column_stack([d, d ** 2, d ** 3]),
                               g1(d, A_GAP, B_GAP, K, 0.0, K), rcond=None)
    p = fit.params
    np.testing.assert_allclose([p["a1"], p["a2"], p["a3"]], coef, rtol=1e-8)
    assert fit.shift == 0.0
    # the square term carries the asymmetry a != b (seed 1.2): a2 > 0 when the open side is b=0
    assert p["a2"] > 0
    np.testing.assert_allclose(fit.torque(d), g2(d, p["a1"], p["a2"], p["a3"]))


def test_symmetric_gap_gives_no_square_term_and_no_shift():
    for family in ("g2", "g3", "g4"):
        fit = _fit(family, 0.01, a=0.001, b=0.001)
        assert fit.shift == 0.0
        if family == "g2":
            assert fit.params["a2"] == 0.0


@pytest.mark.parametrize("family", ["g3", "g4"])
def test_g3_g4_fitted_around_gap_centre(family):
    # a != b: the same gap shifted fits equally well, with shift = (b - a)/2
    centred = _fit(family, 0.01, a=0.001, b=0.001)
    shifted = _fit(family, 0.01 + 0.0005, a=0.0015, b=0.0005)
    assert shifted.shift == pytest.approx(-0.0005)
    assert shifted.params["a0"] == pytest.approx(centred.params["a0"], rel=0.05)
    assert shifted.params["sigma"] == pytest.approx(centred.params["sigma"], rel=0.05)
    law = g3 if family == "g3" else g4
    d = np.linspace(-0.0105, 0.0095, 11)
    np.testing.assert_allclose(shifted.torque(d), law(d + 0.0005, shifted.params["a0"],
                                                      shifted.params["sigma"]))


def test_fit_in_scaled_variables_is_unit_invariant():
    # the seed: unscaled fits work only for small dimensionless gaps/stiffnesses; ours must
    # give the same relative errors whatever the units (N*m/rad vs MN*m/rad, rad vs mrad)
    si = _fit("g3", 0.01)
    other = fit_law("g3", a=A_GAP * 1e3, b=0.0, k1=K * 1e-6, k3=K * 1e-6, amplitude=10.0)
    assert other.rms_total == pytest.approx(si.rms_total, rel=1e-4)
    assert other.params["sigma"] * 1e3 == pytest.approx(si.params["sigma"], rel=1e-4)


@pytest.mark.parametrize("amplitude", [0.010, 0.020, 0.040])
def test_seed_ranking_beyond_2ab_reproduced(amplitude):
    fits = {f: _fit(f, amplitude) for f in ("g2", "g3", "g4")}
    # seed 1.2: g3, g4 more accurate for large amplitudes beyond +-2(a+b)
    assert fits["g3"].rms_beyond < fits["g2"].rms_beyond / 2.5
    assert fits["g4"].rms_beyond < fits["g2"].rms_beyond / 2.0
    assert fits["g3"].max_beyond < fits["g2"].max_beyond
    assert fits["g4"].max_beyond < fits["g2"].max_beyond


@pytest.mark.parametrize("amplitude", [0.004, 0.010, 0.020, 0.040])
def test_seed_ranking_inside_2ab_not_reproduced(amplitude):
    # seed 1.2 says g2 is the more accurate within +-2(a+b); least squares disagrees by
    # a factor 3-8 in RMS (see the module docstring).  If this starts failing, the finding
    # in ident/model/lawfit.py's docstring needs rewriting.
    fits = {f: _fit(f, amplitude) for f in ("g2", "g3", "g4")}
    assert fits["g2"].rms_inside > 3 * fits["g3"].rms_inside
    assert fits["g2"].rms_inside > 3 * fits["g4"].rms_inside


def test_measured_errors_of_the_docstring_table():
    # the 5(a+b) row of the module docstring, in % of max|g1|
    got = {f: _fit(f, 0.010) for f in ("g2", "g3", "g4")}
    table = {"g2": (7.7, 4.5), "g3": (1.2, 0.33), "g4": (1.0, 0.65)}
    for family, (inside, beyond) in table.items():
        assert 100 * got[family].rms_inside == pytest.approx(inside, rel=0.05)
        assert 100 * got[family].rms_beyond == pytest.approx(beyond, rel=0.05)


def test_g3_far_field_error_falls_with_amplitude():
    beyond = [_fit("g3", amp).rms_beyond for amp in (0.006, 0.01, 0.02, 0.04)]
    assert all(x > y for x, y in zip(beyond, beyond[1:]))


def test_g2_fitted_near_gap_deviates_beyond_its_range():
    # seed 1.2: g2 "crosses g1 and begins to deviate significantly" away from the gap
    near = _fit("g2", 2 * (A_GAP + B_GAP) + 0.002)
    near3 = _fit("g3", 2 * (A_GAP + B_GAP) + 0.002)
    d = np.linspace(0.02, 0.04, 50)
    target = g1(d, A_GAP, B_GAP, K, 0.0, K)
    err2 = np.max(np.abs(near.torque(d) - target)) / np.max(np.abs(target))
    err3 = np.max(np.abs(near3.torque(d) - target)) / np.max(np.abs(target))
    assert err2 > 1.0 > 0.1 > err3


def test_errors_are_regional_and_nan_when_beyond_is_empty():
    fit = _fit("g4", 2 * (A_GAP + B_GAP))
    assert math.isnan(fit.rms_beyond) and math.isnan(fit.max_beyond)
    assert 0 < fit.rms_inside <= fit.max_inside
    assert fit.rms_total == pytest.approx(fit.rms_inside)


def test_tight_coupling_is_fitted_exactly():
    # no gap: g1 is linear, g2 gives a1 = k exactly; g3 drives sigma up to a tiny apparent gap
    fit2 = _fit("g2", 0.01, a=0.0, b=0.0)
    assert fit2.params == pytest.approx({"a1": K, "a2": 0.0, "a3": 0.0}, abs=1e-6 * K)
    assert fit2.rms_total < 1e-12
    fit3 = fit_law("g3", a=0.0, b=0.0, k1=K, k3=K, amplitude=0.01)
    assert fit3.rms_total < 1e-3


def test_shape_warning_when_g2_has_two_extrema():
    # amplitude barely past a wide symmetric gap: the cubic dips, a1 < 0 (seed 1.2)
    with pytest.warns(LawShapeWarning, match=r"maximum and a minimum instead of a saddle point"):
        fit = fit_law("g2", a=0.002, b=0.002, k1=K, k3=K, amplitude=0.004)
    p = fit.params
    assert p["a1"] < 0
    assert not g2_is_monotone(p["a1"], p["a2"], p["a3"])
    d = np.linspace(-0.004, 0.004, 401)
    assert np.any(np.diff(fit.torque(d)) < 0)  # the warning is not a false alarm


def test_shape_warning_for_square_term_too_large():
    # asymmetric gap, amplitude just past it: a2 > sqrt(3*a1*a3) with a1 > 0
    with pytest.warns(LawShapeWarning, match=r"a2 > sqrt\(3\*a1\*a3\)"):
        fit = fit_law("g2", a=0.002, b=0.0, k1=K, k3=K, amplitude=0.0025)
    p = fit.params
    assert p["a1"] > 0 and p["a2"] > math.sqrt(3 * p["a1"] * p["a3"])


def test_g2_is_monotone_condition():
    assert g2_is_monotone(1.0, 0.0, 1.0)
    assert g2_is_monotone(3.0, 3.0, 1.0)            # a2**2 == 3*a1*a3: a saddle point
    assert not g2_is_monotone(3.0, 3.0001, 1.0)
    assert not g2_is_monotone(3.0, -3.0001, 1.0)    # the mirrored case has two extrema too
    assert not g2_is_monotone(-1.0, 0.0, 1.0)
    assert not g2_is_monotone(1.0, 0.0, -1.0)
    assert not g2_is_monotone(0.0, 0.0, -1.0)      # -d**3 falls everywhere
    assert g2_is_monotone(0.0, 0.0, 0.0)
    # cross-check against the sign of the derivative on a wide grid
    rng = np.random.default_rng(7)
    d = np.linspace(-10, 10, 20001)
    for a1, a2, a3 in rng.normal(size=(200, 3)):
        slope = a1 + 2 * a2 * d + 3 * a3 * d ** 2
        # the grid is wide enough for |roots| < 10 in these draws; skip the rare others
        roots = np.roots([3 * a3, 2 * a2, a1]) if a3 != 0 else np.array([])
        if np.any(np.abs(roots) > 9):
            continue
        assert g2_is_monotone(a1, a2, a3) == bool(np.all(slope >= -1e-12))


def test_fitted_law_evaluates_in_casadi():
    fit = _fit("g4", 0.01)
    d = ca.SX.sym("d")
    f = ca.Function("f", [d], [fit.torque(d, xp=ca)])
    x = np.linspace(-0.01, 0.01, 9)
    np.testing.assert_allclose(np.array(f.map(9)(x[None, :])).ravel(), fit.torque(x),
                               rtol=1e-12)


def test_convergence_warning_on_exhausted_budget():
    with pytest.warns(ConvergenceWarning, match="without meeting its tolerance"):
        fit_law("g3", a=A_GAP, b=0.0, k1=K, k3=K, amplitude=0.01, max_nfev=2)


@pytest.mark.parametrize("kwargs, match", [
    (dict(family="g5"), r"'family' parameter of fit_law must be one of \['g2', 'g3', 'g4'\]. "
                        r"Got 'g5' instead"),
    (dict(a=-0.001), r"'a' parameter of fit_law must be a finite zero or positive number. "
                     r"Got -0.001"),
    (dict(k1=0.0), r"'k1' parameter of fit_law must be a finite positive number. Got 0.0"),
    (dict(k3=math.nan), r"'k3' parameter .* Got nan"),
    (dict(amplitude=0.0), r"'amplitude' parameter .* positive number. Got 0.0"),
    (dict(n_points=5), r"'n_points' parameter of fit_law must be an integer >= 11. Got 5"),
    (dict(a=0.002, b=0.002, amplitude=0.001), r"g1 is zero over .* must reach beyond the gap"),
])
def test_bad_arguments_are_refused(kwargs, match):
    args = dict(family="g3", a=A_GAP, b=0.0, k1=K, k3=K, amplitude=0.01) | kwargs
    family = args.pop("family")
    with pytest.raises(ValueError, match=match):
        fit_law(family, **args)


def test_options_are_keyword_only():
    with pytest.raises(TypeError):
        fit_law("g3", A_GAP, 0.0, K, 0.0, K, 0.01)  # type: ignore[misc]
