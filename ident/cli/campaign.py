"""``ident campaign DIR --mill M --store URL [--scheduler ADDR] [--workers N]``.

Diagnoses by default with the mill's cached wear model, training it on first use
(with progress; ``--no-diagnose`` skips the diagnosis, ``--model`` names one).

Exit codes: 0 every recording stored, 3 finished but some recordings are stored as
failed (this run or an earlier one), 2 bad input (mill file, folder, store URL,
scheduler), 1 internal failure.
"""

from __future__ import annotations

import argparse
import sys

from ..errors import IdentError
from .common import load_mill_arg, write_json

#: Exit code of a campaign that finished with failed recordings (cli.md).
EXIT_FAILED_RECORDINGS = 3


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "campaign", help="fit every recording under DIR into the results store",
        description="Discover the recordings (*.mcap, *.csv) under DIR, segment, fit and "
                    "diagnose each on worker processes (or a Dask cluster) and write the "
                    "results to the store, one transaction per recording. Resumable: a "
                    "recording stored with the same content and settings is skipped. Prints "
                    "a JSON summary; exits 3 when some recordings failed.")
    p.add_argument("dir", metavar="DIR", help="campaign folder (searched recursively)")
    p.add_argument("--mill", required=True, metavar="FILE", help="mill description (TOML)")
    p.add_argument("--store", default="sqlite:///results.db", metavar="URL",
                   help="SQLAlchemy URL of the results store (default sqlite:///results.db; "
                        "PostgreSQL: postgresql+psycopg://user@host/db)")
    p.add_argument("--scheduler", metavar="ADDR",
                   help="run on the Dask cluster of this scheduler (tcp://host:8786); the "
                        "recordings must be readable by its workers")
    p.add_argument("--workers", type=int, metavar="N",
                   help="local worker processes (default: all cores; 0 = in this process)")
    p.add_argument("--family", metavar="F", help="stiffness-law family of the fit (g1..g4)")
    p.add_argument("--per-transient", action="store_true",
                   help="also fit every transient on its own (costly)")
    p.add_argument("--max-transients", type=int, metavar="N",
                   help="fit at most N transients per recording")
    p.add_argument("--fit-budget", type=float, default=None, metavar="S",
                   help="CPU seconds of a recording's fit: after them it begins no further "
                        "start or path and a restart under way stops unfinished (default 600)")
    p.add_argument("--no-fit", action="store_true", help="skip the gap fit")
    p.add_argument("--no-diagnose", action="store_true", help="skip the wear diagnosis")
    p.add_argument("--model", metavar="MODEL",
                   help="trained wear model for the diagnosis (default: the mill's cached "
                        "model, trained on first use)")
    p.add_argument("--samples", type=int, default=300, metavar="N",
                   help="library size when the mill's model has to be trained first (300)")
    p.add_argument("--jobs", type=int, default=2, metavar="N",
                   help="simulation processes when the model has to be trained first (2)")
    p.add_argument("--no-refit", action="store_true",
                   help="no second pass refitting, from the nearest recording that identified "
                        "it, each recording whose fit left a gap unidentified")
    p.add_argument("--retry-failed", action="store_true",
                   help="process again the recordings stored as failed")
    p.add_argument("--memory-limit-mb", type=int, metavar="MB",
                   help="address-space limit per local worker process")
    p.add_argument("--min-age-s", type=float, default=0.0, metavar="S",
                   help="leave out files modified less than S seconds ago (still arriving)")
    p.add_argument("--out", metavar="FILE", help="write the JSON summary here instead of stdout")
    p.add_argument("--quiet", action="store_true", help="no progress output on stderr")


def run(args: argparse.Namespace) -> int:
    from ..store import Settings, run_campaign  # heavy: imported when the command runs
    from ..store.process import FIT_BUDGET_S

    mill = load_mill_arg(args)
    if args.samples < 10:
        raise IdentError(f"--samples must be at least 10. Got {args.samples}")
    if args.jobs < 1:
        raise IdentError(f"--jobs must be at least 1. Got {args.jobs}")
    budget = FIT_BUDGET_S if args.fit_budget is None else args.fit_budget  # Settings checks it
    settings = Settings(family=args.family, fit=not args.no_fit,
                        per_transient=args.per_transient, max_transients=args.max_transients,
                        diagnose=not args.no_diagnose, model=args.model, fit_budget_s=budget)
    summary = run_campaign(args.dir, mill, args.store, workers=args.workers,
                           scheduler=args.scheduler, settings=settings,
                           progress=not args.quiet, retry_failed=args.retry_failed,
                           memory_limit_mb=args.memory_limit_mb, min_age_s=args.min_age_s,
                           train=True, train_samples=args.samples, train_jobs=args.jobs,
                           refit=not args.no_refit)
    write_json(summary.to_dict(), args.out)
    if not args.quiet:
        print(f"ident campaign: {summary.n_found} recordings: {summary.n_done} stored, "
              f"{summary.n_failed} failed, {summary.n_skipped} already stored, "
              f"{summary.n_refit} refitted from a neighbour "
              f"({summary.elapsed_s:.1f} s, {summary.executor}) -> {summary.store}",
              file=sys.stderr)
        for name, err in summary.failed[:20]:
            print(f"  failed: {name}: {err}", file=sys.stderr)
        if len(summary.failed) > 20:
            print(f"  ... and {len(summary.failed) - 20} more failed", file=sys.stderr)
    return EXIT_FAILED_RECORDINGS if summary.failed else 0
