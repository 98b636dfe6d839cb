"""``ident simulate --mill M --out REC [--bars N] [--set ID.KEY=VALUE ...] [--seed N]``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..errors import IdentError
from ..model.scenario import random_scenario
from ..model.simulate import DEFAULT_T0_NS, sensor_devices, simulate
from .common import load_mill_arg, parse_sets, to_jsonable


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate", help="write a synthetic recording of N rolled bars",
        description="Simulate the nonlinear driveline through N bars (bite and release) and "
                    "write what the telemetry would record, with sensor noise and 16-bit "
                    "quantisation: .mcap or .csv by the --out extension.")
    p.add_argument("--mill", required=True, metavar="FILE", help="mill description (TOML)")
    p.add_argument("--out", required=True, metavar="REC", help="recording to write (.mcap/.csv)")
    p.add_argument("--bars", type=int, default=3, metavar="N", help="bars to roll (default 3)")
    p.add_argument("--set", action="append", metavar="ID.KEY=VALUE",
                   help="override a mill-file value, e.g. C46.gap=0.006 (repeatable)")
    p.add_argument("--seed", type=int, default=0, help="random seed (scenario and noise)")
    p.add_argument("--snr-db", type=float, default=35.0, help="sensor SNR in dB (default 35)")
    p.add_argument("--encoding", choices=["protobuf", "json"], default="protobuf",
                   help="MCAP message encoding (default protobuf)")
    p.add_argument("--no-bearings", action="store_true",
                   help="torque channels only (skip the bearings' radial model)")
    p.add_argument("--truth", metavar="FILE",
                   help="also write the simulation truth (bars, gaps, TAF) as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress output on stderr")


def run(args: argparse.Namespace) -> int:
    from ..io.writers import write_recording
    from ..model.dynamics import ModelOptions
    from ..model.simulate import taf_table

    if args.bars < 1:
        raise IdentError(f"--bars must be at least 1. Got {args.bars}")
    out = Path(args.out)
    if out.suffix.lower() not in (".mcap", ".csv"):
        raise IdentError(f"--out must end in .mcap or .csv. Got {str(out)!r}")
    mill = load_mill_arg(args)
    rng = np.random.default_rng(args.seed)
    scenario = random_scenario(mill, n_bars=args.bars, rng=rng)
    bearings = bool(mill.bearings) and not args.no_bearings and bool(mill.acceleration_channels())
    result = simulate(mill, scenario, options=ModelOptions(bearings=bearings))
    devices = sensor_devices(result, rng=rng, snr_db=args.snr_db,
                             t0_ns=DEFAULT_T0_NS + args.seed * 10**12)
    mill_text = Path(args.mill).read_text(encoding="utf-8")
    write_recording(out, devices, encoding=args.encoding,
                    metadata={"mill": mill.name, "recording_id": out.stem,
                              "campaign": "simulated", "stand": mill.name},
                    mill_toml=mill_text)
    if args.truth:
        taf = taf_table(result)
        truth = {
            "mill": mill.name, "seed": args.seed, "overrides": parse_sets(args.set or []),
            "elements": {e.id: {"gap": e.gap, "gap_open": e.gap_open} for e in mill.elements},
            "bars": [{"t_bite": b.t_bite, "t_step_bite": b.t_step_bite,
                      "t_release": b.t_release, "t_step_release": b.t_step_release,
                      "static_torque": b.static_torque, "rise_time": b.rise_time,
                      "fall_time": b.fall_time} for b in scenario.bars],
            "taf": taf.to_dict(orient="records"),
        }
        Path(args.truth).write_text(json.dumps(to_jsonable(truth), indent=2))
    if not args.quiet:
        import sys
        print(f"ident simulate: wrote {out} ({args.bars} bars, {scenario.duration:.1f} s)",
              file=sys.stderr)
    return 0
