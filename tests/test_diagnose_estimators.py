"""The diagnosis estimators follow scikit-learn's contract, and say "don't know" out of range."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.utils.estimator_checks import parametrize_with_checks
from threadpoolctl import threadpool_limits

from ident.diagnose.estimators import (GapRegressor, NoveltyDetector, WearClassifier,
                                       shrink_to_uniform)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One thread: on a busy machine the trees' OpenMP spin-waiting costs 20x the work."""
    with threadpool_limits(1):
        yield


@parametrize_with_checks([
    WearClassifier(max_iter=10, random_state=0),
    WearClassifier(max_iter=10, calibration=None, novelty=False, random_state=0),
    GapRegressor(max_iter=10, random_state=0),
    NoveltyDetector(),
])
def test_sklearn_contract(estimator, check):
    check(estimator)


def _blobs(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    y = rng.integers(0, 3, n)
    X = rng.normal(0, 1, (n, 6))
    X[:, 0] += 3.0 * y
    X[:, 1] -= 2.0 * y
    return X, np.array(["good", "worn", "critical"])[y]


def test_classifier_is_uncertain_outside_its_training_range():
    rng = np.random.default_rng(0)
    X, y = _blobs(300, rng)
    clf = WearClassifier(max_iter=50, random_state=0).fit(X, y)
    Xt, yt = _blobs(200, rng)
    p_in = clf.predict_proba(Xt)
    assert np.mean(clf.predict(Xt) == yt) > 0.9
    assert np.median(p_in.max(axis=1)) > 0.8
    # far outside: every feature 10 scales away; trees alone would still be confident
    Xo = Xt + 20.0
    raw = WearClassifier(max_iter=50, novelty=False, random_state=0).fit(X, y)
    assert np.median(raw.predict_proba(Xo).max(axis=1)) > 0.6
    p_out = clf.predict_proba(Xo)
    assert np.all(p_out.max(axis=1) < 0.4)
    assert np.all(clf.novelty_ratio(Xo) > 2.0)
    assert np.mean(clf.novelty_ratio(Xt) > 1.0) < 0.1


def test_missing_features_are_imputed():
    rng = np.random.default_rng(1)
    X, y = _blobs(200, rng)
    X[rng.random(X.shape) < 0.1] = np.nan
    clf = WearClassifier(max_iter=30, random_state=0).fit(X, y)
    assert np.all(np.isfinite(clf.predict_proba(X)))
    reg = GapRegressor(max_iter=30, random_state=0).fit(X, np.arange(200.0))
    lo_hi = reg.predict_interval(X)
    assert lo_hi.shape == (200, 2) and np.all(lo_hi[:, 0] <= lo_hi[:, 1])


def test_shrink_to_uniform():
    p = np.array([[1.0, 0.0, 0.0], [0.2, 0.3, 0.5]])
    np.testing.assert_allclose(shrink_to_uniform(p, np.array([0.5, 0.9])), p)
    np.testing.assert_allclose(shrink_to_uniform(p, np.array([3.0, 3.0])), np.full((2, 3), 1 / 3))
    np.testing.assert_allclose(shrink_to_uniform(p, np.array([1.5, 1.0]))[0], [2 / 3, 1 / 6, 1 / 6])


@pytest.mark.parametrize("kwargs, match", [
    ({"quantile": 1.5}, "'quantile' parameter of NoveltyDetector must be in"),
    ({"n_neighbors": 0}, "'n_neighbors' parameter of NoveltyDetector must be >= 1"),
])
def test_novelty_detector_refuses_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        NoveltyDetector(**kwargs).fit(np.zeros((10, 2)))


def test_classifier_refuses_bad_calibration():
    with pytest.raises(ValueError, match="'calibration' parameter of WearClassifier"):
        WearClassifier(calibration="magic").fit(np.zeros((10, 2)), np.arange(10) % 2)


def test_gap_regressor_interval_probabilities_are_calibrated():
    """y = x0 + noise (sd 0.3): the probability of y's interval between two limits, read off
    the out-of-fold residuals of similar predictions, matches the truth's frequency."""
    rng = np.random.default_rng(2)
    X = rng.uniform(0, 3, (600, 3))
    y = X[:, 0] + rng.normal(0, 0.3, 600)
    reg = GapRegressor(max_iter=60, random_state=0).fit(X, y)
    Xt = rng.uniform(0, 3, (400, 3))
    yt = Xt[:, 0] + rng.normal(0, 0.3, 400)
    P = reg.predict_bin_proba(Xt, (1.0, 2.0))
    np.testing.assert_allclose(P.sum(axis=1), 1.0)
    hit = np.digitize(yt, (1.0, 2.0))
    for k in range(3):  # reliability: predicted vs observed share of each interval
        assert abs(P[:, k].mean() - np.mean(hit == k)) < 0.06
    assert np.mean(np.argmax(P, axis=1) == hit) > 0.75
    with pytest.raises(ValueError, match="'edges' parameter of predict_bin_proba"):
        reg.predict_bin_proba(Xt, (2.0, 1.0))


def test_the_regressed_gaps_of_the_seen_elements_are_the_fits_data_start():
    from ident.diagnose.model import Diagnosis, TargetDiagnosis

    def td(size: float, observable: bool) -> TargetDiagnosis:
        return TargetDiagnosis(state="worn", probability=0.8,
                               probabilities={"good": 0.1, "worn": 0.8, "critical": 0.1},
                               size=size, interval=(0.5 * size, 1.5 * size),
                               observable=observable, uncertain=False, novelty=0.2)

    d = Diagnosis(elements={"C12": td(6.6e-3, True), "C23": td(2e-3, False)},
                  bearings={"B23": td(3e-4, True)})
    assert d.gap_start() == {"C12": 6.6e-3}
