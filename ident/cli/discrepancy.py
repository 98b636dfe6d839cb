"""``ident discrepancy REC --mill M``: what the model is missing, named, added and refitted.

Prints (or writes to ``--out``) cli.md's JSON ``{"effect", "location", "explained",
"before": {"nrmse"}, "after": {"nrmse"}, "candidates": [{"effect", "location",
"score"}, ...]}`` plus ``reason``, ``refits``, ``residuals``, ``rule``, ``windows``,
``folds``, ``recording`` and ``warnings``.  Plots (residuals before and after,
spectra, candidates, the worst window) go to ``--plots DIR``, by default beside
``--out`` as ``<stem>_residuals.png`` and so on; without ``--out`` and
``--plots`` none are drawn.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..discrepancy import DecisionRule, discrepancy
from ..discrepancy.plots import save_plots
from ..io.readers import read_recording
from .common import add_common, load_mill_arg, require_channels, write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("discrepancy", help="find, name and add the effect the model misses",
                       description="Fit the mill file's model, locate where it disagrees with "
                                   "the recording, rank every effect of effects.md at every "
                                   "location by its signature, add the leading ones, refit "
                                   "and name the one that explains the disagreement on bars "
                                   "the refit did not see, or answer null.")
    p.add_argument("recording", metavar="REC", help="recording (.mcap or .csv)")
    add_common(p)
    p.add_argument("--set", action="append", metavar="ID.KEY=VALUE",
                   help="override a mill-file value")
    p.add_argument("--plots", metavar="DIR",
                   help="directory of the PNG plots (default: beside --out)")
    p.add_argument("--no-plots", action="store_true", help="draw no plots")
    p.add_argument("--n-refit", type=int, default=3, metavar="N",
                   help="leading candidates to add and refit (default 3)")
    p.add_argument("--min-improvement", type=float, default=DecisionRule.min_improvement,
                   metavar="F", help="least held-out nrmse drop to name an effect "
                                     f"(default {DecisionRule.min_improvement})")


def run(args: argparse.Namespace) -> int:
    from ..errors import IdentError

    mill = load_mill_arg(args)
    if args.n_refit < 1:
        raise IdentError(f"--n-refit must be at least 1. Got {args.n_refit}.")
    if not 0.0 < args.min_improvement < 1.0:
        raise IdentError(f"--min-improvement must lie in (0, 1). Got {args.min_improvement}.")
    rec = read_recording(args.recording, mill, warn=False)
    require_channels(rec, mill, "discrepancy")

    def say(line: str) -> None:
        if not args.quiet:
            print(f"ident discrepancy: {line}", file=sys.stderr, flush=True)

    rule = DecisionRule(min_improvement=args.min_improvement)
    result = discrepancy(rec, mill, rule=rule, n_refit=args.n_refit, progress=say)
    data = result.to_dict()
    data["recording"] = str(args.recording)
    data["warnings"] = [i.to_dict() for i in rec.issues]
    plots_dir, prefix = None, ""
    if not args.no_plots:
        if args.plots:
            plots_dir = Path(args.plots)
        elif args.out:
            plots_dir = Path(args.out).parent
            prefix = Path(args.out).stem + "_"
    if plots_dir is not None:
        paths = save_plots(result, plots_dir, prefix=prefix)
        data["plots"] = [str(p) for p in paths]
        say(f"plots: {', '.join(str(p) for p in paths)}")
    write_json(data, args.out)
    return 0
