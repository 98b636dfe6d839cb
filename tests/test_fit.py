"""Gap identification (``ident.fit``) on simulated recordings of known gaps.

Every recording goes the way ``ident fit`` reads one: the nonlinear driveline
simulated through random bars (static torque 25-100 % of nominal, drawn per
bar, the rolling load fluctuating 1 %), telemetry noise at 35 dB and 16-bit
quantisation, written to MCAP, read back, segmented and windowed
(:func:`ident.fit.synthetic_case`).  Gaps are drawn from a seed: spindles
C46/C57 2-9 mrad, the other elements 0.3-1.5 mrad.

Two kinds of tests:

* **statistics** (single shooting, 0.3 s release windows): the estimate *at*
  the optimum nearest the truth -- started from the simulated truth, so the
  search for it is not what is tested -- its 95 % intervals against the
  truth, against a profile likelihood, and the noise-floor check;
* **the method** (collocation through :func:`ident.fit.fit_gaps` from the mill
  file's designed gaps): gaps recovered, nrmse below the linear baseline's,
  closed gaps found closed, an unseen gap flagged.

Measured on the 2-core CI box (see each docstring): the statistics draws
about 4 s CPU each.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ident.fit import (Collocation, SingleShooting, assess, build_fit_model, fit_gaps,
                       make_problem, random_gaps, synthetic_case)
from ident.fit.result import NOISE_RATIO_MAX
from ident.fit.uncertainty import Z95

MEASURED = ("C12", "C34", "C46", "C57")
FINAL = 3e-5


def draw(mill, seed: int) -> dict[str, float]:
    """A worn state: spindles 2-9 mrad, the rest 0.3-1.5 mrad, open parts uniform."""
    rng = np.random.default_rng(seed)
    over = random_gaps(mill, rng, elements=("C46", "C57"), gap_range=(2e-3, 9e-3))
    over.update(random_gaps(mill, rng, elements=("C12", "C23", "C34", "C45"),
                            gap_range=(3e-4, 1.5e-3)))
    return over


def tolerance(truth: float) -> float:
    """Issue 4's accuracy: max(10 %, 0.3 mrad)."""
    return max(0.1 * truth, 3e-4)


def at_truth(mill, seed: int, tmp_path, **case_kw):
    """Fit one simulated recording by single shooting started at its truth."""
    case = synthetic_case(mill, draw(mill, seed), seed=seed, directory=tmp_path, **case_kw)
    model = build_fit_model(mill)
    problem = make_problem(model, case.windows)
    sh = SingleShooting(widths=(FINAL,), settle=(), horizons=())
    start = case.true_estimate(problem)
    held = problem.with_free(np.zeros(model.n_shared, dtype=bool))
    est, info = sh.solve(held, start)
    est, info = sh.solve(problem, est)
    return case, problem, sh, est, info


# ---- statistics ------------------------------------------------------------------------
STAT_SEEDS = tuple(range(100, 108))


@pytest.fixture(scope="module")
def stat_fits(mill, tmp_path_factory):
    out = []
    for seed in STAT_SEEDS:
        case, problem, sh, est, info = at_truth(
            mill, seed, tmp_path_factory.mktemp(f"stat{seed}"), n_bars=1, window_s=0.3,
            max_windows=1, kinds=("release",))
        out.append((case, problem, sh, est, info, assess(problem, sh, est)))
    return out


@pytest.mark.slow
def test_intervals_cover_the_truth(stat_fits):
    """95 % intervals cover the truth in at least 90 % of parameters x draws.

    8 draws x 6 elements, one 0.3 s release each; measured: 46 of 48 covered
    (96 %), every gap of every draw flagged identifiable but C23 twice.
    """
    covered = total = 0
    for case, problem, sh, est, info, a in stat_fits:
        assert info.success, info.status
        for eid, el in a.elements.items():
            g = case.truth[eid]["gap"]
            total += 1
            covered += el.gap_ci95[0] <= g <= el.gap_ci95[1]
    assert covered / total >= 0.9, f"{covered}/{total} intervals cover the truth"


@pytest.mark.slow
def test_noise_floor_is_reached_at_the_truth(stat_fits):
    """At the optimum nearest the truth the residuals are the sensor noise.

    The noise is estimated from the data alone (fourth differences); measured
    ratios 0.97-1.06, well below the limit above which a fit is declared a
    local minimum.
    """
    ratios = [a.noise_ratio for *_, a in stat_fits]
    assert all(0.85 < r < NOISE_RATIO_MAX for r in ratios), ratios


@pytest.mark.slow
def test_transient_band_is_at_the_noise_at_the_truth(stat_fits):
    """The verdict's statistic (ident.fit.verdict): at the optimum nearest the truth every
    channel's residual in the transient band is the sensor noise's there, so every directly
    measured gap is identified.  One 0.3 s window has about 27 bins per channel in the band
    and the fit's ~26 parameters act there too, so single ratios spread (0.3-1.3 measured)
    below 1; their mean over draws and channels is near 1."""
    from ident.fit.noise import BAND_RATIO_MAX

    ratios = []
    for case, problem, sh, est, info, a in stat_fits:
        assert a.band.all_pass, a.band.ratio
        assert all(v < BAND_RATIO_MAX for v in a.band.ratio.values()), a.band.ratio
        ratios += list(a.band.ratio.values())
        for eid in MEASURED:
            el = a.elements[eid]
            assert el.identified == el.identifiable, (case.path.name, eid, el.reason)
    assert 0.6 < np.mean(ratios) < 1.2, ratios


@pytest.mark.slow
def test_measured_gaps_are_accurate_at_the_optimum(stat_fits):
    """Directly measured elements within max(10 %, 0.3 mrad) in every draw."""
    for case, problem, sh, est, info, a in stat_fits:
        for eid in MEASURED:
            g = case.truth[eid]["gap"]
            assert abs(a.elements[eid].gap - g) <= tolerance(g), (case.path.name, eid)


@pytest.mark.slow
def test_interval_agrees_with_profile_likelihood(stat_fits):
    """The noise part of C46's Wald interval against the profile likelihood.

    At ``gap +- 1.96 gap_se_noise`` (the reported interval adds the model
    error's part, ``gap_se_model``), with every other parameter refitted,
    twice the rise of the noise-weighted cost should be chi2(1)'s 95 % point,
    3.84; measured 3.3-4.4 (the profile is nearly quadratic over the interval).
    """
    case, problem, sh, est, info, a = stat_fits[0]
    model = problem.model
    j = model.shared_names.index("C46.gap")
    sigma = a.covariance.sigma

    def chi2(e) -> float:
        r, _ = sh.residuals(problem, e, FINAL)
        ch = np.arange(r.size) % model.ny
        return float(np.sum((r / sigma[ch]) ** 2))

    base = chi2(est)
    free = np.ones(model.n_shared, dtype=bool)
    free[j] = False
    held = problem.with_free(free)
    el = a.elements["C46"]
    assert el.gap_se == pytest.approx(math.hypot(el.gap_se_noise, el.gap_se_model))
    for end in (el.gap - Z95 * el.gap_se_noise, el.gap + Z95 * el.gap_se_noise):
        shared = est.shared.copy()
        shared[j] = end
        from dataclasses import replace

        e, inf = sh.solve(held, replace(est, shared=shared))
        assert inf.success, inf.status
        assert 2.0 < chi2(e) - base < 7.7, (end, chi2(e) - base)


# ---- the method ----------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.timeout(1500)  # 601-694 s measured beside another test; the default 900 s is close
def test_closed_gaps_are_found_closed(mill, tmp_path):
    """Every gap closed: the fit finds gaps near zero and no better fit than linear."""
    closed = {f"{e.id}.{k}": 0.0 for e in mill.elements for k in ("gap", "gap_open")}
    case = synthetic_case(mill, closed, seed=5, n_bars=1, directory=tmp_path)
    res = fit_gaps(mill, case.windows)
    assert res.converged
    for eid, el in res.elements.items():
        assert el.gap <= 3e-4, (eid, el.gap)
    assert res.nrmse == pytest.approx(res.nrmse_linear, rel=0.1)


def test_unseen_gap_is_flagged(mill, tmp_path):
    """A bite alone never swings the spindles to their back flanks: their total gaps unseen.

    Single shooting on one 0.3 s bite from rest: C46's total gap (8 mrad,
    4 open) is flagged not identifiable and its interval runs to the bound,
    covering the truth, instead of a confident number.
    """
    over = {"C46.gap": 0.008, "C46.gap_open": 0.004, "C57.gap": 0.005, "C57.gap_open": 0.002}
    case = synthetic_case(mill, over, seed=9, n_bars=1, max_windows=1, kinds=("bite",),
                          directory=tmp_path)
    res = fit_gaps(mill, case.windows, method=SingleShooting(horizons=()))
    el = res.elements["C46"]
    assert not el.identifiable
    assert el.gap_ci95[0] <= 0.008 <= el.gap_ci95[1]
    assert el.gap_ci95[1] == pytest.approx(build_fit_model(mill).gap_max)
    assert any("C46" in w and "not identifiable" in w for w in res.warnings)


def test_bad_input_raises_fit_errors(mill, tmp_path):
    from ident.errors import FitError

    with pytest.raises(FitError, match="at least one FitWindow"):
        fit_gaps(mill, [])
    case = synthetic_case(mill, None, seed=2, n_bars=1, max_windows=1, kinds=("bite",),
                          directory=tmp_path)
    with pytest.raises(FitError, match="family must be one of"):
        fit_gaps(mill, case.windows, family="g7")
    with pytest.raises(FitError, match="unknown element 'C99'"):
        fit_gaps(mill, case.windows, starts=[{"C99": 0.001}])
    with pytest.raises(FitError, match="data_starts: unknown element 'C99'"):
        fit_gaps(mill, case.windows, data_starts=[{"C99": 0.001}])
    with pytest.raises(FitError, match="method must be"):
        fit_gaps(mill, case.windows, method="ipopt")
    with pytest.raises(FitError, match="elements_per_sample"):
        Collocation(elements_per_sample=0.3)
    assert math.isfinite(case.windows[0].dt)
