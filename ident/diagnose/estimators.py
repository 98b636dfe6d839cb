"""scikit-learn estimators of the wear diagnosis (samples x features).

* :class:`NoveltyDetector` -- how far a feature vector lies from the training
  library: mean distance to its ``k`` nearest training vectors in robustly
  scaled feature space, over the same leave-one-out distance of the training
  vectors at a high quantile.  ``score_samples`` is that ratio (1 at the
  quantile); ``predict`` marks ratios above 1 as outliers (-1).
* :class:`GapRegressor` -- a gap (or clearance) from the features:
  gradient-boosted trees (missing features allowed); ``predict_interval``
  and ``predict_bin_proba`` read the distribution of the truth around a
  prediction off the out-of-fold residuals of the training samples predicted
  alike (the state is defined by the true gap against fixed limits, so the
  state's probability is that of the gap's interval).
* :class:`WearClassifier` -- good / worn / critical: gradient-boosted trees whose
  probabilities are calibrated by cross-validation
  (``CalibratedClassifierCV``) and shrunk towards "don't know" (uniform) as the
  novelty ratio grows beyond 1, so that a recording unlike anything in the
  library gets a low probability rather than a confident wrong answer.

The libraries are a few hundred samples: the trees gain nothing from
threads, and on a busy machine OpenMP's spin-waiting costs several times the
work, so ``ident.diagnose.model`` trains and predicts under one OpenMP thread
(``threadpoolctl``).

All follow scikit-learn's contract (``__init__`` stores, validation in
``fit``, fitted attributes end in ``_``, ``random_state``) and pass
``sklearn.utils.estimator_checks.parametrize_with_checks``
(``tests/test_diagnose_estimators.py``).
"""

from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin, OutlierMixin, RegressorMixin, clone
from sklearn.calibration import CalibratedClassifierCV
from sklearn.ensemble import HistGradientBoostingClassifier, HistGradientBoostingRegressor
from sklearn.impute import SimpleImputer
from sklearn.model_selection import KFold, cross_val_predict
from sklearn.neighbors import NearestNeighbors
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import check_is_fitted, validate_data

__all__ = ["NoveltyDetector", "GapRegressor", "WearClassifier", "shrink_to_uniform"]



def _imputer() -> SimpleImputer:
    return SimpleImputer(strategy="median", keep_empty_features=True)


class NoveltyDetector(OutlierMixin, BaseEstimator):
    """Distance of feature vectors to the training library (kNN in robust scale).

    Parameters
    ----------
    n_neighbors : int
        Neighbours averaged.
    quantile : float
        Training quantile of the leave-one-out distance that maps to a ratio of 1.
    clip : float
        Robustly scaled features are clipped to +-``clip`` after scaling (in
        units of the inter-quartile range), so that one wild feature counts
        but does not swamp the rest.
    """

    def __init__(self, n_neighbors: int = 5, quantile: float = 0.99, clip: float = 25.0):
        self.n_neighbors = n_neighbors
        self.quantile = quantile
        self.clip = clip

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = True
        return tags

    def fit(self, X, y=None):
        X = validate_data(self, X, ensure_all_finite="allow-nan")
        if not 0.0 < self.quantile < 1.0:
            raise ValueError(f"The 'quantile' parameter of NoveltyDetector must be in (0, 1). "
                             f"Got {self.quantile!r} instead.")
        if int(self.n_neighbors) < 1:
            raise ValueError(f"The 'n_neighbors' parameter of NoveltyDetector must be >= 1. "
                             f"Got {self.n_neighbors!r} instead.")
        self.imputer_ = _imputer().fit(X)
        Xi = self.imputer_.transform(X)
        self.center_ = np.median(Xi, axis=0)
        q75, q25 = np.percentile(Xi, [75, 25], axis=0)
        scale = q75 - q25
        std = Xi.std(axis=0)
        scale = np.where(scale > 1e-12, scale, np.where(std > 1e-12, std, 1.0))
        self.scale_ = scale
        Z = self._scaled(Xi)
        k = min(int(self.n_neighbors), max(Z.shape[0] - 1, 1))
        self.nn_ = NearestNeighbors(n_neighbors=min(k + 1, Z.shape[0])).fit(Z)
        d, _ = self.nn_.kneighbors(Z)
        d_loo = d[:, 1:].mean(axis=1) if d.shape[1] > 1 else d[:, 0]
        self.k_ = k
        ref = float(np.quantile(d_loo, self.quantile))
        self.distance_ref_ = ref if ref > 0 else 1.0
        self.offset_ = -1.0
        return self

    def _scaled(self, Xi: np.ndarray) -> np.ndarray:
        Z = (Xi - self.center_) / self.scale_
        return np.clip(Z, -self.clip, self.clip) / np.sqrt(Xi.shape[1])

    def distance_ratio(self, X) -> np.ndarray:
        """Mean kNN distance over the training quantile's; > 1 is unusual. Shape (n,).

        A vector equal to a training vector does not count that one among its
        neighbours (the training vectors get their leave-one-out distance, the
        one the quantile was taken of).
        """
        check_is_fitted(self, "nn_")
        X = validate_data(self, X, ensure_all_finite="allow-nan", reset=False)
        Z = self._scaled(self.imputer_.transform(X))
        n_fit = self.nn_.n_samples_fit_
        k = self.k_
        d, _ = self.nn_.kneighbors(Z, n_neighbors=min(k + 1, n_fit))
        if d.shape[1] > k:
            self_match = d[:, 0] <= 1e-12
            d = np.where(self_match[:, None], d[:, 1:], d[:, :k])
        return d.mean(axis=1) / self.distance_ref_

    def score_samples(self, X) -> np.ndarray:
        """Opposite of :meth:`distance_ratio` (higher is more normal, sklearn's convention)."""
        return -self.distance_ratio(X)

    def decision_function(self, X) -> np.ndarray:
        return self.score_samples(X) - self.offset_

    def predict(self, X) -> np.ndarray:
        """+1 inside the library's range, -1 outside."""
        return np.where(self.decision_function(X) >= 0, 1, -1)


def shrink_to_uniform(proba: np.ndarray, ratio: np.ndarray, *, span: float = 1.0) -> np.ndarray:
    """Mix probabilities towards uniform as the novelty ratio exceeds 1.

    The weight of the uniform distribution is ``clip((ratio - 1) / span, 0, 1)``:
    no change inside the library's range, fully uniform ("don't know") at
    ``1 + span`` times the training distance.
    """
    proba = np.asarray(proba, dtype=float)
    w = np.clip((np.asarray(ratio, dtype=float) - 1.0) / span, 0.0, 1.0)[:, None]
    return (1.0 - w) * proba + w / proba.shape[1]


class GapRegressor(RegressorMixin, BaseEstimator):
    """Gap or clearance from features: gradient-boosted trees (missing values allowed).

    Besides the point prediction it keeps the out-of-fold predictions of the
    training set, which give the distribution of the truth around a
    prediction: :meth:`predict_interval` (residual quantiles) and
    :meth:`predict_bin_proba` (the probability of each interval between given
    limits, e.g. good / worn / critical) from the residuals of the
    ``n_local`` training samples whose out-of-fold prediction is nearest --
    calibrated where the regressor is precise and where it is not.

    Parameters
    ----------
    max_iter : int
        Boosting iterations.
    learning_rate : float
    max_leaf_nodes : int
    min_samples_leaf : int
    l2_regularization : float
    interval_quantiles : (float, float)
        Quantiles of the out-of-fold residuals that :meth:`predict_interval` adds.
    cv : int
        Folds for the out-of-fold predictions.
    n_local : int
        Training samples whose residuals make one prediction's distribution.
    random_state : int, RandomState or None
    """

    def __init__(self, max_iter: int = 300, learning_rate: float = 0.05,
                 max_leaf_nodes: int = 15, min_samples_leaf: int = 10,
                 l2_regularization: float = 0.0, interval_quantiles: tuple = (0.025, 0.975),
                 cv: int = 3, n_local: int = 40, random_state=None):
        self.max_iter = max_iter
        self.learning_rate = learning_rate
        self.max_leaf_nodes = max_leaf_nodes
        self.min_samples_leaf = min_samples_leaf
        self.l2_regularization = l2_regularization
        self.interval_quantiles = interval_quantiles
        self.cv = cv
        self.n_local = n_local
        self.random_state = random_state

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = True
        return tags

    def _model(self) -> HistGradientBoostingRegressor:
        return HistGradientBoostingRegressor(
            max_iter=self.max_iter, learning_rate=self.learning_rate,
            max_leaf_nodes=self.max_leaf_nodes, min_samples_leaf=self.min_samples_leaf,
            l2_regularization=self.l2_regularization, early_stopping=False,
            random_state=self.random_state)

    def fit(self, X, y):
        X, y = validate_data(self, X, y, ensure_all_finite="allow-nan", y_numeric=True)
        y = np.asarray(y, dtype=float)
        self.model_ = self._model().fit(X, y)
        self.n_iter_ = int(self.model_.n_iter_)
        n_splits = min(int(self.cv), X.shape[0])
        if n_splits >= 2:
            oof = cross_val_predict(self._model(), X, y,
                                    cv=KFold(n_splits, shuffle=True, random_state=0))
        else:
            oof = self.model_.predict(X)
        res = y - oof
        order = np.argsort(oof, kind="stable")
        self.oof_prediction_ = oof[order]
        self.oof_residual_ = res[order]
        self.residual_quantiles_ = np.quantile(res, self.interval_quantiles)
        self.oof_rmse_ = float(np.sqrt(np.mean(res ** 2)))
        return self

    def predict(self, X) -> np.ndarray:
        check_is_fitted(self, "model_")
        X = validate_data(self, X, ensure_all_finite="allow-nan", reset=False)
        return self.model_.predict(X)

    def predict_interval(self, X) -> np.ndarray:
        """Prediction plus the local out-of-fold residual quantiles, shape (n, 2)."""
        p = self.predict(X)
        out = np.empty((p.size, 2))
        for i, pi in enumerate(p):
            out[i] = pi + np.quantile(self._local_residuals(pi), self.interval_quantiles)
        return out

    def _local_residuals(self, p: float) -> np.ndarray:
        n = self.oof_prediction_.size
        k = int(min(max(int(self.n_local), 1), n))
        j = int(np.searchsorted(self.oof_prediction_, p))
        lo = int(np.clip(j - k // 2, 0, n - k))
        return self.oof_residual_[lo:lo + k]

    def predict_bin_proba(self, X, edges) -> np.ndarray:
        """Probability that the truth lies in each interval between ``edges``.

        Parameters
        ----------
        X : array-like, shape (n, n_features)
        edges : sequence of float
            Increasing inner limits (e.g. ``(gap_worn, gap_critical)``); the
            outer intervals are open.

        Returns
        -------
        ndarray, shape (n, len(edges) + 1)
            Rows sum to 1: the share of the local out-of-fold residuals that
            put the truth in each interval, smoothed by a Gaussian kernel
            (Silverman's bandwidth of those residuals).
        """
        from scipy.stats import norm

        edges = np.asarray(edges, dtype=float)
        if edges.ndim != 1 or np.any(np.diff(edges) <= 0):
            raise ValueError("The 'edges' parameter of predict_bin_proba must be increasing. "
                             f"Got {edges.tolist()!r} instead.")
        p = self.predict(X)
        full = np.concatenate([[-np.inf], edges, [np.inf]])
        out = np.empty((p.size, edges.size + 1))
        for i, pi in enumerate(p):
            r = self._local_residuals(pi)
            h = 1.06 * max(float(np.std(r)), 1e-12) * r.size ** (-0.2)
            cdf = norm.cdf((full[None, :] - pi - r[:, None]) / h)
            out[i] = np.diff(cdf, axis=1).mean(axis=0)
        return out / out.sum(axis=1, keepdims=True)


class WearClassifier(ClassifierMixin, BaseEstimator):
    """Wear state from features, with probabilities that know their range.

    Gradient-boosted trees, optionally calibrated by cross-validation
    (``CalibratedClassifierCV``), whose probabilities are shrunk towards
    "don't know" (uniform) as the novelty ratio grows beyond 1, so that a
    recording unlike anything in the library gets a low probability rather
    than a confident wrong answer.

    Parameters
    ----------
    max_iter : int
        Boosting iterations of the gradient-boosted trees.
    learning_rate : float
    max_leaf_nodes : int
    min_samples_leaf : int
    calibration : {"sigmoid", "isotonic", None}
        Probability calibration by cross-validation (``CalibratedClassifierCV``).
    cv : int
        Calibration folds.
    novelty : bool
        Shrink probabilities towards uniform for inputs unlike the training data
        (:class:`NoveltyDetector`, :func:`shrink_to_uniform`).
    novelty_span : float
        Distance ratio beyond 1 at which the probabilities become uniform.
    class_weight : "balanced", dict or None
        Weights of the classes (as sample weights, in the trees and the calibration).
    random_state : int, RandomState or None
    """

    def __init__(self, max_iter: int = 200, learning_rate: float = 0.05,
                 max_leaf_nodes: int = 15, min_samples_leaf: int = 10,
                 calibration: str | None = "sigmoid", cv: int = 3, novelty: bool = True,
                 novelty_span: float = 1.0, class_weight=None, random_state=None):
        self.max_iter = max_iter
        self.learning_rate = learning_rate
        self.max_leaf_nodes = max_leaf_nodes
        self.min_samples_leaf = min_samples_leaf
        self.calibration = calibration
        self.cv = cv
        self.novelty = novelty
        self.novelty_span = novelty_span
        self.class_weight = class_weight
        self.random_state = random_state

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = True
        return tags

    def fit(self, X, y):
        from sklearn.utils.class_weight import compute_sample_weight

        X, y = validate_data(self, X, y, ensure_all_finite="allow-nan")
        check_classification_targets(y)
        if self.calibration not in ("sigmoid", "isotonic", None):
            raise ValueError("The 'calibration' parameter of WearClassifier must be 'sigmoid', "
                             f"'isotonic' or None. Got {self.calibration!r} instead.")
        self.classes_, y_idx = np.unique(y, return_inverse=True)
        cw = self.class_weight
        if isinstance(cw, dict):  # keys are class labels; the trees see indices
            cw = {i: cw.get(c, 1.0) for i, c in enumerate(self.classes_)}
        sw = compute_sample_weight(cw, y_idx) if cw is not None else None
        base = HistGradientBoostingClassifier(
            max_iter=self.max_iter, learning_rate=self.learning_rate,
            max_leaf_nodes=self.max_leaf_nodes, min_samples_leaf=self.min_samples_leaf,
            early_stopping=False, random_state=self.random_state)
        counts = np.bincount(y_idx)
        n_splits = min(int(self.cv), int(counts.min())) if counts.size > 1 else 0
        if counts.size == 1:  # one state only: nothing to learn, certain of it
            from sklearn.dummy import DummyClassifier

            self.estimator_ = DummyClassifier(strategy="prior").fit(X, y_idx)
            self.n_iter_ = 1
        elif self.calibration is not None and n_splits >= 2:
            self.estimator_ = CalibratedClassifierCV(base, method=self.calibration,
                                                     cv=n_splits).fit(X, y_idx, sample_weight=sw)
            self.n_iter_ = int(max(c.estimator.n_iter_
                                   for c in self.estimator_.calibrated_classifiers_))
        else:
            self.estimator_ = clone(base).fit(X, y_idx, sample_weight=sw)
            self.n_iter_ = int(self.estimator_.n_iter_)
        self.novelty_ = NoveltyDetector().fit(X) if self.novelty else None
        return self

    def _raw_proba(self, X: np.ndarray) -> np.ndarray:
        p = np.zeros((X.shape[0], len(self.classes_)))
        p_est = self.estimator_.predict_proba(X)
        p[:, self.estimator_.classes_] = p_est
        return p

    def novelty_ratio(self, X) -> np.ndarray:
        """The novelty detector's distance ratio (1 at the training quantile); zeros without."""
        check_is_fitted(self, "estimator_")
        X = validate_data(self, X, ensure_all_finite="allow-nan", reset=False)
        if self.novelty_ is None:
            return np.zeros(X.shape[0])
        return self.novelty_.distance_ratio(X)

    def predict_proba_in_range(self, X) -> np.ndarray:
        """Class probabilities as if ``X`` were inside the training range (no shrinking)."""
        check_is_fitted(self, "estimator_")
        X = validate_data(self, X, ensure_all_finite="allow-nan", reset=False)
        return self._raw_proba(X)

    def predict_proba(self, X) -> np.ndarray:
        """Class probabilities, shrunk towards uniform outside the training range."""
        check_is_fitted(self, "estimator_")
        X = validate_data(self, X, ensure_all_finite="allow-nan", reset=False)
        p = self._raw_proba(X)
        if self.novelty_ is not None:
            p = shrink_to_uniform(p, self.novelty_.distance_ratio(X), span=self.novelty_span)
        return p

    def predict(self, X) -> np.ndarray:
        check_is_fitted(self, "estimator_")
        return self.classes_[np.argmax(self.predict_proba(X), axis=1)]
