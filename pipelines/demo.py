"""The main job: simulate a small rolling campaign, fit it into a results store, write the report.

    .venv/bin/python -m pipelines.demo            (what ``make demo`` runs)

1. simulates ``--recordings`` recordings of the shipped stand (data/mills/hsm-f1.toml)
   spread over ``--days`` days, the spindle gaps and a bearing clearance growing, plus
   deliberately malformed files, into ``out/demo/recordings`` (kept between runs);
2. ``ident campaign out/demo/recordings --mill ... --store sqlite:///out/demo/results.db``
   (a rerun skips what is stored; the malformed files are stored as failed, exit 3);
3. ``ident report --store ... --out out/demo/report.html`` and prints where it is.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from ident import load_mill
from ident.cli import main as ident_main
from ident.store import make_sample_campaign

REPO = Path(__file__).resolve().parents[1]
MILL = REPO / "data" / "mills" / "hsm-f1.toml"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m pipelines.demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO / "out" / "demo"), help="output folder")
    p.add_argument("--mill", default=str(MILL), help="mill file")
    p.add_argument("--recordings", type=int, default=8, help="recordings to simulate (8)")
    p.add_argument("--bars", type=int, default=2, help="bars per recording (2)")
    p.add_argument("--days", type=float, default=28.0, help="campaign span, days (28)")
    p.add_argument("--workers", type=int, help="worker processes (default: all cores)")
    p.add_argument("--fresh", action="store_true",
                   help="delete earlier recordings, store and report first")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p.parse_args(argv)


def run(argv: list[str] | None = None) -> int:
    """Run the demo; returns 0 when the report was written."""
    args = parse_args(argv)
    out = Path(args.out)
    recordings, db, report = out / "recordings", out / "results.db", out / "report.html"
    if args.fresh and out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    mill = load_mill(args.mill)
    if not any(recordings.rglob("*.mcap")):
        print(f"demo: simulating {args.recordings} recordings over {args.days:g} days "
              f"into {recordings} ...", file=sys.stderr)
        sample = make_sample_campaign(recordings, mill, n_recordings=args.recordings,
                                      bars=args.bars, days=args.days, n_bad=2,
                                      mill_text=Path(args.mill).read_text(encoding="utf-8"))
        print(f"demo: {len(sample.good)} recordings and {len(sample.bad)} malformed files "
              f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    else:
        print(f"demo: reusing the recordings in {recordings} (--fresh to simulate anew)",
              file=sys.stderr)
    store = f"sqlite:///{db}"
    common = ["--mill", args.mill] + (["--quiet"] if args.quiet else [])
    workers = [] if args.workers is None else ["--workers", str(args.workers)]
    code = ident_main(["campaign", str(recordings), "--store", store, "--out",
                       str(out / "campaign.json"), *workers, *common])
    if code not in (0, 3):  # 3: the malformed files are stored as failed, as intended
        print(f"demo: ident campaign failed with exit code {code}", file=sys.stderr)
        return code
    code = ident_main(["report", "--store", store, "--out", str(report)] +
                      (["--quiet"] if args.quiet else []))
    if code != 0:
        return code
    print(f"demo: done in {time.perf_counter() - t0:.1f} s")
    print(f"Report: {report.resolve()}")
    print(f"Store:  {store}   (campaign summary: {out / 'campaign.json'})")
    return 0


if __name__ == "__main__":
    sys.exit(run())
