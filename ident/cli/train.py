"""``ident train --mill M --out MODEL [--samples N] [--seed N] [--jobs N] [--quiet]``."""

from __future__ import annotations

import argparse
import sys
import time

from ..diagnose import save_model, simulate_library, train_model
from ..errors import IdentError
from .common import load_mill_arg, write_json

#: library size of ``ident train`` (a few minutes on two cores)
DEFAULT_SAMPLES = 300


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="train the wear classifier of a mill on a simulated library",
        description="Simulate a library of recordings over random gaps, open parts, bearing "
                    "clearances, static torques, noise and stiffness/damping variation from "
                    "the mill file, extract the transient features and train the per-element "
                    "and per-bearing classifiers and regressors.  The artefact records the "
                    "mill file's SHA-256 and the library versions.")
    p.add_argument("--mill", required=True, metavar="FILE", help="mill description (TOML)")
    p.add_argument("--out", required=True, metavar="MODEL", help="model artefact to write (joblib)")
    p.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, metavar="N",
                   help=f"simulated recordings in the library (default {DEFAULT_SAMPLES})")
    p.add_argument("--seed", type=int, default=0, help="random seed of the library and the trees")
    p.add_argument("--jobs", type=int, default=2, metavar="N",
                   help="worker processes for the simulation (default 2)")
    p.add_argument("--no-bearings", action="store_true",
                   help="torque channels only (no bearing classifiers)")
    p.add_argument("--quiet", action="store_true", help="no progress output on stderr")


def train_and_save(mill, out, *, samples: int, seed: int, jobs: int, bearings: bool,
                   quiet: bool) -> dict:
    """Simulate the library, train, save; return a JSON-able summary."""
    if samples < 10:
        raise IdentError(f"--samples must be at least 10. Got {samples}")
    if jobs < 1:
        raise IdentError(f"--jobs must be at least 1. Got {jobs}")
    t0 = time.perf_counter()
    lib = simulate_library(mill, n=samples, random_state=seed, n_jobs=jobs, progress=not quiet,
                           bearings=bearings)
    t1 = time.perf_counter()

    def progress(tid: str) -> None:
        if not quiet:
            print(f"ident train: fitting {tid}", file=sys.stderr)

    model = train_model(lib, mill, random_state=seed, progress=progress)
    path = save_model(model, out)
    t2 = time.perf_counter()
    if not quiet:
        print(f"ident train: wrote {path} ({samples} recordings simulated in {t1 - t0:.0f} s, "
              f"trained in {t2 - t1:.0f} s)", file=sys.stderr)
    return {"model": str(path), "mill": mill.name, "mill_hash": mill.content_hash(),
            "samples": samples, "seed": seed, "versions": model.versions,
            "elements": list(model.element_ids), "bearings": list(model.bearing_ids),
            "alarms": {tid: tm.alarm for tid, tm in model.targets.items()},
            "seconds": {"simulate": t1 - t0, "train": t2 - t1}}


def run(args: argparse.Namespace) -> int:
    mill = load_mill_arg(args)
    summary = train_and_save(mill, args.out, samples=args.samples, seed=args.seed, jobs=args.jobs,
                             bearings=not args.no_bearings, quiet=args.quiet)
    write_json(summary, None)
    return 0
