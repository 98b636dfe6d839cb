"""The daily job: fit what arrived since yesterday into the store, then rewrite the report.

    python -m pipelines.daily --incoming DIR --mill FILE --store URL --report FILE
                              [--archive DIR] [--workers N | --scheduler ADDR] [--lock FILE]

Incremental by construction: ``ident campaign`` skips every recording the store
already holds with the same content and settings, so a day's run processes only the
new files (and a run that crashed or was killed resumes where it stopped).  The
report is rebuilt from the whole store and written atomically, so readers never see
half a file; with ``--archive`` a dated copy is kept too.  A lock file keeps two runs
from overlapping (a run that finds it taken exits 0 and says so).

Exit code: 0 all recordings stored, 3 some recordings are stored as failed (the
report lists them), 2 bad input (mill file, folder, store URL), 1 internal error.
The report is written whenever the store can be read, also after a failed campaign.
See pipelines/README.md for the cron line and the systemd timer.
"""

from __future__ import annotations

import argparse
import datetime as dt
import fcntl
import shutil
import sys
from pathlib import Path

from ident.cli import main as ident_main


def _log(msg: str) -> None:
    print(f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%dT%H:%M:%SZ} ident-daily: {msg}",
          file=sys.stderr, flush=True)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m pipelines.daily", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--incoming", required=True, help="campaign folder the telemetry lands in")
    p.add_argument("--mill", required=True, help="mill file (TOML)")
    p.add_argument("--store", required=True, help="SQLAlchemy URL of the results store")
    p.add_argument("--report", required=True, help="HTML report to (re)write")
    p.add_argument("--archive", help="also keep report-YYYY-MM-DD.html in this folder")
    p.add_argument("--workers", type=int, help="local worker processes (default all cores)")
    p.add_argument("--scheduler", help="Dask scheduler address instead of local workers")
    p.add_argument("--lock", help="lock file (default: REPORT.lock)")
    p.add_argument("--min-age-s", type=float, default=120.0,
                   help="leave files younger than this for the next run (still being copied "
                        "in); default 120 s")
    p.add_argument("--no-fit", action="store_true",
                   help="skip the gap fit (segments, TAF and the diagnosis only)")
    p.add_argument("--no-diagnose", action="store_true", help="skip the wear diagnosis")
    p.add_argument("--max-transients", type=int, metavar="N",
                   help="fit at most N transients per recording")
    p.add_argument("--progress", action="store_true", help="progress bar (off for cron)")
    return p.parse_args(argv)


def run(argv: list[str] | None = None) -> int:
    """One daily run; returns the exit code."""
    args = parse_args(argv)
    report = Path(args.report)
    report.parent.mkdir(parents=True, exist_ok=True)
    lock_path = Path(args.lock) if args.lock else report.with_name(report.name + ".lock")
    with open(lock_path, "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            _log(f"another run holds {lock_path}; nothing to do")
            return 0
        quiet = [] if args.progress else ["--quiet"]
        opts = ["--min-age-s", str(args.min_age_s)] + \
            (["--workers", str(args.workers)] if args.workers is not None else []) + \
            (["--scheduler", args.scheduler] if args.scheduler else []) + \
            (["--no-fit"] if args.no_fit else []) + \
            (["--no-diagnose"] if args.no_diagnose else []) + \
            (["--max-transients", str(args.max_transients)]
             if args.max_transients is not None else [])
        _log(f"campaign {args.incoming} -> {args.store}")
        code = ident_main(["campaign", args.incoming, "--mill", args.mill, "--store",
                           args.store, "--out", str(report.with_suffix(".campaign.json")),
                           *opts, *quiet])
        _log(f"campaign exit code {code}")
        rcode = ident_main(["report", "--store", args.store, "--out", str(report),
                            "--mill", args.mill])
        if rcode != 0:
            _log(f"report failed with exit code {rcode}")
            return rcode if code in (0, 3) else code
        if args.archive:
            dest = Path(args.archive)
            dest.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(report, dest / f"report-{dt.date.today():%Y-%m-%d}.html")
        _log(f"report written: {report.resolve()}")
        return code


if __name__ == "__main__":
    sys.exit(run())
