"""The noise estimate and the transient-band ratio of the fit's verdict (ident.fit.noise).

Closed forms: white noise of variance s**2 at rate fs has the one-sided density
2 s**2 / fs; its band ratio against that density is 1 with standard deviation
about sqrt(2 / bins).  Anti-alias-filtered noise keeps that density in the pass
band, where the fourth difference (most of its weight near Nyquist) reads it low.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from ident.fit.noise import BAND_RATIO_MAX, band_ratio, bands, density, noise_spectrum
from ident.fit.uncertainty import noise_floor

FS = 2000.0
N = 600


def test_white_noise_density_is_its_closed_form():
    rng = np.random.default_rng(0)
    x = rng.normal(0.0, 3.0, (N, 200))
    f, P = density(x, 1 / FS)
    m = (f > 20) & (f < 900)
    assert np.mean(P[m]) == pytest.approx(2 * 9.0 / FS, rel=0.02)


def test_band_ratio_of_white_noise_is_one():
    rng = np.random.default_rng(1)
    level = 2 * 4.0 / FS
    ratios = [band_ratio([rng.normal(0, 2.0, N) for _ in range(4)], 1 / FS, (10, 100), level)[0]
              for _ in range(200)]
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.03)
    assert np.std(ratios) < 0.25
    assert np.max(ratios) < BAND_RATIO_MAX


def _aa_noise(rng, n, sigma, decim=10):
    """White noise at decim * FS, anti-alias filtered (Butterworth, 0.4 FS) and decimated."""
    b, a = signal.butter(6, 0.4 * FS, fs=decim * FS)
    x = rng.normal(0.0, sigma, n * decim + 4000)
    return signal.lfilter(b, a, x)[4000::decim][:n]


def test_recording_noise_holds_for_anti_alias_filtered_noise():
    """The median density in the noise band gives the pass band's level; the fourth
    difference reads the same noise 2-3x low in variance."""
    rng = np.random.default_rng(2)
    n = 40_000
    sigma = 5.0
    y = _aa_noise(rng, n, sigma)
    t = np.arange(n) / FS
    true_level = 2 * sigma ** 2 / (10 * FS)  # density of the fast white noise, kept in the pass band
    step = 2000  # a "load step" with a ring-down that the estimate must leave out
    y = y + np.where(t > 5.0, 400.0 * (1 - np.exp(-(t - 5.0) * 3) * np.cos(2 * np.pi * 15 * (t - 5))), 0)
    ns = noise_spectrum(t, y[:, None], ["C1"], segment_n=N, exclude=[(4.9, 5.5)])
    bd = bands([12.0, 81.0], FS, N / FS)
    assert ns.level("C1", bd.noise) == pytest.approx(true_level, rel=0.1)
    four = noise_floor([y[:step, None]], np.array([1.0]))[0] ** 2
    white_equiv = true_level * FS / 2  # the variance white noise of that level would have
    assert four < 0.6 * white_equiv


def test_bands_sit_between_the_modes_and_below_the_anti_alias_edge():
    bd = bands([12, 15, 20, 34, 45, 81], 2000.0, 0.3)
    assert bd.transient == pytest.approx((10.0, 101.25))
    assert bd.noise[0] >= bd.transient[1] and bd.noise[1] == pytest.approx(600.0)
    low = bands([9.0, 60.0, 190.0], 1000.0, 0.3)  # modes near the top of a slow recording
    assert low.noise[1] - low.noise[0] >= 6 / 0.3 - 1e-9
    assert low.transient[1] <= 0.3 * 1000.0
