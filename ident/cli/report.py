"""``ident report --store URL --out report.html [--json status.json] [--mill FILE]``.

The wear trend report, and with ``--json`` each element's and bearing's status for
plant systems (cli.md ``report --json``).
"""

from __future__ import annotations

import argparse
import sys

from ..io.millfile import load_mill


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report", help="wear trend report (one self-contained HTML file) of a results store",
        description="Read the results store and write one HTML file (plots embedded) with, "
                    "per mill, a traffic-light summary, gap trends with worn/critical limits "
                    "and forecasts, TAF against static torque (seed Fig. 4), natural-frequency "
                    "amplitude and phase trends, bearing clearance trends, a data-quality "
                    "summary and the failed recordings.")
    p.add_argument("--store", default="sqlite:///results.db", metavar="URL",
                   help="SQLAlchemy URL of the results store (default sqlite:///results.db)")
    p.add_argument("--out", required=True, metavar="FILE", help="HTML file to write")
    p.add_argument("--json", metavar="FILE", dest="json_out",
                   help="also write each element's and bearing's status as JSON (status, now "
                        "with its 95 %% band, worn_at/critical_at with intervals, days left, "
                        "last recording, identified/total counts)")
    p.add_argument("--stale-days", type=float, default=14.0, metavar="D",
                   help="flag data older than D days as stale (default 14)")
    p.add_argument("--mill", metavar="FILE",
                   help="report only this mill, with this file's limits (default: every "
                        "mill in the store, limits from the mill files stored with them)")
    p.add_argument("--horizon-days", type=float, default=30.0, metavar="D",
                   help="look-ahead of the amber status, days (default 30)")
    p.add_argument("--title", default="Driveline wear trend report", help="page title")
    p.add_argument("--quiet", action="store_true", help="no output on stderr")


def run(args: argparse.Namespace) -> int:
    from ..report import build_report  # matplotlib: imported when the command runs

    mill = load_mill(args.mill) if args.mill else None
    r = build_report(args.store, args.out, mill=mill, horizon_days=args.horizon_days,
                     title=args.title, json_out=args.json_out, stale_days=args.stale_days)
    if not args.quiet:
        worst = [f"{m}/{a.id} {a.status}" for m, a in r.assessments
                 if a.status in ("worn", "critical")]
        also = f" and {r.json_path}" if r.json_path is not None else ""
        print(f"ident report: wrote {r.path}{also} ({len(r.mills)} mill(s), {r.n_recordings} "
              f"recordings, {r.n_failed} failed; {', '.join(worst) or 'nothing worn'}; "
              f"{r.elapsed_s:.1f} s)", file=sys.stderr)
    return 0
