"""``ident fit REC --mill M [--family g1|g2|g3|g4] [--out F] [--quiet]``.

Reads the recording, finds its load-step transients (``ident.segment``), cuts
the fit windows around them and identifies every element's gap
(:func:`ident.fit.fit_recording`: :func:`ident.fit.fit_gaps`, CasADi direct
collocation by default).  The JSON is cli.md's ``fit`` document --
``mill``, ``family``, ``elements`` (every element of the mill file: ``gap``,
``gap_ci95``, ``gap_open``, ``gap_mm`` where the element gives a radius,
``params``), ``metrics`` (``nrmse``, ``nrmse_linear``) and ``solver``
(``status``, ``iterations``, ``seconds``) -- plus the extra keys of
:meth:`ident.fit.FitResult.to_dict` and ``recording``, ``windows_used`` and
``quality`` (the read's findings).

Exit codes
----------
0
    A result was written, whether or not every gap is identified (cli.md):
    each element carries ``identified`` and, when false, a one-line
    ``reason`` (:mod:`ident.fit.verdict`), and stderr gets one line per
    element saying the same, even with ``--quiet``.
1
    An internal failure (as for every subcommand).
2
    Bad input: unreadable recording, channels that contradict the mill file,
    no usable transient, bad option values -- one line on stderr naming the
    file, channel or key.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..errors import FitError
from ..fit import Collocation, SingleShooting, fit_recording
from ..io.readers import read_recording
from ..segment import segment_transients
from .common import add_common, load_mill_arg, parse_sets, write_json

#: --held choices -> fit_gaps(direct=...)
HELD = {"auto": "auto", "always": True, "never": False}


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit", help="identify gaps and smoothing parameters (CasADi collocation)",
        description="Identify every element's gap (total and open part) and the stiffness "
                    "family's smoothing parameters from the load-step transients of a "
                    "recording, by CasADi direct collocation solved with IPOPT (or single "
                    "shooting with --method shooting), with 95 % intervals.  Exit 0 whenever "
                    "the result is written: each element says whether it is identified, and "
                    "why not.")
    p.add_argument("recording", metavar="REC", help="recording (.mcap or .csv)")
    add_common(p)
    p.add_argument("--family", default="g1", choices=["g1", "g2", "g3", "g4"],
                   help="stiffness law (default g1: explicit gaps)")
    p.add_argument("--set", action="append", metavar="ID.KEY=VALUE",
                   help="override a mill-file value, e.g. C46.gap=0.006 (the start) "
                        "(repeatable)")
    p.add_argument("--method", default="collocation", choices=["collocation", "shooting"],
                   help="direct collocation (default) or single shooting")
    p.add_argument("--starts", type=int, default=1, metavar="N",
                   help="starts: the mill file's gaps, then N-1 random ones (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random starts")
    p.add_argument("--start-from", metavar="FIT.json", default=None,
                   help="start at the gaps of an earlier 'ident fit' JSON of this mill (e.g. "
                        "the last recording's) instead of the mill file's: gaps grow slowly, "
                        "and a start near them finds worn gaps the designed ones miss")
    p.add_argument("--model", metavar="MODEL", default=None,
                   help="a trained wear model of this mill ('ident train'; 'ident diagnose' "
                        "caches one): when the fit from the mill file's gaps fails its "
                        "check, restart from the gaps the model reads from the recording "
                        "(worn gaps that the designed ones lead astray; 'ident diagnose' "
                        "does this itself)")
    p.add_argument("--max-transients", type=int, default=None, metavar="N",
                   help="fit at most N transient windows (default: the fit's default, 4)")
    p.add_argument("--window-s", type=float, default=None, metavar="S",
                   help="length of each transient window, s (default 0.3)")
    p.add_argument("--max-iter", type=int, default=None, metavar="N",
                   help="solver iterations per continuation stage (IPOPT max_iter / "
                        "least_squares max_nfev)")
    p.add_argument("--held", choices=("auto", "always", "never"), default="auto",
                   help="also run each start's continuation with the gaps held at the start, "
                        "freed at the final width, and keep the better: 'auto' (default) only "
                        "when the continued fit stays above the noise floor, 'always' (e.g. "
                        "from the last identified gaps; about twice the time) or 'never'")
    p.add_argument("--nuisance", action=argparse.BooleanOptionalAction, default=True,
                   help="fit the plant nuisances with the gaps: per-window channel offsets, "
                        "drag torques spread over the shafts and the load ramps' shape "
                        "(default; --no-nuisance leaves them out)")
    p.add_argument("--ramp-polish", action=argparse.BooleanOptionalAction, default=True,
                   help="where a converged fit's residual fails the transient-band check, "
                        "one more solve lets the load ramps take linear, exponential and "
                        "S-shaped forms, kept where it fits better (default; "
                        "--no-ramp-polish is faster and identifies fewer gaps on plant "
                        "recordings)")
    p.add_argument("--time-budget", type=float, default=1800.0, metavar="S",
                   help="CPU seconds of the fit: after them no further start or path is "
                        "begun and a restart under way stops unfinished (default 1800; the "
                        "first start always runs to its end, each solver call bounded in "
                        "iterations and CPU time)")
    p.add_argument("--no-uncertainty", action="store_true",
                   help="skip standard errors and intervals (faster)")


def _method(args: argparse.Namespace) -> Collocation | SingleShooting:
    if args.max_iter is not None and args.max_iter < 1:
        raise FitError(f"--max-iter must be at least 1. Got {args.max_iter}.")
    if args.method == "shooting":
        return SingleShooting() if args.max_iter is None else SingleShooting(
            max_nfev=args.max_iter)
    polish = bool(getattr(args, "ramp_polish", True))
    return (Collocation(ramp_polish=polish) if args.max_iter is None
            else Collocation(max_iter=args.max_iter, ramp_polish=polish))


def _windows_kw(args: argparse.Namespace) -> dict[str, Any]:
    kw: dict[str, Any] = {}
    if args.max_transients is not None:
        if args.max_transients < 1:
            raise FitError(f"--max-transients must be at least 1. Got {args.max_transients}.")
        kw["max_windows"] = args.max_transients
    if args.window_s is not None:
        if not args.window_s > 0:
            raise FitError(f"--window-s must be positive. Got {args.window_s}.")
        kw["window_s"] = args.window_s
        kw["min_s"] = min(0.25, 0.5 * args.window_s)
    return kw


def start_from_fit(path: str, mill_name: str, element_ids: tuple[str, ...]) -> dict[str, float]:
    """The gaps of an earlier fit's JSON, as a start ``{element: gap}``.

    Raises
    ------
    FitError
        The file cannot be read, is not a fit of ``mill_name``, or lacks gaps.
    """
    import json
    import math

    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FitError(f"--start-from {path}: cannot read a fit JSON ({exc})") from None
    els = doc.get("elements") if isinstance(doc, dict) else None
    if not isinstance(els, dict):
        raise FitError(f"--start-from {path}: not an 'ident fit' JSON (no 'elements' object)")
    if doc.get("mill") not in (None, mill_name):
        raise FitError(f"--start-from {path}: a fit of mill {doc.get('mill')!r}, not "
                       f"{mill_name!r}")
    start = {}
    for eid, el in els.items():
        gap = el.get("gap") if isinstance(el, dict) else None
        if eid in element_ids and isinstance(gap, (int, float)) and math.isfinite(gap) \
                and gap >= 0:
            start[eid] = float(gap)
    if not start:
        raise FitError(f"--start-from {path}: no gap of the mill's elements "
                       f"{list(element_ids)} in it")
    return start


def run(args: argparse.Namespace) -> int:
    if args.starts < 1:
        raise FitError(f"--starts must be at least 1. Got {args.starts}.")
    if args.start_from is not None and args.starts > 1:
        raise FitError("--start-from gives the one start; drop --starts (or use --set for "
                       "more)")
    if not args.time_budget > 0:
        raise FitError(f"--time-budget must be positive. Got {args.time_budget}.")
    method = _method(args)
    wkw = _windows_kw(args)
    mill = load_mill_arg(args)
    starts = None
    if args.start_from is not None:  # checked before the (long) read
        over = {k.split(".")[0]: float(v) for k, v in parse_sets(args.set or []).items()
                if k.endswith(".gap") and isinstance(v, float)}  # --set wins
        starts = [{**start_from_fit(args.start_from, mill.name, mill.element_ids), **over}]
    wear_model = None
    if args.model is not None:  # checked before the (long) read
        from ..diagnose import load_model

        wear_model = load_model(args.model, mill)
    rec = read_recording(args.recording, mill, warn=False)  # findings go into the JSON
    segments = segment_transients(rec, mill)
    data_starts: tuple = ()
    if wear_model is not None and segments:
        from ..diagnose import diagnose_recording

        data_starts = (diagnose_recording(wear_model, rec, mill, segments,
                                          explain=False)[0].gap_start(),)

    def say(windows: Any) -> None:
        if not args.quiet:
            print(f"ident fit: {len(segments)} transients, fitting {len(windows)} windows of "
                  f"{windows[0].n_samples} samples ({method.name}, {args.family})",
                  file=sys.stderr)

    result, windows = fit_recording(  # ConvergenceWarning: reported below, once
        rec, mill, segments, windows=wkw, on_windows=say, family=args.family, method=method,
        n_starts=args.starts, random_state=args.seed, starts=starts, data_starts=data_starts,
        uncertainty=not args.no_uncertainty, direct=HELD[args.held],
        time_budget_s=args.time_budget, nuisance=args.nuisance, progress=not args.quiet)
    doc = result.to_dict()
    doc["recording"] = str(args.recording)
    doc["windows_used"] = [w.label for w in windows]
    doc["quality"] = [i.to_dict() for i in rec.issues]
    write_json(doc, args.out)
    if not args.quiet:
        for w in result.warnings:
            print(f"ident fit: warning: {w}", file=sys.stderr)
        print(f"ident fit: {result.solver.status} after {result.solver.iterations} iterations, "
              f"{result.solver.seconds:.1f} s; nrmse {result.nrmse:.4f} (linear "
              f"{result.nrmse_linear:.4f})", file=sys.stderr)
    for line in element_summary(result):  # the verdicts, even with --quiet
        print(f"ident fit: {line}", file=sys.stderr)
    return 0


def element_summary(result: Any) -> list[str]:
    """One line per element: its gap, interval and verdict (with the reason when not identified;
    a gap the fit bounds says so)."""
    out = []
    for eid, el in result.elements.items():
        lo, hi = el.gap_ci95
        head = f"{eid} gap {1e3 * el.gap:.2f} mrad [{1e3 * lo:.2f}, {1e3 * hi:.2f}]"
        out.append(f"{head} identified" if el.identified else
                   f"{head} bounded, not identified: {el.reason}" if el.bounded else
                   f"{head} not identified: {el.reason}")
    return out
