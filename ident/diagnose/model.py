"""The trained diagnosis model: training, the artefact on disk, diagnosing one recording.

A :class:`DiagnosticModel` holds, per element of the mill, a
:class:`~ident.diagnose.estimators.GapRegressor` (gap, rad) and a
:class:`~ident.diagnose.estimators.WearClassifier` (good / worn / critical by
the element's ``gap_worn``/``gap_critical``), and per bearing the same for the
radial clearance (m).  The state is defined by the true gap against fixed
limits, so its probability is mostly (``blend`` = 3/4) that of the gap's
interval under the regressor's local out-of-fold error distribution
(:meth:`~ident.diagnose.estimators.GapRegressor.predict_bin_proba`), the rest
the direct classifier's -- on four pairs of held-out libraries the regressor's
intervals alone were the more accurate for most targets, the 3/4 mix the best
on average (0, 1/2, 3/4 and 1 tried); the classifier's novelty detector says
when a recording lies outside the library, and then both are shrunk towards
"don't know"; both are shrunk towards "don't know" as the recording
leaves the library's range; a recording so far outside that the
probabilities are uniform keeps the state the trees point to (a tie is no
reason to say "good").  The state is the most probable one, except that a
target whose probability of ``good`` falls below its ``alarm`` threshold is
called worn (critical where that is the likelier of the two): the threshold is
calibrated at training on the library's out-of-fold probabilities
(:data:`CALIBRATION_FOLDS` folds) as the highest that keeps the false alarms
among the library's good samples at :data:`FALSE_ALARM_RATE` (:func:`alarm_threshold`),
so a worn element the trees see only dimly is not called good because "good"
is the likeliest of three; where the most probable state alone already raises
more false alarms (hsm-f1's bearings), the threshold is 0 and the most probable
state decides.  Elements learn from the torque features,
bearings from their accelerometers' features (seed section 2.2) plus their
context: the static torque, rise time and idle load, and the numbers of bites
and releases the medians are of (always kept); each target from the
``max_features`` of its features that rank-correlate best with its gap over
the library.  An element without a torque channel on it is diagnosed all the
same but marked ``observable: False``.

The artefact (:func:`save_model`/:func:`load_model`) is a joblib file of the
model with the mill's content hash (:meth:`~ident.description.Mill.content_hash`,
the parsed description's values: a comment or a reformatted file keeps it, any
changed value changes it) and the versions of ident, scikit-learn and numpy it
was trained with, and the training recipe (:data:`TRAINING_RECIPE`); loading
refuses another mill, an older recipe or other versions with
:class:`~ident.errors.ModelArtifactError`, and ``ident diagnose`` and the
campaign then retrain the cached model.  The default cache is
``$IDENT_CACHE/models/<content hash>.joblib`` (or ``~/.cache/ident/models``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import pandas as pd

from ..description import Mill
from ..errors import ModelArtifactError
from ..features.extract import FeatureOptions
from ..io.writers import new_file_mode
from .estimators import GapRegressor, WearClassifier, shrink_to_uniform
from .library import Library, LibraryRanges
from .states import STATES

__all__ = ["DiagnosticModel", "TargetDiagnosis", "Diagnosis", "train_model", "save_model",
           "load_model", "model_cache_path", "library_versions", "diagnose_features",
           "diagnose_recording",
           "element_feature_names", "bearing_feature_names", "bearing_context_names",
           "UNCERTAIN_PROBABILITY", "TRAINING_RECIPE", "FALSE_ALARM_RATE", "CALIBRATION_FOLDS",
           "alarm_threshold", "decide_state"]

#: a decision whose probability is below this is reported ``uncertain``
UNCERTAIN_PROBABILITY = 0.6
ARTEFACT_FORMAT = 2  # 2: keyed by the mill's content hash, not its file's bytes
#: the library and training recipe an artefact was made by; bump it whenever the library's
#: draws, its simulation or the features change, so that cached models of an older recipe
#: are retrained rather than used (2: idle drag in half the samples, spread uniformly over
#: the masses; 2-8 bars; rise times 5-80 ms; the numbers of transients in the bearings'
#: context; 3: each target's alarm threshold calibrated out of fold)
TRAINING_RECIPE = 3
#: false alarms (good samples called worn or critical) an alarm threshold allows on the
#: library's out-of-fold probabilities: the rate the wear diagnosis is asked not to exceed
FALSE_ALARM_RATE = 0.10
#: folds of the out-of-fold probabilities that calibrate the alarm thresholds
CALIBRATION_FOLDS = 3
#: fewest library samples (and good samples of a target) an alarm threshold is calibrated
#: from; a smaller library (tests, demos) decides by the most probable state alone
CALIBRATION_MIN_SAMPLES = 60


def library_versions() -> dict[str, str]:
    """Versions of the libraries a model artefact depends on."""
    import importlib.metadata

    import sklearn

    try:  # the installed distribution's version (ident's top-level package is downstream)
        ident_version = importlib.metadata.version("ident")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - run from a checkout
        ident_version = "unknown"
    return {"ident": ident_version, "scikit-learn": sklearn.__version__,
            "numpy": np.__version__}


def _is_accel(name: str) -> bool:
    parts = name.split(".")
    return len(parts) >= 2 and ":" in parts[1]


#: per-transient context features (static torque, fitted rise time, load between bars)
CONTEXT_FEATURES: tuple[str, ...] = ("static", "rise_ms", "idle_level")
#: recording context of a bearing: how many transients its medians are of
COUNT_FEATURES: tuple[str, ...] = ("n_bites", "n_releases")


def element_feature_names(columns: list[str]) -> list[str]:
    """Torque-derived features (everything but accelerometer features and counts)."""
    return [c for c in columns if not _is_accel(c) and not c.startswith("n_")]


def bearing_context_names(columns: list[str]) -> list[str]:
    """The bearings' context: static torque, rise time, idle load, numbers of transients."""
    ctx = {f"{k}.{c}" for k in ("bite", "release") for c in CONTEXT_FEATURES}
    ctx.update(COUNT_FEATURES)
    return [c for c in columns if c in ctx]


def bearing_feature_names(columns: list[str], bearing_id: str) -> list[str]:
    """A bearing's accelerometer features plus its context (:func:`bearing_context_names`)."""
    return [c for c in columns if _is_accel(c) and c.split(".")[1].startswith(f"{bearing_id}:")] \
        + bearing_context_names(columns)


def decide_state(proba_in_range: np.ndarray, alarm: float = 0.0) -> str:
    """The state of one target from its in-range probabilities (``STATES`` order).

    The most probable state, except that a probability of ``good`` below
    ``alarm`` calls the target worn, or critical where that is the likelier of
    the two.  Every decision that says "not good" by the most probable state
    says so here too, whatever ``alarm``.

    Parameters
    ----------
    proba_in_range : array-like, shape (3,)
    alarm : float
        See :func:`alarm_threshold`.

    Returns
    -------
    str
    """
    p = np.asarray(proba_in_range, dtype=float).ravel()
    k = int(np.argmax(p))
    if k == 0 and p[0] < alarm:
        k = 1 if p[1] >= p[2] else 2
    return STATES[k]


def alarm_threshold(proba: np.ndarray, states: np.ndarray, *,
                    rate: float = FALSE_ALARM_RATE) -> float:
    """The highest probability of ``good`` below which to call a target not good.

    Over labelled samples the false alarms of :func:`decide_state` (good
    samples called worn or critical) grow with the threshold; this returns the
    highest threshold at which they stay at or below ``rate``.  It is 0 where
    the most probable state alone already exceeds ``rate``, or where no sample
    is good.

    Parameters
    ----------
    proba : ndarray, shape (n, 3)
        Out-of-fold probabilities (``STATES`` order).
    states : ndarray of str, shape (n,)
        The samples' true states.
    rate : float
        Allowed share of good samples called worn or critical.

    Returns
    -------
    float
    """
    proba = np.asarray(proba, dtype=float)
    good = np.asarray(states) == STATES[0]
    if not good.any():
        return 0.0
    pg = proba[good]
    by_max = np.argmax(pg, axis=1) > 0
    budget = int(np.floor(rate * good.sum() + 1e-9)) - int(by_max.sum())
    if budget < 0:
        return 0.0
    # each good sample still called good raises an alarm once the threshold passes its p(good)
    cand = np.sort(pg[~by_max, 0])
    if budget >= cand.size:
        return 1.0
    return float(cand[budget])


@dataclass(frozen=True)
class TargetModel:
    """Regressor and classifier of one element or bearing.

    Attributes
    ----------
    kind : str
        ``"element"`` or ``"bearing"``.
    features : tuple of str
        The columns both estimators read, in order.
    classifier : WearClassifier
    regressor : GapRegressor
    limits : (float, float)
        Worn and critical limits of the gap (rad) or clearance (m).
    importances : tuple of (str, float)
        Permutation importance of the regressor over the library, largest first.
    class_medians : dict
        Per state, each feature's median over the library's samples of that state.
    observable : bool
        A torque channel sees the element (always True for bearings).
    blend : float
        Weight of the regressor's interval probabilities (the classifier's: ``1 - blend``).
    alarm : float
        Probability of ``good`` below which the target is called worn or critical
        (:func:`alarm_threshold`); 0 decides by the most probable state alone.
    """

    kind: str  # "element" | "bearing"
    features: tuple[str, ...]
    classifier: WearClassifier
    regressor: GapRegressor
    limits: tuple[float, float]
    importances: tuple[tuple[str, float], ...]
    class_medians: dict[str, dict[str, float]]
    observable: bool = True
    blend: float = 0.75
    alarm: float = 0.0

    def decide(self, proba_in_range: np.ndarray) -> str:
        """The state of one row of :meth:`state_proba_in_range` (see :func:`decide_state`)."""
        return decide_state(proba_in_range, self.alarm)

    def state_proba_in_range(self, X: np.ndarray) -> np.ndarray:
        """Probabilities of :data:`~ident.diagnose.states.STATES` as if ``X`` were in range.

        The regressor's interval probabilities blended with the classifier's,
        not shrunk by the novelty; shape (n, 3).
        """
        X = np.asarray(X, dtype=float)
        p_clf = np.zeros((X.shape[0], len(STATES)))
        raw = self.classifier.predict_proba_in_range(X)
        for j, c in enumerate(self.classifier.classes_):
            p_clf[:, STATES.index(str(c))] = raw[:, j]
        return self.blend * self.regressor.predict_bin_proba(X, self.limits) + \
            (1.0 - self.blend) * p_clf

    def state_proba(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Probabilities of :data:`~ident.diagnose.states.STATES` (in that order) and novelty.

        Returns
        -------
        proba : ndarray, shape (n, 3)
            :meth:`state_proba_in_range` shrunk towards uniform as the novelty grows.
        novelty : ndarray, shape (n,)
            The distance ratio to the library (> 1: unusual).
        """
        X = np.asarray(X, dtype=float)
        nov = self.classifier.novelty_ratio(X)
        p = self.state_proba_in_range(X)
        return shrink_to_uniform(p, nov, span=self.classifier.novelty_span), nov


@dataclass(frozen=True)
class DiagnosticModel:
    """Everything ``ident diagnose`` needs for one mill file.

    Attributes
    ----------
    mill_name, mill_hash : str
        The mill's name and :meth:`~ident.description.Mill.content_hash`.
    versions : dict
        ``ident``, ``scikit-learn``, ``numpy`` versions at training.
    feature_names : tuple of str
        Columns of the library's features, in order.
    targets : dict
        Element and bearing id to its :class:`TargetModel`.
    n_samples : int
        Library size.
    ranges : LibraryRanges
    options : FeatureOptions
    random_state : int or None
    """

    mill_name: str
    mill_hash: str
    versions: dict[str, str]
    feature_names: tuple[str, ...]
    targets: dict[str, TargetModel]
    n_samples: int
    ranges: LibraryRanges = field(default_factory=LibraryRanges)
    options: FeatureOptions = field(default_factory=FeatureOptions)
    random_state: int | None = None

    @property
    def element_ids(self) -> tuple[str, ...]:
        return tuple(k for k, t in self.targets.items() if t.kind == "element")

    @property
    def bearing_ids(self) -> tuple[str, ...]:
        return tuple(k for k, t in self.targets.items() if t.kind == "bearing")


def _rank_columns(X: np.ndarray) -> np.ndarray:
    """Column ranks (average ties) with NaN at the column's median rank."""
    import scipy.stats as st

    R = np.empty_like(X, dtype=float)
    for j in range(X.shape[1]):
        x = X[:, j]
        ok = np.isfinite(x)
        r = np.full(x.size, np.nan)
        r[ok] = st.rankdata(x[ok])
        r[~ok] = np.nanmedian(r) if ok.any() else 0.0
        R[:, j] = r
    return R


def select_features(X: np.ndarray, y: np.ndarray, names: list[str], k: int) -> list[str]:
    """The ``k`` columns whose ranks correlate best (absolute Spearman) with ``y``.

    Columns with no spread, or with finite values in no more than a third of the rows
    (at least two), are never chosen: the regressor's 3-fold out-of-fold predictions
    could then train on a fold where the column has none, which the trees' binning
    cannot take (a 10-sample library of 2-8 bars did that).
    """
    X = np.asarray(X, dtype=float)
    finite = np.isfinite(X)
    lo = np.where(finite, X, np.inf).min(axis=0)
    hi = np.where(finite, X, -np.inf).max(axis=0)
    need = max(2, -(-X.shape[0] // 3) + 1)
    usable = (finite.sum(axis=0) >= need) & (hi > lo)
    idx = np.flatnonzero(usable)
    if idx.size <= k:
        return [names[i] for i in idx]
    R = _rank_columns(X[:, idx])
    ry = _rank_columns(np.asarray(y, dtype=float)[:, None])[:, 0]
    Rc = R - R.mean(axis=0)
    yc = ry - ry.mean()
    den = np.sqrt((Rc ** 2).sum(axis=0) * (yc ** 2).sum())
    rho = np.abs(Rc.T @ yc) / np.where(den > 0, den, np.inf)
    best = idx[np.argsort(-rho, kind="stable")[:k]]
    return [names[i] for i in sorted(best)]


def _importances(reg: GapRegressor, X: np.ndarray, y: np.ndarray, names: list[str], *,
                 top: int = 20, candidates: int = 40,
                 random_state: int | None = 0) -> tuple[tuple[str, float], ...]:
    """Permutation importance of the regressor on a subsample, for its top-correlated columns.

    The drop of R^2 when one column is shuffled (one repeat, at most 200
    rows), tried for the ``candidates`` columns that rank-correlate best with
    the target; the ``top`` largest positive ones.
    """
    rng = np.random.default_rng(random_state)
    n = min(X.shape[0], 200)
    idx = rng.choice(X.shape[0], n, replace=False)
    Xs, ys = X[idx], y[idx]
    cand = select_features(Xs, ys, list(range(X.shape[1])), candidates)  # type: ignore[arg-type]
    base = reg.score(Xs, ys)
    imp = []
    for j in cand:
        Xp = Xs.copy()
        Xp[:, j] = Xp[rng.permutation(n), j]
        imp.append((names[j], float(base - reg.score(Xp, ys))))
    imp.sort(key=lambda t: -t[1])
    return tuple((k, v) for k, v in imp[:top] if v > 0)


def _fit_estimators(X: np.ndarray, y: np.ndarray, yr: np.ndarray, *, max_iter: int, leaf: int,
                    random_state: int | None) -> tuple[GapRegressor, WearClassifier]:
    """The regressor (of ``yr``) and classifier (of ``y``) of one target."""
    reg = GapRegressor(max_iter=max_iter, min_samples_leaf=leaf,
                       random_state=random_state).fit(X, yr)
    clf = WearClassifier(max_iter=max(max_iter // 2, 1), min_samples_leaf=leaf,
                         calibration=None, random_state=random_state).fit(X, y)
    return reg, clf


def _calibrated_alarm(X: np.ndarray, y: np.ndarray, yr: np.ndarray, limits: tuple[float, float],
                      *, blend: float, max_iter: int, leaf: int,
                      random_state: int | None) -> float:
    """:func:`alarm_threshold` of a target's out-of-fold state probabilities.

    The estimators are refitted on :data:`CALIBRATION_FOLDS` - 1 folds and
    predict the held-out one, with the features chosen on the whole library
    (a small optimism the threshold tolerates).  0 for a library smaller than
    :data:`CALIBRATION_MIN_SAMPLES` or with fewer good samples than that.
    """
    from sklearn.model_selection import KFold, StratifiedKFold

    good = int(np.sum(y == STATES[0]))
    if X.shape[0] < CALIBRATION_MIN_SAMPLES or good < CALIBRATION_MIN_SAMPLES // 2:
        return 0.0
    oof = np.zeros((X.shape[0], len(STATES)))
    _, counts = np.unique(y, return_counts=True)
    split = StratifiedKFold if counts.min() >= CALIBRATION_FOLDS else KFold
    folds = split(CALIBRATION_FOLDS, shuffle=True, random_state=0)
    for tr, te in folds.split(X, y):
        reg, clf = _fit_estimators(X[tr], y[tr], yr[tr], max_iter=max_iter, leaf=leaf,
                                   random_state=random_state)
        oof[te] = TargetModel(kind="", features=(), classifier=clf, regressor=reg,
                              limits=limits, importances=(), class_medians={},
                              blend=blend).state_proba_in_range(X[te])
    return alarm_threshold(oof, y)


def train_model(library: Library, mill: Mill, *, random_state: int | None = 0,
                max_iter: int = 200, max_features: int = 200, blend: float = 0.75,
                progress: Callable[[str], None] | None = None) -> DiagnosticModel:
    """Train the regressors and classifiers of every element and bearing.

    Parameters
    ----------
    library : Library
        Simulated from ``mill`` (:func:`ident.diagnose.simulate_library`).
    mill : Mill
    random_state : int or None
    max_iter : int
        Boosting iterations of each regressor (the classifiers take half).
    max_features : int
        Features per target (those whose ranks correlate best with its gap).
    blend : float
        Weight of the regressor's interval probabilities in the state's (the
        classifier's is ``1 - blend``).
    progress : callable, optional
        Called with each target's id as its training starts.

    Returns
    -------
    DiagnosticModel

    Raises
    ------
    ModelArtifactError
        When the library was simulated from another mill file.
    """
    from threadpoolctl import threadpool_limits

    if library.mill_hash != mill.content_hash():
        raise ModelArtifactError(
            f"the library was simulated from another mill description (content hash "
            f"{library.mill_hash[:16]}), not from {mill.source or mill.name} "
            f"({mill.content_hash()[:16]})")
    X_all = library.features
    cols = list(X_all.columns)
    seen = {c.element for c in mill.torque_channels()}
    targets: dict[str, TargetModel] = {}
    jobs: list[tuple[str, str, list[str], str, str, tuple[float, float]]] = []
    for e in mill.elements:
        jobs.append((e.id, "element", element_feature_names(cols), f"{e.id}.state",
                     f"{e.id}.gap", (e.gap_worn, e.gap_critical)))
    if library.bearings:
        for b in mill.bearings:
            names = bearing_feature_names(cols, b.id)
            if len(names) > len(bearing_context_names(cols)):
                jobs.append((b.id, "bearing", names, f"{b.id}.state", f"{b.id}.clearance",
                             (b.clearance_worn, b.clearance_critical)))
    with threadpool_limits(1):
        for tid, kind, names, ycol, rcol, limits in jobs:
            if progress is not None:
                progress(tid)
            yr = library.truth[rcol].to_numpy(dtype=float)
            # a bearing's context does not correlate with its clearance, it tells the trees
            # how to read the accelerometers: kept, not ranked
            keep = bearing_context_names(cols) if kind == "bearing" else []
            ranked = [c for c in names if c not in keep]
            names = select_features(X_all[ranked].to_numpy(dtype=float), yr, ranked,
                                    max_features - len(keep)) + keep
            X = X_all[names].to_numpy(dtype=float)
            y = library.truth[ycol].to_numpy()
            # leaves of at least 10 samples, fewer for a small library (tests, demos)
            leaf = int(np.clip(X.shape[0] // 20, 2, 10))
            reg, clf = _fit_estimators(X, y, yr, max_iter=max_iter, leaf=leaf,
                                       random_state=random_state)
            med = {}
            for st_ in STATES:
                sel = y == st_
                sub = X[sel]
                with np.errstate(all="ignore"):
                    med[st_] = {n: (float(np.nanmedian(sub[:, j]))
                                    if sel.any() and np.isfinite(sub[:, j]).any() else np.nan)
                                for j, n in enumerate(names)}
            targets[tid] = TargetModel(
                kind=kind, features=tuple(names), classifier=clf, regressor=reg,
                limits=(float(limits[0]), float(limits[1])),
                importances=_importances(reg, X, yr, names, random_state=random_state),
                class_medians=med, observable=(tid in seen) if kind == "element" else True,
                blend=float(blend),
                alarm=_calibrated_alarm(X, y, yr, limits, blend=float(blend), max_iter=max_iter,
                                        leaf=leaf, random_state=random_state))
    return DiagnosticModel(mill_name=mill.name, mill_hash=mill.content_hash(),
                           versions=library_versions(), feature_names=tuple(X_all.columns),
                           targets=targets, n_samples=len(library), ranges=library.ranges,
                           options=library.options, random_state=random_state)


# ---- artefact ------------------------------------------------------------------------------

def model_cache_path(mill: Mill) -> Path:
    """Default artefact path of a mill: ``$IDENT_CACHE/models/<content hash>.joblib``.

    Keyed by :meth:`~ident.description.Mill.content_hash`: editing a comment or the
    file's layout finds the same model; changing any value trains a new one.
    """
    base = os.environ.get("IDENT_CACHE") or os.path.join(os.path.expanduser("~"), ".cache",
                                                         "ident")
    return Path(base) / "models" / f"{mill.content_hash()}.joblib"


def save_model(model: DiagnosticModel, path: str | Path) -> Path:
    """Write the artefact atomically (joblib, compressed), with the umask's permissions.

    Returns
    -------
    Path
    """
    import tempfile

    import joblib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, new_file_mode())  # as a plain open() would (mkstemp gives 0600)
    finally:
        os.close(fd)
    try:
        joblib.dump({"format": ARTEFACT_FORMAT, "recipe": TRAINING_RECIPE,
                     "mill_hash": model.mill_hash,
                     "versions": dict(model.versions), "model": model}, tmp, compress=3)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_model(path: str | Path, mill: Mill) -> DiagnosticModel:
    """Load an artefact and check it belongs to ``mill`` and to these library versions.

    Raises
    ------
    ModelArtifactError
        Unreadable file, another mill (content hash), an older training recipe
        (:data:`TRAINING_RECIPE`) or other library versions.
    """
    import joblib

    path = Path(path)
    try:
        data = joblib.load(path)
    except FileNotFoundError:
        raise ModelArtifactError(f"model artefact {path} does not exist") from None
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad artefact
        raise ModelArtifactError(f"model artefact {path} cannot be read: "
                                 f"{type(exc).__name__}: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != ARTEFACT_FORMAT or \
            not isinstance(data.get("model"), DiagnosticModel):
        raise ModelArtifactError(f"{path} is not an ident diagnosis model (format "
                                 f"{ARTEFACT_FORMAT})")
    if data.get("recipe", 1) != TRAINING_RECIPE:
        raise ModelArtifactError(
            f"model artefact {path} was trained by an older library recipe "
            f"({data.get('recipe', 1)}, now {TRAINING_RECIPE}); retrain with 'ident train "
            f"--mill {mill.source or 'MILL'} --out {path}'")
    found, want = data["mill_hash"], mill.content_hash()
    if found != want:
        raise ModelArtifactError(
            f"model artefact {path} was trained for another mill description (content "
            f"hash {found}), but {mill.source or mill.name} has {want}; retrain with "
            f"'ident train --mill {mill.source or 'MILL'} --out {path}'")
    now = library_versions()
    diff = {k: (v, now.get(k)) for k, v in data["versions"].items() if now.get(k) != v}
    if diff:
        txt = ", ".join(f"{k} {v[0]} (now {v[1]})" for k, v in diff.items())
        raise ModelArtifactError(f"model artefact {path} was trained with {txt}; retrain with "
                                 f"'ident train' under the installed versions")
    return data["model"]


# ---- diagnosis ------------------------------------------------------------------------------

@dataclass(frozen=True)
class TargetDiagnosis:
    """Diagnosis of one element or bearing.

    Attributes
    ----------
    state : str
        ``good``, ``worn`` or ``critical``.
    probability : float
        Probability of ``state`` (calibrated, shrunk towards 1/3 out of range).
    probabilities : dict
        Every state's probability.
    size : float
        Regressed gap (rad) or clearance (m).
    interval : (float, float)
        Approximate 95 % interval of ``size`` (out-of-fold residuals).
    observable : bool
        A torque channel sees the element (always True for bearings).
    uncertain : bool
        ``probability`` below :data:`UNCERTAIN_PROBABILITY` or the recording
        out of the library's range.
    novelty : float
        Distance to the library over its 99 % quantile (> 1: unusual).
    explanation : tuple of dict
        Features that drove the decision (:mod:`ident.diagnose.explain`).
    """

    state: str
    probability: float
    probabilities: dict[str, float]
    size: float
    interval: tuple[float, float]
    observable: bool
    uncertain: bool
    novelty: float
    explanation: tuple[dict[str, Any], ...] = ()


@dataclass(frozen=True)
class Diagnosis:
    """Wear states of one recording."""

    elements: dict[str, TargetDiagnosis]
    bearings: dict[str, TargetDiagnosis]
    warnings: tuple[str, ...] = ()

    def gap_start(self) -> dict[str, float]:
        """The regressed gap of every element a torque channel sees, rad: a start for the
        fit (``fit_gaps(data_starts=[...])``) where the mill file's gaps lead astray."""
        return {eid: float(d.size) for eid, d in self.elements.items() if d.observable}


def diagnose_features(model: DiagnosticModel, features: pd.Series | Mapping[str, float], *,
                      explain: bool = True, n_explain: int = 3) -> Diagnosis:
    """Diagnose one recording from its feature vector.

    Parameters
    ----------
    model : DiagnosticModel
    features : Series or mapping
        :func:`ident.features.recording_features` of the recording.
    explain : bool
        Attach the features that drove each decision.
    n_explain : int
        Features per decision.

    Returns
    -------
    Diagnosis
    """
    from threadpoolctl import threadpool_limits

    from .explain import explain_decision

    f = pd.Series(features, dtype=float).reindex(list(model.feature_names))
    warnings: list[str] = []
    elements, bearings = {}, {}
    with threadpool_limits(1):
        for tid, tm in model.targets.items():
            x = f.reindex(list(tm.features)).to_numpy(dtype=float)[None, :]
            if not np.isfinite(x).any():
                warnings.append(f"{tid}: none of its features could be computed from the "
                                f"recording")
            elif np.isnan(x).mean() > 0.5:
                warnings.append(f"{tid}: {int(np.isnan(x).sum())} of {x.size} features missing")
            proba, nov_ = tm.state_proba(x)
            probs = {s_: float(proba[0, i]) for i, s_ in enumerate(STATES)}
            # the state is the in-range decision (shrinking towards uniform keeps its order);
            # fully shrunk, the probabilities tie, and "don't know" must not read as "good"
            state = tm.decide(tm.state_proba_in_range(x)[0])
            nov = float(nov_[0])
            size = float(tm.regressor.predict(x)[0])
            lo, hi = tm.regressor.predict_interval(x)[0]
            expl: tuple = ()
            if explain:
                expl = explain_decision(tm, x[0], state, n=n_explain)
            d = TargetDiagnosis(state=state, probability=probs[state], probabilities=probs,
                                size=max(size, 0.0), interval=(max(float(lo), 0.0), float(hi)),
                                observable=tm.observable,
                                uncertain=bool(probs[state] < UNCERTAIN_PROBABILITY or nov > 1.0),
                                novelty=nov, explanation=expl)
            (elements if tm.kind == "element" else bearings)[tid] = d
    return Diagnosis(elements=elements, bearings=bearings, warnings=tuple(warnings))


def diagnose_recording(model: DiagnosticModel, rec: Any, mill: Mill, segments: Any, *,
                       explain: bool = True) -> tuple[Diagnosis, Any]:
    """Diagnose one recording around its load-step transients.

    Parameters
    ----------
    model : DiagnosticModel
    rec : Recording
    mill : Mill
    segments : sequence of Segment
        Its transients (:func:`ident.segment.segment_transients`).
    explain : bool
        Attach the features that drove each decision.

    Returns
    -------
    diagnosis : Diagnosis
    features : TransientFeatures
        :func:`ident.features.transient_features` of the recording.

    Raises
    ------
    IdentError
        No transient far enough from the others and from the recording's ends.
    """
    from ..errors import IdentError
    from ..features import recording_features, transient_features

    tf = transient_features(rec, mill, [s.t_step for s in segments], options=model.options)
    if len(tf.table) == 0:
        raise IdentError(f"{getattr(rec, 'path', None) or 'the recording'}: the load steps "
                         f"found are too close together or too close to the recording's "
                         f"ends to analyse")
    return diagnose_features(model, recording_features(tf), explain=explain), tf
