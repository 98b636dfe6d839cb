"""``ident segment REC --mill M``: the load-step transients found in a recording.

Prints (or writes to ``--out``) ``{"segments": [...]}`` with the cli.md keys
``t_start, t_step, t_end, kind, static_torque, step`` per segment (plus
``channel`` and ``rise_s``), and beside it ``recording``, ``mill``, ``channels``
and ``warnings`` (the quality findings of the read, as dicts).  Recordings longer
than ``--window-s`` (default 600 s) are read window by window
(:func:`ident.segment.segment_file`), so an hour needs no more memory than ten
minutes.
"""

from __future__ import annotations

import argparse
import sys

from ..segment import segment_file
from .common import add_common, load_mill_arg, write_json


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("segment", help="load-step transients (bites, releases) in a recording",
                       description="Find every bite and release in a recording (MCAP or CSV) "
                                   "and the window a fit should use for each.")
    p.add_argument("recording", metavar="REC", help="recording (.mcap or .csv)")
    add_common(p)
    p.add_argument("--window-s", type=float, default=600.0, metavar="S",
                   help="read recordings longer than this window by window (default 600 s)")


def run(args: argparse.Namespace) -> int:
    mill = load_mill_arg(args)
    found = segment_file(args.recording, mill, window_s=args.window_s,
                         overlap_s=min(30.0, args.window_s / 2))  # findings go into the JSON
    if not args.quiet:
        print(f"ident segment: {len(found.segments)} transients, {len(found.issues)} quality "
              f"findings", file=sys.stderr)
        for issue in found.issues:
            print(f"ident segment: warning: {issue}", file=sys.stderr)
    write_json({"recording": str(args.recording), "mill": mill.name,
                "channels": list(found.channels),
                "segments": [s.to_dict() for s in found.segments],
                "warnings": [i.to_dict() for i in found.issues]}, args.out)
    return 0
