"""``ident diagnose REC --mill M [--model MODEL] [--out F] [--quiet]``.

Reads the recording, finds its load-step transients (``ident.segment``),
extracts the natural-frequency amplitudes and phases against the linear
baseline and the other transient features (``ident.features``) and applies
the mill's trained model (``ident.diagnose``); with ``--fit FIT.json`` an element
whose gap that fit identified takes its state from the gap
(:mod:`ident.diagnose.verdict`, as the campaign does).  Without ``--model`` it uses the
cached model of that mill file (``$IDENT_CACHE/models/<sha256>.joblib``),
training it on first use.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..diagnose import (DiagnosticModel, diagnose_features, diagnosis_json, load_model,
                        model_cache_path)
from ..errors import IdentError, ModelArtifactError
from ..features import feature_summary, recording_features, transient_features
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
    p.add_argument("--fit", metavar="FIT.json",
                   help="the recording's fit (ident fit --out): an element whose gap it "
                        "identified takes its state from that gap (source 'fit')")
    p.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, metavar="N",
                   help="library size when a model has to be trained first")
    p.add_argument("--jobs", type=int, default=2, metavar="N",
                   help="worker processes when a model has to be trained first")


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
    tf = transient_features(rec, mill, [s.t_step for s in segments], options=model.options)
    if len(tf.table) == 0:
        raise IdentError(f"{rec_path}: the load steps found are too close together or too "
                         f"close to the recording's ends to analyse")
    fv = recording_features(tf)
    diag = diagnose_features(model, fv)
    out = {"mill": mill.name, "recording": str(rec_path)}
    out.update(diagnosis_json(mill, diag, fit=fit, features=feature_summary(tf, mill=mill),
                              warnings=[i.message for i in rec.issues]))
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
