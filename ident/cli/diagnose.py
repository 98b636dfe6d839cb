"""``ident diagnose REC --mill M [--model MODEL] [--fit FIT.json | --no-fit] [--out F] [--quiet]``.

Reads the recording, finds its load-step transients (``ident.segment``),
extracts the natural-frequency amplitudes and phases against the linear
baseline and the other transient features (``ident.features``) and applies
the mill's trained model (``ident.diagnose``).  An element whose gap the
recording's fit identified (or bounded: an interval the fit trusts, wider than an
identified gap's) takes its state from that gap and interval, the most accurate
evidence (:mod:`ident.diagnose.verdict`, as the campaign does).  The fit is the
one given by ``--fit FIT.json`` (``ident fit --out``); without it, diagnose runs
the fit itself as ``ident fit`` would (bounded by ``--fit-budget``, default the
campaign's, ``store.process.FIT_BUDGET_S``);
``--no-fit`` leaves the states to the trained model (seconds instead of minutes).
A fit that cannot run (a torque channel the fit needs is missing, no usable
window) is one warning, and the model decides.  Without ``--model`` it uses the
cached model of that mill (``$IDENT_CACHE/models/<hash>.joblib``, keyed by the
parsed mill description), training it on first use.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..diagnose import (DiagnosticModel, diagnose_recording, diagnosis_json, load_model,
                        model_cache_path)
from ..errors import IdentError, ModelArtifactError
from ..features import feature_summary
from .common import add_common, load_mill_arg, require_channels, write_json
from .train import DEFAULT_SAMPLES, train_and_save


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "diagnose", help="wear state per element and bearing",
        description="Wear state (good/worn/critical) per element and bearing from the "
                    "natural-frequency amplitudes and phases of the load-step transients "
                    "against the linear baseline, TAF against static torque and the "
                    "bearings' accelerometers.  Without --model the mill's cached model is "
                    "used, trained on first use.")
    p.add_argument("recording", metavar="REC", help="recording (.mcap or .csv)")
    add_common(p)
    p.add_argument("--model", metavar="MODEL", help="trained model artefact (ident train)")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--fit", metavar="FIT.json",
                     help="the recording's fit (ident fit --out): an element whose gap it "
                          "identified or bounded takes its state from that gap and its "
                          "interval (source 'fit'); "
                          "without it the fit is run here")
    how.add_argument("--no-fit", action="store_true",
                     help="do not run the fit: the trained model decides every state "
                          "(seconds instead of minutes; less accurate for worn gaps)")
    p.add_argument("--fit-budget", type=float, default=None, metavar="S",
                   help="CPU seconds of the fit run here: after them it begins no further "
                        "start or path and a restart under way stops unfinished (default: "
                        "the campaign's, 600)")
    p.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, metavar="N",
                   help="library size when a model has to be trained first")
    p.add_argument("--jobs", type=int, default=2, metavar="N",
                   help="worker processes when a model has to be trained first")


def run_fit(rec: Any, mill: Any, segments: Any, *, budget_s: float,
            data_starts: Sequence[Mapping[str, float]] = (), progress: bool = False
            ) -> tuple[dict[str, Any] | None, str | None]:
    """The recording's fit as ``ident fit`` runs it, for the verdicts.

    Parameters
    ----------
    rec : Recording
    mill : Mill
    segments : sequence of Segment
        The recording's load-step transients.
    budget_s : float
        The fit's time budget (``fit_gaps(time_budget_s=...)``).
    data_starts : sequence of dict
        Gaps to restart from where the mill file's lead astray
        (``fit_gaps(data_starts=...)``): the trained model's.
    progress : bool
        Show the fit's progress bar.

    Returns
    -------
    fit : dict or None
        cli.md ``fit`` JSON (:meth:`ident.fit.FitResult.to_dict`), or None when the
        fit could not run.
    why : str or None
        Why not, in one line (a missing torque channel, no usable window).
    """
    try:
        from ..fit import fit_recording
    except ImportError as exc:  # the fit's optional dependencies (CasADi) are missing
        return None, f"the fit stage is not installed ({exc})"
    try:
        result, _ = fit_recording(rec, mill, segments, time_budget_s=budget_s,
                                  data_starts=tuple(data_starts), progress=progress)
    except IdentError as exc:
        return None, str(exc)
    return result.to_dict(), None


def _cached_model(args: argparse.Namespace, mill: Any) -> tuple[DiagnosticModel, str]:
    """The mill's cached model, trained first when there is none (or it is unusable)."""
    path = model_cache_path(mill)
    if path.exists():
        try:
            return load_model(path, mill), str(path)
        except ModelArtifactError as exc:
            if not args.quiet:
                print(f"ident diagnose: cached model unusable ({exc}); retraining",
                      file=sys.stderr)
    if not args.quiet:
        print(f"ident diagnose: no model for mill '{mill.name}' yet; training one on "
              f"{args.samples} simulated recordings (cached in {path})", file=sys.stderr)
    train_and_save(mill, path, samples=args.samples, seed=0, jobs=args.jobs, bearings=True,
                   quiet=args.quiet)
    return load_model(path, mill), str(path)


def read_fit(path: str | Path, mill: Any) -> dict[str, Any]:
    """A cli.md ``fit`` JSON (``ident fit --out``) of ``mill``, for the verdicts.

    Raises
    ------
    IdentError
        The file is missing, not JSON, not a fit result or of another mill.
    """
    import json

    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise IdentError(f"fit result not found: {p}") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise IdentError(f"{p}: not a fit result (JSON of 'ident fit'): {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("elements"), dict):
        raise IdentError(f"{p}: not a fit result: it needs an 'elements' object "
                         f"(the JSON of 'ident fit')")
    if doc.get("mill") not in (None, mill.name):
        raise IdentError(f"{p}: the fit is of mill '{doc['mill']}', not of '{mill.name}'")
    return doc


def run(args: argparse.Namespace) -> int:
    from ..io.readers import read_recording
    from ..segment import segment_transients

    budget = args.fit_budget
    if budget is None:
        from ..store.process import FIT_BUDGET_S  # the campaign's (store.Settings)

        budget = FIT_BUDGET_S
    if not budget > 0:
        raise IdentError(f"--fit-budget must be positive. Got {budget}.")
    mill = load_mill_arg(args)
    rec_path = Path(args.recording)
    fit = read_fit(args.fit, mill) if args.fit else None
    rec = read_recording(rec_path, mill, warn=False)  # findings go into the JSON's warnings
    # a given model is loaded (cheap) before anything else; without one, the mill's model
    # (cached, or trained below) diagnoses every bearing
    given = load_model(args.model, mill) if args.model else None
    require_channels(rec, mill, "diagnose",
                     bearings=None if given is None else given.bearing_ids)
    segments = segment_transients(rec, mill)
    if not segments:
        raise IdentError(f"{rec_path}: no load-step transient (bite or release) found; "
                         f"diagnosis needs at least one bar")
    model, model_path = (given, str(args.model)) if given is not None else \
        _cached_model(args, mill)
    diag, tf = diagnose_recording(model, rec, mill, segments)
    notes = [i.message for i in rec.issues]
    fit_info: dict[str, Any] = {"source": "file", "path": str(args.fit)} if fit else \
        {"source": None}
    if fit is None and not args.no_fit:
        if not args.quiet:
            print(f"ident diagnose: fitting the gaps (up to {budget:g} s; --no-fit "
                  f"skips)", file=sys.stderr)
        fit, why = run_fit(rec, mill, segments, budget_s=budget,
                           data_starts=[diag.gap_start()], progress=not args.quiet)
        if fit is None:
            notes.append(f"the fit did not run ({why}); the trained model decides every "
                         f"state")
            if not args.quiet:
                print(f"ident diagnose: warning: {notes[-1]}", file=sys.stderr)
        else:
            fit_info = {"source": "run", "seconds": fit["solver"]["seconds"]}
    if fit is not None:
        fit_info["identified"] = [k for k, v in fit["elements"].items()
                                  if v.get("identified")]
        # the fit's evidence on every element, the gaps it did not identify too
        fit_info["elements"] = {k: {"gap": v.get("gap"), "gap_ci95": v.get("gap_ci95"),
                                    "identified": bool(v.get("identified")),
                                    "bounded": bool(v.get("bounded")),
                                    **({"reason": v["reason"]} if v.get("reason") else {})}
                                for k, v in fit["elements"].items()}
        fit_info["solver_path"] = fit.get("solver", {}).get("path")  # the run that won
    out = {"mill": mill.name, "recording": str(rec_path)}
    out.update(diagnosis_json(mill, diag, fit=fit, features=feature_summary(tf, mill=mill),
                              warnings=notes))
    out["fit"] = fit_info
    out["uncertain"] = any(v["uncertain"] for v in (*out["elements"].values(),
                                                     *out["bearings"].values()))
    out["transients"] = {"bites": int((tf.table["kind"] == "bite").sum()),
                         "releases": int((tf.table["kind"] == "release").sum())}
    out["model"] = {"path": model_path, "samples": model.n_samples,
                    "mill_hash": model.mill_hash, "versions": model.versions}
    write_json(out, args.out)
    if not args.quiet:
        states = ", ".join(f"{k}={v['state']}" + (" (fit)" if v["source"] == "fit" else "")
                           for k, v in out["elements"].items())
        print(f"ident diagnose: {rec_path.name}: {states}", file=sys.stderr)
    return 0
