"""Regenerate the tiny sample campaign shipped in ``data/samples/`` (about 0.5 MB).

    .venv/bin/python -m pipelines.sample_data      (what ``make sample-data`` runs)

Four torque-only MCAP recordings of the shipped stand, one bar each, a week apart,
with the spindle gaps growing, and two malformed files (a truncated MCAP and a
garbage CSV) under ``incoming/``.  Deterministic (seeded).  Try it with::

    .venv/bin/ident campaign data/samples/hsm-f1 --mill data/mills/hsm-f1.toml \\
        --store sqlite:///out/sample.db
    .venv/bin/ident report --store sqlite:///out/sample.db --out out/sample.html
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from ident import load_mill
from ident.store import make_sample_campaign

REPO = Path(__file__).resolve().parents[1]


def run(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pipelines.sample_data", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO / "data" / "samples" / "hsm-f1"))
    p.add_argument("--mill", default=str(REPO / "data" / "mills" / "hsm-f1.toml"))
    args = p.parse_args(argv)
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    s = make_sample_campaign(out, load_mill(args.mill), n_recordings=4, bars=1, days=21.0,
                             bearings=False, csv_every=0, n_bad=2, seed=2026)
    (out / "TRUTH.json").write_text(json.dumps(
        {k: {"t0_ns": v["t0_ns"], "values": v["values"]} for k, v in s.truth.items()},
        indent=1) + "\n")
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"sample_data: wrote {len(s.good)} recordings + {len(s.bad)} malformed files to "
          f"{out} ({size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(run())
