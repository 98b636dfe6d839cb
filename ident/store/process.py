"""Process one recording through every stage into a :class:`RecordingOutcome`.

``read -> segment -> taf -> fit -> diagnose``, each stage through its package's
public API (imported inside :func:`process_recording`, so this module imports
before those stages are installed).  Whatever goes wrong in a stage ends the
recording as ``failed`` with a one-line reason naming the stage; warnings the
stages raise become data-quality findings.  Nothing here writes anywhere: the
campaign's parent process stores the outcome.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import sys
import time
import traceback
import warnings
from dataclasses import asdict, dataclass
from importlib import metadata as _md
from pathlib import Path
from typing import Any, Callable, Mapping

from ..description import Mill
from ..errors import DataQualityWarning, IdentError
from .outcome import RecordingOutcome, jsonable

__all__ = ["Settings", "process_recording", "settings_hash", "library_versions", "ProcessFn",
           "available_stages", "model_path", "ensure_model", "DEFAULT_LIBRARY_SAMPLES"]

#: Library size of a wear model trained on first use (as ``ident train`` and ``ident diagnose``).
DEFAULT_LIBRARY_SAMPLES = 300

#: The signature of a per-recording processing function (the campaign's unit of work).
ProcessFn = Callable[[Path, Mill, "Settings"], RecordingOutcome]

_VERSIONED = ("ident", "numpy", "scipy", "pandas", "casadi", "scikit-learn", "mcap", "sqlalchemy")


#: Default CPU budget of one recording's fit in a campaign, s (:class:`Settings`).
FIT_BUDGET_S = 600.0


@dataclass(frozen=True)
class Settings:
    """How each recording of a campaign is processed (part of the idempotency key).

    Attributes
    ----------
    family : str or None
        Stiffness-law family for the fit (``g1`` ... ``g4``); None = the fit's default.
    fit : bool
        Identify gaps (CasADi collocation).  Without it only segments, TAF and the
        diagnosis are stored.
    per_transient : bool
        Also fit every transient on its own (gap trend within a recording; costly).
    max_transients : int or None
        Fit at most this many transients per recording (the first ones), to bound
        the cost of long recordings; None = all.
    diagnose : bool
        Run the wear diagnosis (the trained model).  Without it, or without a model,
        the elements whose gap the fit identified still get their verdict from that
        gap (:func:`ident.diagnose.diagnosis_json` of the fit alone).
    model : str or None
        Trained wear model for the diagnosis; None = the mill's cached model
        (``ident.diagnose.model_cache_path``); without one the diagnosis is skipped
        with a ``no_model`` finding.
    taf_window_s : float
        Window after each bite searched for the peak torque, s.
    starts : tuple of (str, float)
        Start the fit at these gaps (rad, ``(element, gap)`` pairs; the others at the
        mill file's): the campaign's refit from a neighbouring recording
        (:func:`ident.store.campaign.neighbour_starts`); empty = the mill file's gaps.
    nuisance : bool
        Fit the plant nuisances with the gaps (``fit_gaps(nuisance=...)``: channel
        offsets, drag, the ramps' shape).  Off in campaigns for now, unlike ``ident
        fit``: on the project's own recordings they cost 2-4 times the solve (the
        demo's day-14 recording: 67 s against 19 s, the same gaps), and a campaign
        study on plant recordings that would justify them has not run yet.
    fit_budget_s : float
        CPU seconds after which a recording's fit begins no further start or path
        and a restart under way stops unfinished (``fit_gaps(time_budget_s=...)``;
        only the first start runs to its end, each IPOPT call bounded itself), so that one recording whose fit keeps restarting
        cannot hold a worker without end: it is stored with what the fit reached and
        the fit's warning.  The default, 600 s, is 10-20 times a fit that passes
        first time on the project's recordings.
    """

    family: str | None = None
    fit: bool = True
    per_transient: bool = False
    max_transients: int | None = None
    diagnose: bool = True
    model: str | None = None
    taf_window_s: float = 1.0
    starts: tuple[tuple[str, float], ...] = ()
    nuisance: bool = False
    fit_budget_s: float = FIT_BUDGET_S

    def __post_init__(self) -> None:
        if not self.fit_budget_s > 0:
            raise IdentError(f"fit_budget_s (ident campaign --fit-budget) must be positive. "
                             f"Got {self.fit_budget_s} s.")

    def to_dict(self) -> dict[str, Any]:
        """The settings as JSON-able values; ``starts`` only when given, ``nuisance``
        only when on and ``fit_budget_s`` only when not the default, so that the hash of
        every setting that existed before them is what it was."""
        d = asdict(self)
        if not d["nuisance"]:
            del d["nuisance"]
        if d["fit_budget_s"] == FIT_BUDGET_S:
            del d["fit_budget_s"]
        if not d["starts"]:
            del d["starts"]
        else:
            d["starts"] = [list(x) for x in d["starts"]]
        return d


def settings_hash(settings: Settings, mill: Mill, *, extra: Mapping[str, Any] | None = None) -> str:
    """SHA-256 of the settings and the mill description (its values, not its formatting).

    ``extra`` adds further inputs of the result, e.g. the hash of a model file.
    """
    blob = json.dumps({"settings": settings.to_dict(), "mill": mill.content_hash(),
                       "extra": dict(extra or {})}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def library_versions() -> dict[str, str]:
    """Versions of ident, Python and the libraries that shape the results."""
    out = {"python": sys.version.split()[0]}
    for name in _VERSIONED:
        try:
            out[name] = _md.version(name)
        except _md.PackageNotFoundError:
            pass
    return out


#: Stages that need a package of their own, and the names it must export.
_OPTIONAL_STAGES = {"fit": ("ident.fit", ("fit_gaps", "windows_from_recording")),
                    "diagnose": ("ident.diagnose", ("diagnose_features", "load_model",
                                                    "model_cache_path")),
                    "features": ("ident.features", ("transient_features",
                                                    "recording_features", "feature_summary"))}


def available_stages() -> tuple[str, ...]:
    """The optional stages (``fit``, ``diagnose``) this installation provides.

    They are part of the idempotency key (see :func:`ident.store.run_campaign`): a
    recording stored before a stage was available is processed again once it is.
    """
    import importlib

    out = []
    for stage, (module, names) in _OPTIONAL_STAGES.items():
        try:
            mod = importlib.import_module(module)
        except ImportError:
            continue
        if all(hasattr(mod, n) for n in names):
            out.append(stage)
    if "features" in out:  # the diagnosis needs both
        out.remove("features")
    elif "diagnose" in out:
        out.remove("diagnose")
    return tuple(out)


def model_path(mill: Mill, settings: Settings) -> Path | None:
    """The wear model a campaign diagnoses with: ``settings.model`` or the mill's cached one."""
    if settings.model:
        return Path(settings.model)
    if "diagnose" not in available_stages():
        return None
    from ..diagnose import model_cache_path

    p = Path(model_cache_path(mill))
    return p if p.is_file() else None


def ensure_model(mill: Mill, *, samples: int = DEFAULT_LIBRARY_SAMPLES, jobs: int = 2,
                 seed: int = 0, progress: bool = True) -> Path:
    """The mill's cached wear model, trained first when there is none (or it is unusable).

    The model is trained as ``ident diagnose`` trains it on first use (a simulated
    library of ``samples`` recordings, bearings included) and cached at
    :func:`ident.diagnose.model_cache_path`.

    Parameters
    ----------
    mill : Mill
    samples : int
        Simulated recordings in the library.
    jobs : int
        Worker processes of the simulation.
    seed : int
        Random seed of the library and the trees.
    progress : bool
        Say what happens on stderr (a progress bar while simulating).

    Returns
    -------
    Path
        The artefact.
    """
    from ..diagnose import (load_model, model_cache_path, save_model, simulate_library,
                            train_model)
    from ..errors import ModelArtifactError

    path = Path(model_cache_path(mill))
    if path.is_file():
        try:
            load_model(path, mill)
            return path
        except ModelArtifactError as exc:
            if progress:
                print(f"ident campaign: cached wear model unusable ({exc}); retraining",
                      file=sys.stderr)
    if progress:
        print(f"ident campaign: no wear model for mill '{mill.name}' yet; training one on "
              f"{samples} simulated recordings (once; cached in {path})", file=sys.stderr)
    t0 = time.perf_counter()
    lib = simulate_library(mill, n=samples, random_state=seed, n_jobs=jobs, progress=progress,
                           bearings=True)

    def say(tid: str) -> None:
        if progress:
            print(f"ident campaign: training the wear model of {tid}", file=sys.stderr)

    save_model(train_model(lib, mill, random_state=seed, progress=say), path)
    if progress:
        print(f"ident campaign: wear model trained in {time.perf_counter() - t0:.0f} s",
              file=sys.stderr)
    return path


def _model_diagnosis(rec: Any, mill: Mill, segs: tuple, model_file: Path) -> tuple[Any, Any]:
    """The trained model's diagnosis of one recording and its transient features."""
    from ..diagnose import diagnose_recording, load_model

    return diagnose_recording(load_model(model_file, mill), rec, mill, segs, explain=False)


def _diagnose(rec: Any, mill: Mill, segs: tuple, model_file: Path,
              fit: Mapping[str, Any] | None, pre: tuple[Any, Any] | None = None
              ) -> dict[str, Any]:
    """cli.md ``diagnose`` JSON of one recording: the verdicts of its fit and the model
    (``pre``: :func:`_model_diagnosis` already computed)."""
    from ..diagnose import diagnosis_json
    from ..features import feature_summary

    diag, tf = pre if pre is not None else _model_diagnosis(rec, mill, segs, model_file)
    return diagnosis_json(mill, diag, fit=fit, features=feature_summary(tf, mill=mill))


def _finding(stage: str, kind: str, message: str) -> dict[str, Any]:
    """A data-quality finding of a stage (the ``quality`` entries of an outcome)."""
    return {"stage": stage, "kind": kind, "message": message, "channel": None,
            "t_start": None, "t_end": None, "fatal": False}


class _Failed(Exception):
    """Internal: a stage failed; carries the outcome fields."""

    def __init__(self, stage: str, exc: BaseException) -> None:
        self.stage = stage
        self.exc = exc


def describe_error(stage: str, exc: BaseException) -> str:
    """One line saying where and why a recording failed."""
    if isinstance(exc, IdentError):
        return f"{stage}: {exc}"
    if isinstance(exc, MemoryError):
        return f"{stage}: out of memory (MemoryError {exc})".rstrip()
    tb = traceback.extract_tb(exc.__traceback__)
    where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
    return f"{stage}: internal error {type(exc).__name__}: {exc}{where}"


def process_recording(path: str | os.PathLike, mill: Mill, settings: Settings) -> RecordingOutcome:
    """Read, segment, measure TAF, fit and diagnose one recording.

    Parameters
    ----------
    path : path
        The recording (``.mcap``, or the ``.csv`` key file of a CSV recording).
    mill : Mill
    settings : Settings

    Returns
    -------
    RecordingOutcome
        ``done`` with every stage's dicts, or ``failed`` with the stage, the error
        and whatever the earlier stages produced.  It never raises for a bad
        recording (or a bug in a stage); only ``KeyboardInterrupt``/``SystemExit``
        pass through.
    """
    started = time.time()
    t_start = time.perf_counter()
    path = Path(path)
    parts: dict[str, Any] = {"recording": {}, "segments": (), "taf": (), "fit": None,
                             "transient_fits": (), "diagnosis": None}
    quality: list[dict[str, Any]] = []

    def stage(name: str, fn: Callable[[], Any]) -> Any:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                value = fn()
            except (KeyboardInterrupt, SystemExit):
                raise
            except BaseException as exc:  # noqa: BLE001 - every failure is recorded
                raise _Failed(name, exc) from exc
            finally:
                for w in caught:
                    if name == "read" and issubclass(w.category, DataQualityWarning):
                        continue  # the reader lists every finding in Recording.issues too
                    quality.append(_finding(name, f"warning:{w.category.__name__}",
                                            str(w.message)))
        return value

    status, error, kind, failed_stage = "done", None, None, None
    try:
        from ..io.readers import read_recording

        rec = stage("read", lambda: read_recording(path, mill))
        quality[:0] = [dict(q.to_dict(), stage="read") for q in rec.issues]
        t0_ns = int(rec.t0_ns)
        if t0_ns == 0:  # e.g. a CSV with times in seconds from its start
            t0_ns = path.stat().st_mtime_ns
            quality.append(_finding("read", "no_absolute_time",
                                    "the recording holds no absolute time; its start is "
                                    "taken from the file's modification time"))
        parts["recording"] = {"recording_id": rec.metadata.get("recording_id"),
                              "metadata": dict(rec.metadata), "t0_ns": t0_ns,
                              "duration_s": float(rec.duration)}

        from ..segment import segment_transients

        segs = stage("segment", lambda: tuple(segment_transients(rec, mill)))
        parts["segments"] = tuple(jsonable(s.to_dict()) for s in segs)
        if not segs:
            raise _Failed("segment", IdentError(
                f"{path}: no load-step transients found; nothing to fit"))

        from .taf import measured_taf

        parts["taf"] = tuple(stage("taf", lambda: measured_taf(
            rec, mill, parts["segments"], window_s=settings.taf_window_s)))

        stages = available_stages()
        for name, wanted in (("fit", settings.fit), ("diagnose", settings.diagnose)):
            if wanted and name not in stages:
                quality.append(_finding(name, "stage_unavailable",
                                        f"the {name} stage is not installed in this ident; "
                                        f"skipped"))
        model_file = model_path(mill, settings) if settings.diagnose else None
        if settings.diagnose and "diagnose" in stages and model_file is None:
            quality.append(_finding("diagnose", "no_model",
                                    f"no trained wear model for mill '{mill.name}': run "
                                    f"'ident train' (or 'ident diagnose' once) and rerun; "
                                    f"diagnosis skipped"))

        pre = None  # the model's diagnosis first: its gaps are the fit's data start
        if settings.diagnose and "diagnose" in stages and model_file is not None:
            try:
                pre = _model_diagnosis(rec, mill, segs, model_file)
            except Exception:  # noqa: BLE001 -- the diagnose stage below says why
                pre = None
        if settings.fit and "fit" in stages:
            from ..fit import fit_recording

            use = segs if settings.max_transients is None else segs[:settings.max_transients]
            kw: dict[str, Any] = {"nuisance": settings.nuisance,
                                  "time_budget_s": settings.fit_budget_s}
            if settings.family is not None:
                kw["family"] = settings.family
            if settings.starts:
                kw["starts"] = [dict(settings.starts)]
            if pre is not None:
                kw["data_starts"] = (pre[0].gap_start(),)
            fitted = stage("fit", lambda: fit_recording(rec, mill, use, **kw))[0]
            parts["fit"] = jsonable(fitted.to_dict())
            if settings.per_transient:
                per = []
                for i, seg in enumerate(use):
                    one = stage("fit", lambda seg=seg: fit_recording(rec, mill, (seg,), **kw))[0]
                    per.append(dict(jsonable(one.to_dict()), transient_idx=i))
                parts["transient_fits"] = tuple(per)

        if settings.diagnose and "diagnose" in stages and model_file is not None:
            parts["diagnosis"] = jsonable(stage("diagnose", lambda: _diagnose(
                rec, mill, segs, model_file, parts["fit"], pre)))
        elif parts["fit"] is not None and "diagnose" in stages:
            from ..diagnose import diagnosis_json  # the verdicts of the fit alone

            parts["diagnosis"] = jsonable(diagnosis_json(mill, None, fit=parts["fit"]))
    except _Failed as f:
        status, failed_stage = "failed", f.stage
        error, kind = describe_error(f.stage, f.exc), type(f.exc).__name__
    return RecordingOutcome(
        status=status, error=error, error_kind=kind, stage=failed_stage,
        quality=tuple(jsonable(q) for q in quality), versions=library_versions(),
        started_at=started, elapsed_s=time.perf_counter() - t_start,
        worker=f"{socket.gethostname()}:{os.getpid()}", **parts)

